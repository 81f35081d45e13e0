"""The server-side figures render headless, from any thread, as PNG and SVG."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from ra2vipas.services.orchestrator import plots
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors import physics

SCENARIO = build_scenario("paper", {"steps": 30})


def model_data() -> dict:
    grid = np.linspace(-55.0, -20.0, 40)
    return {"rssi_grid_dbm": grid.tolist(), "mean": physics.pod_of_rssi(SCENARIO, grid).tolist(), "std": [0.05] * 40}


def episode() -> dict:
    t = np.arange(30)
    estimates = physics.wrap(math.pi - 0.01 + 0.002 * (-1) ** t)  # crosses ±π: drawn without a vertical jump
    return {"test_index": 4, "algorithm": "ra2vipas", "tx_index": 1, "bearings": [0.5, float(math.pi - 0.01), -2.0],
            "ranges": [3.0, 2.0, 5.5], "pans": physics.wrap(0.3 * t).tolist(), "estimates": estimates.tolist(),
            "hits": [bool(k > 3) for k in t]}


@pytest.mark.parametrize("fmt, magic", [("png", b"\x89PNG"), ("svg", b"<?xml")])
def test_pod_and_episode_figures_render(fmt, magic):
    truth = {"rssi_dbm": np.linspace(-50, -25, 5000).tolist(), "pod": np.full(5000, 0.5).tolist()}
    for build in (lambda: plots.pod_figure(SCENARIO, model_data(), truth, "POD"), lambda: plots.pod_figure(SCENARIO, model_data(), None),
                  lambda: plots.episode_figure(SCENARIO, episode())):
        assert plots.draw(build, fmt).startswith(magic)


def test_a_wrapping_estimate_is_broken_not_drawn_across_the_axis():
    deg = np.array([179.0, -179.0, 178.0])
    assert np.isnan(plots._unwrapped_for_plot(deg)).sum() == 2


def test_figures_render_concurrently_from_worker_threads():
    errors: list = []

    def work():
        try:
            assert plots.draw(lambda: plots.episode_figure(SCENARIO, episode()), "png").startswith(b"\x89PNG")
        except Exception as err:  # pragma: no cover - reported below
            errors.append(err)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(60)
    assert not errors


def test_an_unknown_format_is_refused():
    with pytest.raises(ValueError, match="png, svg"):
        plots.render(plots.episode_figure(SCENARIO, episode()), "gif")


def test_a_study_varying_two_parameters_is_a_heat_map_per_algorithm():
    """First parameter on y, second on x, both in sorted order; a cell per point (empty where a
    point has no value yet); one colour scale, [0, 1] for the final DR."""
    rows = [{"algorithm": a, "n_targets": n, "rf_noise_db": s, "dr_final": round(0.1 * i + (0.05 if a == "rapas" else 0.0), 3)}
            for i, (n, s) in enumerate([(8, 4.0), (8, 2.0), (4, 4.0), (4, 2.0), (12, 2.0)]) for a in ("ra2vipas", "rapas")]
    results = {"preset": "paper", "tests": 3, "seed": 1, "parameters": ["n_targets", "rf_noise_db"],
               "algorithms": ["ra2vipas", "rapas"], "rows": rows}
    fig = plots.study_figure(results, "dr_final")
    maps = [ax for ax in fig.axes if ax.images]
    assert [ax.get_title() for ax in maps] == [plots.LABELS.get(a, a) for a in ("ra2vipas", "rapas")]
    assert [ax.get_xlabel() for ax in maps] == ["rf_noise_db"] * 2 and maps[0].get_ylabel() == "n_targets"
    for ax, offset in zip(maps, (0.0, 0.05)):
        grid = np.ma.filled(ax.images[0].get_array().astype(float), np.nan)
        expected = np.array([[0.3, 0.2], [0.1, 0.0], [0.4, np.nan]]) + offset  # y: 4, 8, 12; x: 2.0, 4.0
        np.testing.assert_allclose(grid, expected, equal_nan=True)
        assert ax.images[0].get_clim() == (0.0, 1.0)
    assert len(fig.axes) == len(maps) + 1  # and one colour bar
    assert plots.render(fig, "png")[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="varies 3"):
        plots.study_figure({**results, "parameters": ["n_targets", "rf_noise_db", "steps"]}, "dr_final")
