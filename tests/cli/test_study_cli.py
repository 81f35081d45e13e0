"""``ra2vipas study ...`` against a live API, and ``ra2vipas simulate --vary`` / ``--workers`` in-process:
the real command as a subprocess."""

from __future__ import annotations

import json

import pytest

from tests.cli.conftest import one_error_line, ra2vipas
from tests.conftest import differences, untimed

SMALL = ["--set", "steps=20", "--set", "n_train=200"]


def last_json(proc) -> dict:
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def cli_study(live):
    """A study started and waited for with the CLI: its results object."""
    proc = ra2vipas("study", "start", "--api", live.url, "--vary", "n_targets=4,8", "--tests", "2", "--seed", "4",
                    "-a", "ra2vipas,rapas", *SMALL, "--wait", "--json")
    return last_json(proc)


def test_study_start_wait_prints_the_results_object(cli_study):
    assert cli_study["status"] == "done" and cli_study["partial"] is False
    assert cli_study["parameters"] == ["n_targets"] and cli_study["vary"] == {"n_targets": [4, 8]}
    assert [(r["n_targets"], r["algorithm"]) for r in cli_study["rows"]] == [(4, "ra2vipas"), (4, "rapas"), (8, "ra2vipas"), (8, "rapas")]


def test_list_show_results_csv_and_plot(live, cli_study, tmp_path):
    sid = cli_study["id"]
    listed = ra2vipas("study", "list", "--api", live.url)
    assert listed.returncode == 0 and sid in listed.stdout
    page = last_json(ra2vipas("study", "list", "--api", live.url, "--status", "done", "--json"))
    assert sid in [s["id"] for s in page["items"]]
    shown = ra2vipas("study", "show", sid, "--api", live.url)
    assert shown.returncode == 0 and "n_targets" in shown.stdout and cli_study["points"][0]["campaign_id"] in shown.stdout
    assert last_json(ra2vipas("study", "show", sid, "--api", live.url, "--json"))["points_total"] == 2
    table = ra2vipas("study", "results", sid, "--api", live.url)
    assert table.returncode == 0 and "DR final" in table.stdout and "rapas" in table.stdout
    assert last_json(ra2vipas("study", "results", sid, "--api", live.url, "--json"))["rows"] == cli_study["rows"]
    out = tmp_path / "study.csv"
    assert ra2vipas("study", "results", sid, "--api", live.url, "--csv", str(out)).returncode == 0
    assert out.read_text().count("\n") >= 4 and "dr_final" in out.read_text()
    png = tmp_path / "study.png"
    proc = ra2vipas("study", "plot", sid, "--api", live.url, "-o", str(png), "--metric", "in_fov_final")
    assert proc.returncode == 0, proc.stderr
    assert png.read_bytes()[:4] == b"\x89PNG"
    watched = last_json(ra2vipas("study", "watch", sid, "--api", live.url, "--json"))
    assert watched["rows"] == cli_study["rows"]


def test_cancel_a_finished_study_and_delete(live):
    sid = ra2vipas("study", "start", "--api", live.url, "--vary", "rf_noise_db=2:3:1", "--tests", "1", "-a", "rapas", *SMALL).stdout.strip()
    assert sid
    done = last_json(ra2vipas("study", "watch", sid, "--api", live.url, "--json"))
    assert done["status"] == "done" and [r["rf_noise_db"] for r in done["rows"]] == [2.0, 3.0]
    proc = ra2vipas("study", "cancel", sid, "--api", live.url)
    assert proc.returncode == 1 and "finished" in one_error_line(proc)
    assert ra2vipas("study", "delete", sid, "--api", live.url).returncode == 0
    proc = ra2vipas("study", "show", sid, "--api", live.url)
    assert proc.returncode == 1 and sid in one_error_line(proc)


@pytest.mark.parametrize("args, words", [
    (["--vary", "n_target=1,2"], ["n_target", "n_targets"]),
    (["--vary", "n_targets"], ["NAME=a,b,c"]),
    (["--vary", "rf_noise_db=6:2:1"], ["never reaches"]),
    (["--vary", "n_targets=2:5:0.5"], ["fractions"]),
    ([], ["--vary"]),
])
def test_bad_grids_are_usage_errors(live, args, words):
    proc = ra2vipas("study", "start", "--api", live.url, *args)
    assert proc.returncode == 2
    line = one_error_line(proc)
    for word in words:
        assert word in line, line


def test_a_grid_the_server_rejects_is_exit_2(live):
    proc = ra2vipas("study", "start", "--api", live.url, "--vary", "rf_noise_db=-1,2")
    assert proc.returncode == 2 and "rf_noise_db" in one_error_line(proc)


def test_simulate_vary_prints_the_study_results_object_and_a_point_equals_its_campaign(tmp_path):
    plot = tmp_path / "study.svg"
    study = last_json(ra2vipas("simulate", "--vary", "n_targets=4,8", "--tests", "2", "--seed", "6", "-a", "ra2vipas,rapas", *SMALL,
                               "--workers", "2", "--json", "--plot", str(plot), timeout=300))
    assert study["id"] is None and study["status"] == "done" and study["workers"] == 2 and len(study["rows"]) == 4
    assert b"<svg" in plot.read_bytes()[:400]
    alone = last_json(ra2vipas("simulate", "--set", "n_targets=8", "--tests", "2", "--seed", "6", "-a", "ra2vipas,rapas", *SMALL,
                               "--workers", "1", "--json", timeout=300))
    for row in study["rows"][2:]:
        block = alone["algorithms"][row["algorithm"]]
        assert row["dr_final"] == block["dr_final"] and [row["ci95_lo"], row["ci95_hi"]] == block["ci95"]
        assert row["calibration_ece_final"] == block["calibration"]["ece_final"] and row["pod_r2"] == alone["pod"]["r2"]
    table = ra2vipas("simulate", "--vary", "n_targets=4,8", "--tests", "1", "-a", "rapas", *SMALL, timeout=300)
    assert table.returncode == 0 and "DR final" in table.stdout and "n_targets" in table.stdout


def test_simulate_workers_2_equals_workers_1():
    args = ["simulate", "--tests", "4", "--seed", "9", *SMALL, "--set", "n_targets=8", "--stop-confidence", "0.7", "--json"]
    one = untimed(last_json(ra2vipas(*args, "--workers", "1", timeout=300)))
    two = untimed(last_json(ra2vipas(*args, "--workers", "2", timeout=300)))
    assert one == two, differences(one, two)


def test_simulate_vary_usage_errors():
    proc = ra2vipas("simulate", "--vary", "n_targets=4,8", "--reliability-plot", "x.png")
    assert proc.returncode == 2 and "--reliability-plot" in one_error_line(proc)
    proc = ra2vipas("simulate", "--vary", "nope=1,2")
    assert proc.returncode == 2 and "nope" in one_error_line(proc)
