"""Property-based run of every operation in /openapi.json against the live server
(Schemathesis' Python API driving Hypothesis): for valid and for invalid inputs, no 5xx, and
every response has a documented status code, content type and headers and conforms to its
schema.

(Schemathesis' own pytest plugin does not run under pytest 9, so each operation is one
parametrized test here, with its cases drawn from ``operation.as_strategy``.)
"""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from ra2vipas.services.orchestrator.api.app import create_app
from ra2vipas.services.orchestrator.api.schemas import CampaignProgress
from ra2vipas.services.orchestrator.settings import OrchestratorSettings
from tests.api.live import SMALL, LiveAPI

CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_headers_conformance,
          response_schema_conformance]
EXAMPLES = 20

OPERATIONS = [(method.upper(), path) for path, item in create_app(OrchestratorSettings()).openapi()["paths"].items()
              for method in item]


@pytest.fixture(scope="module")
def fuzz_db(tmp_path_factory):
    """A database holding one finished campaign (run on a full in-memory mesh first)."""
    path = tmp_path_factory.mktemp("schemathesis") / "fuzz.db"
    mesh = LiveAPI(path).start()
    try:
        with mesh.client() as http:
            cid = http.post("/campaigns", json={"overrides": SMALL, "algorithms": ["ra2vipas", "sweep"], "tests": 2}).json()["id"]
        assert mesh.wait(cid)["status"] == "done"
    finally:
        mesh.stop()
    return path, cid


@pytest.fixture(scope="module")
def bare_api(fuzz_db):
    """The API on that database without rigs or a learner: campaigns created by the run wait
    for a learner and never run, so they cost nothing but rows."""
    server = LiveAPI(fuzz_db[0], rigs=(), learner=False).start()
    yield server
    server.stop()


@pytest.fixture(scope="module")
def api_schema(bare_api):
    return schemathesis.openapi.from_url(f"{bare_api.url}/openapi.json")


def test_the_run_covers_every_operation_of_the_served_schema(api_schema):
    served = {(op.ok().method.upper(), op.ok().path) for op in api_schema.get_all_operations()}
    assert served == set(OPERATIONS) and len(served) >= 16


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE], ids=["valid", "invalid"])
@pytest.mark.parametrize("method, path", OPERATIONS, ids=[f"{m} {p}" for m, p in OPERATIONS])
def test_operation_conforms_to_its_schema(api_schema, bare_api, method, path, mode):
    operation = api_schema[path][method]
    # /health answers 503 by design while the mesh is not ready (this server has no rigs): a
    # documented status, so only that operation skips the "no 5xx" check.
    checks = [c for c in CHECKS if c is not not_a_server_error] if path == "/health" else CHECKS

    @given(case=operation.as_strategy(generation_mode=mode))
    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    def run(case):
        response = case.call_and_validate(base_url=bare_api.url, checks=checks, timeout=30)
        if path == "/health":
            assert response.status_code in (200, 503)

    try:
        run()
    except Unsatisfiable:
        # e.g. GET /rigs or GET /presets/{name}: no input of this operation can be invalid
        assert mode is GenerationMode.NEGATIVE


READS_OF_A_CAMPAIGN = [(m, p) for m, p in OPERATIONS if "{campaign_id}" in p and m == "GET"]


@pytest.mark.parametrize("method, path", READS_OF_A_CAMPAIGN, ids=[f"{m} {p}" for m, p in READS_OF_A_CAMPAIGN])
def test_reads_of_a_finished_campaign_conform_to_their_schema(api_schema, bare_api, fuzz_db, method, path):
    """The same checks with the path naming the finished campaign (and its test 1), so the
    200 responses (results as JSON and CSV, outcome pages, traces, figures, the event
    stream) are validated, not only the 404s."""
    operation = api_schema[path][method]
    fixed = {"campaign_id": fuzz_db[1], **({"test_index": 1} if "{test_index}" in path else {}),
             # a policy name is any name matching the pattern (protocol 1.2): name one the campaign ran
             **({"algorithm": "sweep"} if "{algorithm}" in path else {})}
    statuses = set()

    @given(case=operation.as_strategy(generation_mode=GenerationMode.POSITIVE, path_parameters=fixed))
    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
    def run(case):
        response = case.call_and_validate(base_url=bare_api.url, checks=CHECKS, timeout=30)
        statuses.add(response.status_code)
        if path.endswith("/events") and response.status_code == 200:
            # Schemathesis checks each event's envelope; its JSON data (contentSchema) is checked here
            data = [line[5:] for line in response.text.splitlines() if line.startswith("data:")]
            assert data and all(CampaignProgress.model_validate_json(d).id == fuzz_db[1] for d in data)

    run()
    assert 200 in statuses
