"""``ra2vipas campaign ...`` and ``ra2vipas rigs``: the real commands against a live API,
tables for people, ``--json`` for scripts, exit codes 0 / 1 / 2 with one-line errors."""

from __future__ import annotations

import json
import re

import pytest

from ra2vipas.services.orchestrator.api.export import read_results_csv
from tests.api.live import SMALL
from tests.cli.conftest import TOKEN, one_error_line, ra2vipas

SETS = [arg for k, v in SMALL.items() for arg in ("--set", f"{k}={v}")]


def last_json(stdout: str):
    return json.loads(stdout.strip().splitlines()[-1])


def test_start_prints_the_new_id_or_with_json_the_campaign(live):
    plain = ra2vipas("campaign", "start", "--api", live.url, "--tests", "1", "-a", "rapas", "--seed", "2", *SETS)
    assert plain.returncode == 0, plain.stderr
    cid = plain.stdout.strip()
    assert re.fullmatch(r"[0-9a-f]{12}", cid)
    as_json = ra2vipas("campaign", "start", "--tests", "1", "-a", "rapas", "--name", "scripted", "--json", *SETS,
                       env={"RA2VIPAS_API": live.url})
    assert as_json.returncode == 0, as_json.stderr
    c = last_json(as_json.stdout)
    assert re.fullmatch(r"[0-9a-f]{12}", c["id"]) and c["name"] == "scripted" and c["scenario"]["steps"] == SMALL["steps"]
    for i in (cid, c["id"]):
        live.wait(i)


def test_start_wait_follows_the_campaign_then_prints_results(live, tmp_path):
    table = ra2vipas("campaign", "start", "--api", live.url, "--tests", "2", "-a", "ra2vipas,rapas", "--wait", "--plot",
                     str(tmp_path / "dr.svg"), *SETS)
    assert table.returncode == 0, table.stderr
    assert "Discovery rate" in table.stdout and "ra2vipas" in table.stdout and "POD regression R²" in table.stdout
    assert (tmp_path / "dr.svg").read_text().lstrip().startswith(("<?xml", "<svg"))
    as_json = ra2vipas("campaign", "start", "--api", live.url, "--tests", "2", "-a", "rapas", "--seed", "5", "--wait", "--json", *SETS)
    assert as_json.returncode == 0, as_json.stderr
    results = last_json(as_json.stdout)
    assert results["seed"] == 5 and list(results["algorithms"]) == ["rapas"]


def test_list_shows_a_table_or_the_page(live, done_campaign):
    table = ra2vipas("campaign", "list", "--api", live.url, "--status", "done")
    assert table.returncode == 0, table.stderr
    assert done_campaign["id"] in table.stdout and "Campaigns 1–" in table.stdout
    page = last_json(ra2vipas("campaign", "list", "--api", live.url, "--json", "--limit", "200").stdout)
    assert done_campaign["id"] in {c["id"] for c in page["items"]} and page["total"] >= 1
    bad = ra2vipas("campaign", "list", "--api", live.url, "--status", "sleeping")
    assert bad.returncode == 2 and "--status must be one of" in one_error_line(bad)


def test_show_and_status(live, done_campaign):
    cid = done_campaign["id"]
    table = ra2vipas("campaign", "show", cid, "--api", live.url)
    assert table.returncode == 0, table.stderr
    for needle in (f"Campaign {cid}", "done", "6/6", "POD R²", "Scenario (* overridden)", "n_targets *"):
        assert needle in table.stdout, needle
    assert last_json(ra2vipas("campaign", "show", cid, "--api", live.url, "--json").stdout)["id"] == cid
    status = ra2vipas("campaign", "status", cid, "--api", live.url)
    assert status.returncode == 0 and status.stdout.startswith(f"{cid}: done, 6/6 episodes done")


