"""The campaign id is never lost (issue 23, point 4): ``campaign start --wait`` prints it on its
own line when it starts, also when the output is piped (these tests read a pipe), and every
results object carries it (``--json``, the API; null for a campaign run in-process)."""

from __future__ import annotations

import json

import ra2vipas
from tests.api.live import SMALL
from tests.cli.conftest import ra2vipas as cli

SETS = [f"--set={k}={v}" for k, v in SMALL.items()]


def test_start_wait_prints_the_id_first_and_the_results_carry_it(live):
    proc = cli("campaign", "start", "--api", live.url, "--tests", "2", "-a", "rapas", "--seed", "11", "--wait", *SETS, timeout=180)
    assert proc.returncode == 0, proc.stderr
    first = proc.stdout.splitlines()[0]
    assert first.startswith("campaign ") and len(first.split()) == 2
    cid = first.split()[1]
    assert live.client().get(f"/campaigns/{cid}").json()["seed"] == 11
    as_json = cli("campaign", "start", "--api", live.url, "--tests", "2", "-a", "rapas", "--seed", "12", "--wait", "--json", *SETS,
                  timeout=180)
    assert as_json.returncode == 0, as_json.stderr
    results = json.loads(as_json.stdout)  # stdout stays one JSON line; the id line went to stderr
    assert f"campaign {results['id']}" in as_json.stderr.splitlines()
    assert live.client().get(f"/campaigns/{results['id']}").json()["seed"] == 12


def test_every_results_object_carries_the_id(done_campaign, live):
    cid = done_campaign["id"]
    assert live.client().get(f"/campaigns/{cid}/results").json()["id"] == cid
    shown = json.loads(cli("campaign", "results", cid, "--api", live.url, "--json").stdout)
    assert shown["id"] == cid
    exported = json.loads(cli("campaign", "export", cid, "--api", live.url).stdout)
    assert exported["id"] == cid
    with ra2vipas.Client(live.url) as client:
        assert client.results(cid)["id"] == cid
    here = ra2vipas.simulate(overrides=SMALL, tests=1, seed=1, algorithms=["rapas"])
    assert "id" in here and here["id"] is None
