"""``ra2vipas record`` and ``ra2vipas replay``: campaigns to MCAP files and back
(``services/rigs/recording.py``)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from ra2vipas.cli.client import DEFAULT_API, ApiOpt, Client, JsonOpt, TokenOpt
from ra2vipas.cli.output import EXIT_USAGE, fail, print_json, stderr, stdout
from ra2vipas.cli.services import ConfigOpt, ConnectOpt, ListenOpt, ModeOpt

OutOpt = Annotated[Path, typer.Option("--output", "-o", metavar="FILE", help="The MCAP file to write (e.g. campaign.mcap).")]


def _store_entries(client: Client, campaign: dict, skip: set[tuple[int, str]]):
    """What the orchestrator kept of every recorded test not in ``skip``, as messages."""
    from ra2vipas.services.rigs.recording import entries_from_trace

    out, offset = [], 0
    while True:
        page = client.request("GET", f"/campaigns/{campaign['id']}/tests", params={"status": "done", "limit": 200, "offset": offset})
        for row in page["items"]:
            if (row["test_index"], row["algorithm"]) in skip:
                continue
            trace = client.request("GET", f"/campaigns/{campaign['id']}/tests/{row['test_index']}/{row['algorithm']}")
            out += entries_from_trace(campaign, trace)
        offset += len(page["items"])
        if not page["items"] or offset >= page["total"]:
            return out


def _pod_model(bus, campaign: dict) -> dict | None:
    """The campaign's POD model from the learner (cached there: it answers at once)."""
    import queue

    from ra2vipas.services.protocol import keys
    from ra2vipas.services.protocol.messages import PODRequest, PODResponse, dump
    from ra2vipas.services.protocol.scenario import Scenario
    from ra2vipas.services.protocol.versions import PROTOCOL_VERSION
    from ra2vipas.services.transport.runtime import first_valid_reply

    got: queue.Queue = queue.Queue()
    bus.query(keys.pod_model(), dump(PODRequest(scenario=Scenario.model_validate(campaign["scenario"]), seed=campaign["seed"],
                                                   protocol=PROTOCOL_VERSION)), 60.0,
              got.put)
    try:
        response, _ = first_valid_reply(got.get(timeout=70.0), PODResponse, "PODResponse")
    except queue.Empty:
        return None
    return None if response is None else response.model_dump(mode="json")


def save_recording(client: Client, cid: str, output: Path, recorder=None, bus=None) -> int:
    """Write campaign ``cid`` (finished) to ``output``: the live ``recorder``'s messages, and
    what the orchestrator kept of every test the recorder did not see. Returns messages written."""
    from ra2vipas.services.rigs.recording import RecordingError, write_mcap

    campaign = client.request("GET", f"/campaigns/{cid}")
    if campaign["status"] not in ("done", "failed", "cancelled"):
        fail(f"campaign {cid} is {campaign['status']}: record it when it has finished")
    results = client.request("GET", f"/campaigns/{cid}/results") if campaign["status"] == "done" else None
    live = recorder.campaign_entries(cid) if recorder is not None else []
    seen = set()
    for e in live:
        msg = json.loads(e.payload)
        if msg.get("kind") == "start":
            seen.add((msg["test_index"], msg["algorithm"]))
    # a test counts as seen live only if its result was recorded live too
    results_live = {json.loads(e.payload)["episode_id"] for e in live if e.key.endswith("/episode") and "/result/" in e.key}
    seen = {(int(eid.split(".")[1]), eid.split(".")[2]) for eid in results_live} & seen
    entries = live + _store_entries(client, campaign, seen)
    rigs = client.request("GET", "/rigs")
    descriptors = {r["name"]: r["descriptor"] for r in rigs["rigs"] if r.get("descriptor")}
    pod = _pod_model(bus, campaign) if bus is not None else None
    source = "live" if live and not (entries[len(live):]) else ("live+store" if live else "store")
    try:
        return write_mcap(output, entries, campaign=campaign, results=results, source=source, descriptors=descriptors, pod=pod)
    except RecordingError as err:
        fail(str(err))


def open_bus(mode, connect, listen, zenoh_config):
    from ra2vipas.cli.services import zenoh_settings
    from ra2vipas.services.transport.zenoh_bus import ZenohBus

    try:
        return ZenohBus(zenoh_settings(mode, connect, listen, zenoh_config))
    except Exception as err:  # zenoh raises ZError for bad endpoints, unreachable routers, ...
        fail(f"cannot open the Zenoh session: {err}")