def test_watch_follows_until_done_with_json_lines(live):
    cid = last_json(ra2vipas("campaign", "start", "--api", live.url, "--tests", "3", "-a", "ra2vipas", "--json", *SETS).stdout)["id"]
    watch = ra2vipas("campaign", "watch", cid, "--api", live.url, "--json")
    assert watch.returncode == 0, watch.stderr
    updates = [json.loads(line) for line in watch.stdout.strip().splitlines()]
    assert updates[-1]["status"] == "done" and updates[-1]["progress"]["done"] == 3
    assert [u["progress"]["done"] for u in updates] == sorted(u["progress"]["done"] for u in updates)
    plain = ra2vipas("campaign", "watch", cid, "--api", live.url)
    assert plain.returncode == 0 and f"{cid}: done, 3/3 episodes done" in plain.stdout


def test_results_table_json_and_per_test(live, done_campaign):
    cid = done_campaign["id"]
    table = ra2vipas("campaign", "results", cid, "--api", live.url)
    assert table.returncode == 0 and "rapas" in table.stdout and "95% CI" in table.stdout
    results = last_json(ra2vipas("campaign", "results", cid, "--api", live.url, "--json").stdout)
    assert results["seed"] == 3
    per_test = ra2vipas("campaign", "results", cid, "--api", live.url, "--per-test", "--algorithm", "rapas")
    assert per_test.returncode == 0 and "Tests 1–3 of 3" in per_test.stdout
    page = last_json(ra2vipas("campaign", "results", cid, "--api", live.url, "--per-test", "--json").stdout)
    assert page["total"] == 6


def test_trace_of_one_test(live, done_campaign):
    cid = done_campaign["id"]
    table = ra2vipas("campaign", "trace", cid, "--api", live.url, "--test", "1", "--algorithm", "rapas")
    assert table.returncode == 0, table.stderr
    assert "Test 1 (rapas): the Tx is target" in table.stdout and "γ̂_t" in table.stdout
    body = last_json(ra2vipas("campaign", "trace", cid, "--api", live.url, "--test", "1", "--algorithm", "rapas", "--json").stdout)
    assert len(body["steps"]) == SMALL["steps"]
    absent = ra2vipas("campaign", "trace", cid, "--api", live.url, "--test", "1", "--algorithm", "sweep")
    assert absent.returncode == 1 and "has no test 1 of sweep" in one_error_line(absent)


def test_export_json_and_csv(live, done_campaign, tmp_path):
    cid = done_campaign["id"]
    to_stdout = ra2vipas("campaign", "export", cid, "--api", live.url)
    assert to_stdout.returncode == 0 and json.loads(to_stdout.stdout)["seed"] == 3
    out = tmp_path / "r.csv"
    to_file = ra2vipas("campaign", "export", cid, "--api", live.url, "-o", str(out))
    assert to_file.returncode == 0, to_file.stderr
    meta = read_results_csv(out.read_text())
    assert meta["seed"] == 3 and meta["scenario"] == done_campaign["scenario"] and meta["campaign_id"] == cid
    bad = ra2vipas("campaign", "export", cid, "--api", live.url, "--format", "xml")
    assert bad.returncode == 2 and "--format must be json or csv" in one_error_line(bad)


def test_plot_writes_the_server_rendered_figures(live, done_campaign, tmp_path):
    cid = done_campaign["id"]
    for args, name in ((["--kind", "dr"], "dr.png"), (["--kind", "pod"], "pod.svg"),
                       (["--kind", "episode", "--test", "1", "--algorithm", "ra2vipas"], "ep.png")):
        proc = ra2vipas("campaign", "plot", cid, "--api", live.url, *args, "-o", str(tmp_path / name))
        assert proc.returncode == 0, proc.stderr
        data = (tmp_path / name).read_bytes()
        assert data.startswith(b"\x89PNG") if name.endswith(".png") else b"<svg" in data[:500]
    default = ra2vipas("campaign", "plot", cid, "--api", live.url, cwd=tmp_path)
    assert default.returncode == 0 and (tmp_path / f"campaign-{cid}-dr.png").exists()
    missing = ra2vipas("campaign", "plot", cid, "--api", live.url, "--kind", "episode")
    assert missing.returncode == 2 and "--test" in one_error_line(missing)
    absent = ra2vipas("campaign", "plot", cid, "--api", live.url, "--kind", "episode", "--test", "7", "--algorithm", "rapas",
                      "-o", str(tmp_path / "x.png"))
    assert absent.returncode == 1 and "has no test 7" in one_error_line(absent)
    assert not (tmp_path / "x.png").exists()


