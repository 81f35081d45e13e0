"""Figures and tables say what the reader needs (issue 23, point 8): an overlay's title names the
settings all its campaigns share; a DR plot of early-stopping tests says so; a time-to-DR90 heat
map labels the cells that never reach 0.9; a cancelled campaign's table says how many tests were
recorded and that its algorithms are unpaired."""

from __future__ import annotations

import re

from ra2vipas.cli.output import describe_rig, print_results
from ra2vipas.services.orchestrator.plots import dr_figure, overlay_title, study_figure


def results_of(n_targets: int, **extra) -> dict:
    block = {"dr": [0.5, 0.75], "dr_final": 0.75, "ci95": [0.6, 0.8], "dr_ci95": [[0.4, 0.6], [0.6, 0.8]], "time_to_dr90_s": None,
             "in_fov_final": 0.8}
    return {"preset": "paper", "overrides": {"n_targets": n_targets, "rf_noise_db": 2.0}, "tests": 12, "seed": 1,
            "scenario": {"rf_period_s": 0.1, "steps": 2, "n_targets": n_targets, "rf_noise_db": 2.0}, "pod": {"r2": 0.9, "train_seconds": 0.1},
            "algorithms": {"ra2vipas": dict(block), "rapas": dict(block)}, "steps_per_second": None, **extra}


def test_an_overlays_title_names_every_setting_its_campaigns_share():
    runs = [("n_targets=30", results_of(30)), ("n_targets=10", results_of(10))]
    assert overlay_title(runs, "n_targets") == "DR_t by n_targets: preset paper, tests 12, seed 1, rf_noise_db=2.0"
    other = results_of(10)
    other["scenario"]["rf_noise_db"] = 4.0
    other["overrides"]["rf_noise_db"] = 4.0
    assert "rf_noise_db" not in overlay_title([("a", results_of(30)), ("b", other)])
    stopped = [("a", results_of(30, stop_confidence=0.95)), ("b", results_of(10, stop_confidence=0.95))]
    assert overlay_title(stopped).endswith("stopped at confidence 0.95")


def test_a_dr_plot_of_early_stopping_tests_says_so():
    title = dr_figure(results_of(30, stop_confidence=0.95)).axes[0].get_title()
    assert "each test stopped at confidence 0.95" in " ".join(title.split())


def test_a_time_to_dr90_heat_map_labels_the_cells_that_never_reach_it():
    rows = []
    for n in (4, 8):
        for noise in (2.0, 6.0):
            t90 = None if noise == 6.0 else 1.2
            rows.append({"point": len(rows), "n_targets": n, "rf_noise_db": noise, "algorithm": "ra2vipas", "tests": 3, "dr_final": 0.5,
                         "ci95_lo": 0.2, "ci95_hi": 0.8, "time_to_dr90_s": t90, "in_fov_final": 0.5, "pod_r2": 0.9, "campaign_id": None})
    study = {"preset": "paper", "parameters": ["n_targets", "rf_noise_db"], "algorithms": ["ra2vipas"], "tests": 3, "seed": 1,
             "rows": rows, "partial": False}
    fig = study_figure(study, "time_to_dr90_s")
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert texts.count("never") == 2 and texts.count("1.20") == 2
    assert "never: DR does not stay at 0.9" in fig._suptitle.get_text()
    rows_none = [{**r, "time_to_dr90_s": None} for r in rows]  # no cell reaches it: still a figure, all labelled
    assert [t.get_text() for t in study_figure({**study, "rows": rows_none}, "time_to_dr90_s").axes[0].texts].count("never") == 4


def test_a_cancelled_campaigns_table_says_what_was_recorded_and_that_it_is_unpaired(capsys):
    res = results_of(30, partial=True, tests_recorded={"ra2vipas": 17, "rapas": 16})
    res["tests"] = 60
    print_results(res)
    out = " ".join(capsys.readouterr().out.split())
    assert "PARTIAL: 16–17 of 60 tests" in out and "(60 tests" not in out
    assert "tests recorded: ra2vipas 17, rapas 16 (of 60)" in out
    assert re.search(r"the algorithms are unpaired: they rest on different numbers of tests", out)


def test_an_overlay_of_campaigns_with_one_seed_pairs_them_test_by_test():
    from ra2vipas.cli.campaign import overlay_pairs

    a = results_of(30, outcomes={"ra2vipas": [1] * 8 + [0, 0], "rapas": [1] * 10})
    b = results_of(10, outcomes={"ra2vipas": [0] * 8 + [1, 1], "rapas": [1] * 10})
    lines = overlay_pairs([("n_targets=30", a), ("n_targets=10", b), ("seed 2", {**b, "seed": 2})])
    assert lines == [
        "paired, ra2vipas: n_targets=30 vs n_targets=10: 10 tests, found only by the first 8, only by the second 2, "
        "DR difference +0.600, McNemar p = 0.109",
        "paired, rapas: n_targets=30 vs n_targets=10: 10 tests, found only by the first 0, only by the second 0, "
        "DR difference +0.000, McNemar p = 1"]