def record(
    campaign: Annotated[str, typer.Option("--campaign", help="The campaign to record.")],
    output: OutOpt,
    mode: ModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None, zenoh_config: ConfigOpt = None,
    api: ApiOpt = DEFAULT_API, token: TokenOpt = None,
) -> None:
    """Record a campaign to an MCAP file (JSON messages, JSON Schemas embedded; opens in Foxglove).

    A campaign still running is recorded live from now on, every message of every episode
    (commands, measurements, results, timing, truth), until it finishes; the tests it finished
    before are added from what the orchestrator kept (no measurements). A finished campaign is
    recorded from what the orchestrator kept: enough to re-score it, not to re-run a controller
    (for that, record as it runs: `ra2vipas campaign start --record FILE`). The Zenoh options
    (or the RA2VIPAS_ZENOH_* environment, e.g. a stack's zenoh.env) say how to join the mesh."""
    from ra2vipas.services.rigs.recording import Recorder

    client = Client(api, token)
    c = client.request("GET", f"/campaigns/{campaign}")
    bus = open_bus(mode, connect, listen, zenoh_config)
    try:
        recorder = None
        if c["status"] not in ("done", "failed", "cancelled"):
            recorder = Recorder(bus)
            stderr.print(f"recording campaign {campaign} live until it finishes ...")
            while client.request("GET", f"/campaigns/{campaign}")["status"] not in ("done", "failed", "cancelled"):
                time.sleep(0.5)
            time.sleep(0.5)  # the last messages
            recorder.stop()
        count = save_recording(client, campaign, output, recorder, bus)
    finally:
        bus.close()
    print(f"wrote {count} messages of campaign {campaign} to {output}")


def replay(
    file: Annotated[Path, typer.Argument(help="A recording (ra2vipas record).")],
    rerun_algorithm: Annotated[Optional[str], typer.Option("--rerun", metavar="ALGORITHM", help="Re-run a controller on the recorded measurements: 'same' (each episode's own algorithm, the current code) or an algorithm name.")] = None,
    as_json: JsonOpt = False,
) -> None:
    """Re-score a recording (and compare with the results it recorded), or re-run a controller
    on its episodes where the pans it asks for match the recorded ones."""
    from ra2vipas.services.controller.registry import BUILTINS
    from ra2vipas.services.rigs.recording import RecordingError, read_mcap, replay_scores, rerun, rerun_summary

    try:
        rec = read_mcap(file)
        if rerun_algorithm is None:
            results = replay_scores(rec)
            same = _comparable(results) == _comparable(rec.results) if rec.results is not None else None
            body = {"campaign": rec.campaign["id"], "source": rec.source, "matches_recorded_results": same, "results": results}
        else:
            if rerun_algorithm != "same" and rerun_algorithm not in BUILTINS:  # a rerun drives the built-ins' Controller
                fail(f"--rerun must be 'same' or one of {', '.join(BUILTINS)}, got {rerun_algorithm!r}", EXIT_USAGE)
            runs = rerun(rec, None if rerun_algorithm == "same" else rerun_algorithm)
            body = {"campaign": rec.campaign["id"], "source": rec.source, "rerun": rerun_summary(runs)}
    except RecordingError as err:
        fail(str(err))
    if as_json:
        print_json(body)
        return
    if "results" in body:
        from ra2vipas.cli.output import print_results

        print_results(body["results"])
        verdict = {True: "the same as the recorded results", False: "DIFFERENT from the recorded results",
                   None: "no recorded results to compare with"}[body["matches_recorded_results"]]
        stdout.print(f"re-scored {sum(1 for _ in rec.recorded())} episodes of campaign {rec.campaign['id']}: {verdict}")
    else:
        for name, s in body["rerun"].items():
            stdout.print(f"{name}: {s['episodes']} episodes, {s['steps_matched']:.1%} of the steps on recorded pans, "
                         f"{s['episodes_matched']} matched to the end (final DR there: "
                         f"{'-' if s['dr_final_matched'] is None else format(s['dr_final_matched'], '.3f')}), "
                         f"{s['same_estimates']} with the recorded estimates")
            if s["stopped_other_pan"] or s["stopped_missing_measurement"]:
                stdout.print(f"  stopped early: {s['stopped_other_pan']} where the controller asked for another pan than the "
                             f"recorded one, {s['stopped_missing_measurement']} at a step whose measurement the recording lacks "
                             "(a message lost while recording)")


def _comparable(results: dict | None) -> dict | None:
    """A results object without what depends on the wall clock."""
    if results is None:
        return None
    out = json.loads(json.dumps(results))
    out.pop("steps_per_second", None)
    out.pop("latency_ms", None)
    out.get("pod", {}).pop("train_seconds", None)
    return out