def test_cancel_and_delete(live, done_campaign):
    cancel_done = ra2vipas("campaign", "cancel", done_campaign["id"], "--api", live.url)
    assert cancel_done.returncode == 1 and "already finished (done)" in one_error_line(cancel_done)
    cid = last_json(ra2vipas("campaign", "start", "--api", live.url, "--tests", "1", "-a", "rapas", "--json", *SETS).stdout)["id"]
    live.wait(cid)
    deleted = ra2vipas("campaign", "delete", cid, "--api", live.url)
    assert deleted.returncode == 0 and deleted.stdout.strip() == f"campaign {cid} deleted"
    gone = ra2vipas("campaign", "show", cid, "--api", live.url)
    assert gone.returncode == 1 and f"no campaign '{cid}'" in one_error_line(gone)


@pytest.mark.parametrize("args", [["results", "0123456789ab"], ["watch", "0123456789ab"], ["delete", "0123456789ab"],
                                  ["export", "0123456789ab"]])
def test_unknown_campaigns_fail_with_one_line_and_exit_1(live, args):
    proc = ra2vipas("campaign", *args, "--api", live.url)
    assert proc.returncode == 1 and "no campaign '0123456789ab'" in one_error_line(proc)


def test_input_the_api_rejects_is_exit_2(live):
    proc = ra2vipas("campaign", "start", "--api", live.url, "--set", "n_targets=0")
    assert proc.returncode == 2 and "n_targets: expected an integer in [1, 500]" in one_error_line(proc)


def test_usage_errors_are_exit_2():
    assert ra2vipas("campaign", "show").returncode == 2
    assert ra2vipas("campaign", "list", "--limit", "500").returncode == 2
    assert ra2vipas("campaign", "frobnicate").returncode == 2


def test_rigs_table_and_json(live):
    table = ra2vipas("rigs", "list", "--api", live.url)
    assert table.returncode == 0 and "rig-1" in table.stdout and "learners: learner" in table.stdout
    body = last_json(ra2vipas("rigs", "list", "--json", env={"RA2VIPAS_API": live.url}).stdout)
    assert body["rigs"][0]["name"] == "rig-1" and body["rigs"][0]["live"] is True
    assert [p["name"] for p in body["rigs"][0]["policies"]][:4] == ["ra2vipas", "rapas", "ravipas", "sweep"]
    assert "policies" in table.stdout
    old = ra2vipas("rigs", "--json", "--api", live.url)  # the old spelling still lists, with a warning
    assert old.returncode == 0 and [r["name"] for r in last_json(old.stdout)["rigs"]] == [r["name"] for r in body["rigs"]]
    assert old.stderr.strip() == "warning: `ra2vipas rigs` is deprecated; use `ra2vipas rigs list`"


def test_an_unreachable_api_is_one_line_and_exit_1():
    proc = ra2vipas("rigs", "list", "--api", "http://127.0.0.1:9")
    assert proc.returncode == 1 and "cannot reach the API at http://127.0.0.1:9" in one_error_line(proc)


def test_the_token_comes_from_the_flag_or_the_environment(guarded):
    denied = ra2vipas("campaign", "start", "--api", guarded.url, "--tests", "1")
    assert denied.returncode == 1 and "HTTP 401" in one_error_line(denied)
    by_flag = ra2vipas("campaign", "start", "--api", guarded.url, "--tests", "1", "--token", TOKEN)
    assert by_flag.returncode == 0, by_flag.stderr
    cid = by_flag.stdout.strip()
    by_env = ra2vipas("campaign", "cancel", cid, "--api", guarded.url, env={"RA2VIPAS_TOKEN": TOKEN})
    assert by_env.returncode == 0 and f"campaign {cid} cancelled" in by_env.stdout
    assert ra2vipas("campaign", "show", cid, "--api", guarded.url).returncode == 0  # reads need no token