def test_a_study_results_points_carry_their_paired_tests():
    import ra2vipas
    from tests.api.live import SMALL

    study = ra2vipas.study({"rf_noise_db": [2.0, 6.0]}, overrides=SMALL, tests=3, seed=2, algorithms=["ra2vipas", "rapas"])
    for point in study["points"]:
        assert [(p["a"], p["b"], p["tests"]) for p in point["paired"]] == [("ra2vipas", "rapas", 3)]


def _tags_block(finals: list[float], all_found: float, decided: bool = True) -> dict:
    def one(v: float) -> dict:
        return {"dr": [v / 2, v], "dr_final": v, "ci95": [v - 0.1, min(v + 0.05, 1.0)], "dr_ci95": [[0.0, 0.5], [v - 0.1, v]],
                "time_to_dr90_s": None, "in_fov_final": v, "calibration": {"ece_final": 0.042}}
    per_tag = [one(v) for v in finals]
    if decided:
        for b in per_tag:
            b["decision"] = {"median_s": 0.7, "p90_s": 1.1, "undecided": 0.25}
    out = {"per_tag": per_tag, "mean_tag_dr_final": sum(finals) / len(finals), "all_found": one(all_found)}
    if decided:
        out["all_decided"] = {"median_s": 1.3, "p90_s": 1.9, "undecided": 0.5}
    return out


def test_a_many_tags_campaign_has_a_per_tag_table_and_one_curve_per_tag_plus_all_found(capsys):
    results = results_of(8)
    results["algorithms"]["ra2vipas"]["tags"] = _tags_block([0.75, 0.5, 0.25], 0.125)
    print_results(results)
    out = capsys.readouterr().out
    assert "Per tag: DR_t of each tag k" in out
    table = out[out.index("Per tag"):]
    rows = [line for line in table.splitlines() if line.startswith("│ ra2vipas ")]
    assert [r.split("│")[2].strip() for r in rows] == ["0", "1", "2", "all"]
    assert "0.125" in rows[-1] and "1.3 s" in rows[-1] and "1.9 s" in rows[-1] and "0.500" in rows[-1]
    assert "0.042" in rows[0] and "0.7 s" in rows[0]
    assert "ra2vipas 0.500" in " ".join(out.split())  # the mean per-tag DR, in the caption
    labels = [line.get_label() for line in dr_figure(results).axes[0].lines]
    assert [lb for lb in labels if lb.startswith("Ra")][:4] == [
        "Ra²ViPAS, tag 0 (final 0.750)", "Ra²ViPAS, tag 1 (final 0.500)", "Ra²ViPAS, tag 2 (final 0.250)",
        "Ra²ViPAS, all found (final 0.125)"]
    del results["algorithms"]["ra2vipas"]["tags"]
    print_results(results)
    assert "Per tag" not in capsys.readouterr().out  # one tag: no such table


def test_a_rigs_line_says_its_radio_and_how_many_tags_it_hears():
    """`ra2vipas rigs list`: a real two-tag BLE node (protocol 1.5) says so; a 1.1 descriptor says
    nothing of the radio, and a v1 node is undescribed."""
    ble = {"kind": "hardware", "vendor": "Acme", "model": "nRF52 pair", "frames_per_rf": 5, "rf_period_s": 0.1,
           "fov_half_angle_deg": 22.5, "box_bearing_noise_deg": 0.5, "rx_dir": {"model": "unknown"}, "radio": "adverts",
           "tags": 2, "protocol": "1.5"}
    assert describe_rig({"descriptor": ble}) == ("hardware, Acme nRF52 pair, nu 5, T_RF 0.1 s, half-FoV 22.5 deg, box noise 0.5 deg, "
                                                 "Rx(dir) unknown, BLE adverts, hears 2 tags, protocol 1.5")
    old = {k: v for k, v in ble.items() if k not in ("radio", "tags", "protocol")}
    assert describe_rig({"descriptor": {**old, "frames_per_rf": None}}).endswith("nu =campaign, T_RF 0.1 s, half-FoV 22.5 deg, "
                                                                               "box noise 0.5 deg, Rx(dir) unknown, protocol 1.1")
    assert describe_rig({"descriptor": None, "described": "undescribed"}).startswith("undescribed (v1 node")
