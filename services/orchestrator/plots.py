"""Server-side figures (matplotlib, headless, PNG or SVG).

* ``dr_figure``: the DR curves of every algorithm with Wilson 95 % bands (paper Fig. 4);
* ``pod_figure``: the learned POD p_hat_D(r) against the true p_D(r) (paper Fig. 3);
* ``episode_figure``: one test of one algorithm: the targets, the FoV, the pan trajectory and
  the estimate gamma_hat_t over time;
* ``study_figure``: a study's metric (e.g. the final DR) against its varied parameter, one line
  per algorithm with its 95 % band, or a heat map per algorithm when two parameters vary.

Figures are built on ``matplotlib.figure.Figure`` (never pyplot, whose global state is not
thread-safe) and rendered one at a time under a lock (``draw``), for callers that render from
threads. The API never draws in its own process: it sends a ``PlotJob`` (plain data) to the
renderer processes of ``ra2vipas.services.orchestrator.api.render``, which call ``draw_job``.
"""

from __future__ import annotations

import io
import math
import os
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Literal

import numpy as np

from ra2vipas.services.controller.registry import BUILTINS
from ra2vipas.services.orchestrator.names import colours
from ra2vipas.services.orchestrator.names import label as _label
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.sensors import physics

if TYPE_CHECKING:
    from matplotlib.figure import Figure

LABELS = {name: _label(name, non_active=True) for name in BUILTINS}
"""The built-ins' labels in figures; any other policy is labelled with its name."""
FORMATS = ("png", "svg")
MEDIA_TYPES = {"png": "image/png", "svg": "image/svg+xml"}
MAX_SCATTER = 3000  # truth points drawn in the POD figure (a uniform subsample beyond this)

_RENDER_LOCK = threading.RLock()


def _figure(**kwargs) -> Figure:
    """A new ``matplotlib.figure.Figure``; matplotlib is imported here, on the first figure, not with this
    module: the orchestrator imports it for its names and renders in other processes (~0.6 s of CPU saved
    at every start)."""
    from matplotlib.figure import Figure

    return Figure(**kwargs)


def run_title(results: dict[str, Any], name: str | None = None, width: int = 90) -> str:
    """What was run, for a figure's title: the campaign's name, the preset and every override,
    tests and seed (and "partial" for a cancelled or failed campaign), wrapped to ``width``."""
    import textwrap

    overrides = results.get("overrides") or {}
    what = results["preset"] + "".join(f", {k}={v}" for k, v in overrides.items())
    tests = f"{results['tests']} tests"
    if results.get("partial"):
        recorded = sorted(set((results.get("tests_recorded") or {}).values()))
        tests = f"partial: {'/'.join(map(str, recorded)) or 0} of {results['tests']} tests"
    line = f"{name + ' — ' if name else ''}{what}: {tests}, seed {results['seed']}"
    if results.get("stop_confidence"):
        line += f", each test stopped at confidence {results['stop_confidence']:g}"
    return "\n".join(textwrap.wrap(line, width)) or line


def overlay_title(runs: list[tuple[str, dict[str, Any]]], label: str | None = None, width: int = 90) -> str:
    """An overlay's title: what every campaign shares, so the legend need only say what differs:
    the preset, tests and seed, every scenario parameter overridden alike in all of them (the
    resolved value is the same everywhere and differs from the first one's preset), and the
    stop confidence."""
    import textwrap

    results = [r for _, r in runs]
    first = results[0]
    shared = [f"{k} {first[k]}" for k in ("preset", "tests", "seed") if len({str(r[k]) for r in results}) == 1]
    for name, value in (first.get("overrides") or {}).items():
        if name != label and all((r.get("scenario") or {}).get(name) == first["scenario"].get(name) for r in results):
            shared.append(f"{name}={value}")
    stops = {r.get("stop_confidence") or 0.0 for r in results}
    if len(stops) == 1 and stops != {0.0}:
        shared.append(f"stopped at confidence {stops.pop():g}")
    line = "DR_t" + (f" by {label}" if label else "") + (f": {', '.join(shared)}" if shared else "")
    return "\n".join(textwrap.wrap(line, width)) or line


_TAG_STYLES = (":", "--", "-.", (0, (1, 1)), (0, (5, 1)))  # tag k's curve in a many-tags figure


def dr_figure(results: dict[str, Any], name: str | None = None) -> Figure:
    """DR_t of every algorithm against time, with its Wilson 95 % band (paper Fig. 4); the
    title says what was run (``run_title``). An algorithm that searched for several tags
    (issue 21) draws one curve per tag and the "all tags found" rate with its band."""
    period = results["scenario"]["rf_period_s"]
    fig = _figure(figsize=(7.0, 4.2), dpi=120)
    ax = fig.subplots()
    colour = colours(results["algorithms"])
    for algorithm, block in results["algorithms"].items():
        dr = block["dr"]
        t = [(i + 1) * period for i in range(len(dr))]
        label = LABELS.get(algorithm, algorithm)
        tags = block.get("tags")
        if tags:  # several tags (issue 21): one thin curve per tag, and "all found" with its band
            for k, tag in enumerate(tags["per_tag"]):
                ax.plot(t, tag["dr"], label=f"{label}, tag {k} (final {tag['dr_final']:.3f})", linewidth=1.1,
                        linestyle=_TAG_STYLES[k % len(_TAG_STYLES)], color=colour[algorithm], alpha=0.85)
            block = tags["all_found"]
            dr = block["dr"]
            label = f"{label}, all found"
        line = ax.plot(t, dr, label=f"{label} (final {block['dr_final']:.3f})", linewidth=2.2 if tags else 1.8,
                       color=colour[algorithm])[0]
        lo = [b[0] for b in block["dr_ci95"]]
        hi = [b[1] for b in block["dr_ci95"]]
        ax.fill_between(t, lo, hi, color=line.get_color(), alpha=0.15, linewidth=0)
    ax.axhline(0.9, color="0.5", linestyle=":", linewidth=1)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlim(0.0, len(next(iter(results["algorithms"].values()))["dr"]) * period)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("discovery rate DR$_t$ (association rule)")
    r2 = results["pod"]["r2"]
    ax.set_title(run_title(results, name) + ("" if r2 is None else f", POD R² {r2:.3f}"), fontsize=10)
    ax.grid(True, linestyle=":", linewidth=0.6)
    ax.legend(loc="lower right", fontsize=9)
    fig.tight_layout()
    return fig


_BUILTIN_STYLES = ("-", "--", "-.", ":")  # one per registry.BUILTINS, in order
_OTHER_STYLE = (0, (6, 1.5, 1, 1.5, 1, 1.5))  # any other policy: dash-dot-dot


def _line_style(algorithm: str) -> Any:
    return _BUILTIN_STYLES[BUILTINS.index(algorithm)] if algorithm in BUILTINS else _OTHER_STYLE


def overlay_figure(runs: list[tuple[str, dict[str, Any]]], title: str = "") -> Figure:
    """DR_t of several campaigns on one axis (``runs``: (label, results object) pairs): one
    colour per campaign, one line style per algorithm, each with its Wilson 95 % band."""
    fig = _figure(figsize=(7.6, 4.6), dpi=120)
    ax = fig.subplots()
    colours = [f"C{i % 10}" for i in range(len(runs))]
    x_max = 0.0
    for colour, (label, results) in zip(colours, runs):
        period = results["scenario"]["rf_period_s"]
        for algorithm, block in results["algorithms"].items():
            dr = block["dr"]
            t = [(i + 1) * period for i in range(len(dr))]
            x_max = max(x_max, len(dr) * period)
            ax.plot(t, dr, color=colour, linestyle=_line_style(algorithm), linewidth=1.6,
                    label=f"{label}, {LABELS.get(algorithm, algorithm)} (final {block['dr_final']:.3f})")
            ax.fill_between(t, [b[0] for b in block["dr_ci95"]], [b[1] for b in block["dr_ci95"]], color=colour, alpha=0.08,
                            linewidth=0)
    ax.axhline(0.9, color="0.5", linestyle=":", linewidth=1)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlim(0.0, x_max or 1.0)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("discovery rate DR$_t$ (association rule)")
    if title:
        ax.set_title(title, fontsize=10)
    ax.grid(True, linestyle=":", linewidth=0.6)
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    return fig


def write_overlay_plot(runs: list[tuple[str, dict[str, Any]]], title: str, path: str) -> None:
    """Write ``overlay_figure`` to ``path`` (.png or .svg)."""
    fmt = "svg" if str(path).lower().endswith(".svg") else "png"
    write_bytes(draw(lambda: overlay_figure(runs, title), fmt), path)


def reliability_figure(results: dict[str, Any], name: str | None = None) -> Figure:
    """Reliability diagram of the final confidences: per bin, the share of final hits against
    the mean confidence, one line per algorithm (the diagonal is perfect calibration); ECE in
    the legend."""
    fig = _figure(figsize=(5.6, 5.0), dpi=120)
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1], color="0.6", linestyle=":", linewidth=1, label="perfectly calibrated")
    colour = colours(results["algorithms"])
    for algorithm, block in results["algorithms"].items():
        cal = block.get("calibration")
        if not cal:
            continue
        pts = [(b["confidence"], b["accuracy"], b["n"]) for b in cal.get("reliability", []) if b["n"]]
        if not pts:
            continue
        x, y, n = zip(*pts)
        line = ax.plot(x, y, marker="o", linewidth=1.5, label=f"{LABELS.get(algorithm, algorithm)} (ECE {cal['ece_final']:.3f})",
                       color=colour[algorithm])[0]
        total = sum(n)
        ax.scatter(x, y, s=[20 + 300 * k / total for k in n], color=line.get_color(), alpha=0.35)
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("confidence in the final answer")
    ax.set_ylabel("share of final answers that are the Tx")
    ax.set_title(run_title(results, name), fontsize=10)
    ax.grid(True, linestyle=":", linewidth=0.6)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    return fig


def pod_figure(scenario: Scenario, model: dict[str, Any], truth: dict[str, Any] | None, title: str = "") -> Figure:
    """The learned POD p_hat_D(r) (mean and 95 % band) against the true p_D(g^-1(r)) (paper Fig. 3).

    Parameters
    ----------
    model : dict
        A ``PODModel`` as JSON data: ``rssi_grid_dbm``, ``mean``, ``std`` of shape (M,).
    truth : dict or None
        The training episode's truth, ``rssi_dbm`` and ``pod`` of shape (n_train,): the
        noiseless iso RSSI of each training sample and the true p_D there.
    """
    grid = np.asarray(model["rssi_grid_dbm"], dtype=float)
    mean = np.asarray(model["mean"], dtype=float)
    std = np.asarray(model["std"], dtype=float)
    fig = _figure(figsize=(7.0, 4.6), dpi=120)
    ax = fig.subplots()
    if truth is not None:
        r = np.asarray(truth["rssi_dbm"], dtype=float)
        p = np.asarray(truth["pod"], dtype=float)
        if r.size > MAX_SCATTER:
            keep = np.linspace(0, r.size - 1, MAX_SCATTER).astype(int)
            r, p = r[keep], p[keep]
        ax.scatter(r, p, s=7, color="tab:orange", alpha=0.6, linewidths=0, zorder=3,
                   label=f"training samples: true p$_D$ at their true RSSI (n={len(truth['rssi_dbm'])})")
        ax.plot(r, np.full(r.size, -0.01), "|", color="tab:orange", alpha=0.3, markersize=6)  # where the samples are
        lo_r, hi_r = min(grid[0], float(r.min())), max(grid[-1], float(r.max()))
    else:
        lo_r, hi_r = grid[0], grid[-1]
    dense = np.linspace(lo_r, hi_r, 400)
    ax.plot(dense, physics.pod_of_rssi(scenario, dense), color="black", linewidth=1.6, label="true p$_D$(r) (eq. 22)")
    line = ax.plot(grid, mean, color="tab:blue", linewidth=1.8, label="learned $\\hat p_D$(r), mean")[0]
    ax.fill_between(grid, np.clip(mean - 2 * std, 0, 1), np.clip(mean + 2 * std, 0, 1), color=line.get_color(), alpha=0.2,
                    linewidth=0, label="learned, ±2 std")
    ax.set_xlim(lo_r, hi_r)
    ax.set_ylim(-0.03, 1.02)
    ax.set_xlabel("iso RSSI r [dBm]")
    ax.set_ylabel("probability of detection")
    ax.set_title(title or "POD regression")
    ax.grid(True, linestyle=":", linewidth=0.6)
    ax.legend(loc="upper left", fontsize=8)
    fig.text(0.01, 0.01, "Points: the truth at each training sample (noiseless RSSI, true p_D); the noisy labels the learner "
             "fitted are not kept by the orchestrator.", fontsize=7, color="0.35")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return fig


def _unwrapped_for_plot(deg: np.ndarray) -> np.ndarray:
    """Angles in degrees with NaN inserted where consecutive values jump across ±180°, so a
    line does not cross the whole axis."""
    out = np.asarray(deg, dtype=float).copy()
    jumps = np.flatnonzero(np.abs(np.diff(out)) > 180.0)
    return np.insert(out, jumps + 1, np.nan)


def _times_for_plot(t: np.ndarray, deg: np.ndarray) -> np.ndarray:
    jumps = np.flatnonzero(np.abs(np.diff(np.asarray(deg, dtype=float))) > 180.0)
    return np.insert(np.asarray(t, dtype=float), jumps + 1, np.nan)


def episode_bearings(episode: dict[str, Any], steps: int) -> np.ndarray:
    """(steps, N) bearings [rad] of every target at each step of a recorded episode: the walkers'
    recorded trajectories (``trajectories``, as the episode page animates them), the others
    held at their step-0 bearing."""
    bearings = np.asarray(episode["bearings"], dtype=float)
    out = np.tile(bearings, (max(steps, 1), 1))
    for walk in episode.get("trajectories") or []:
        path = np.asarray(walk["bearings_rad"], dtype=float)
        if path.size:
            n = min(len(out), path.size)
            out[:n, walk["index"]] = path[:n]
            out[n:, walk["index"]] = path[n - 1]
    return out


def episode_figure(scenario: Scenario, episode: dict[str, Any]) -> Figure:
    """One test: the targets seen from above with the FoV at the final estimate (left), and the
    pan angle s_t, the FoV around it and the estimate gamma_hat_t against time (right), with
    every target's bearing, the Tx's in red: a line over time for targets that walk (their
    recorded trajectory, as on the episode page), so the estimate is read against where the Tx
    was at each step; walkers are drawn where they ended, their path behind them."""
    ranges = np.asarray(episode["ranges"], dtype=float)
    tx = int(episode["tx_index"])
    pans = np.degrees(np.asarray(episode["pans"], dtype=float))
    est = np.degrees(np.asarray(episode["estimates"], dtype=float))
    hits = np.asarray(episode["hits"], dtype=bool)
    period = scenario.rf_period_s
    t = (np.arange(len(est)) + 1) * period
    fov = scenario.fov_half_angle_deg
    track = episode_bearings(episode, len(est))  # (T, N) rad
    walks = {w["index"]: w for w in episode.get("trajectories") or []}
    ranges_now = ranges.copy()
    for i, w in walks.items():
        if w.get("ranges_m"):
            ranges_now[i] = w["ranges_m"][min(len(est), len(w["ranges_m"])) - 1]
    bearings = track[-1]

    fig = _figure(figsize=(11.0, 4.6), dpi=110)
    grid = fig.add_gridspec(1, 2, width_ratios=(1.0, 1.7))
    top = fig.add_subplot(grid[0, 0], projection="polar")
    for i, w in walks.items():
        n = min(len(est), len(w["bearings_rad"]), len(w.get("ranges_m") or []))
        if n:
            top.plot(w["bearings_rad"][:n], w["ranges_m"][:n], color="tab:red" if i == tx else "0.7", linewidth=0.9,
                     alpha=0.8 if i == tx else 0.6, label="Tx path" if i == tx else None)
    others = np.arange(len(bearings)) != tx
    top.scatter(bearings[others], ranges_now[others], s=22, color="0.45", label="targets")
    top.scatter([bearings[tx]], [ranges_now[tx]], s=110, marker="*", color="tab:red", label="Tx", zorder=3)
    rmax = float(max(ranges_now.max(), ranges.max(), 1.0)) * 1.1
    final = math.radians(float(est[-1]))
    wedge = np.linspace(final - math.radians(fov), final + math.radians(fov), 30)
    top.fill_between(wedge, 0, rmax, color="tab:blue", alpha=0.15, label="FoV at final $\\hat\\gamma$")
    top.plot([final, final], [0, rmax], color="tab:blue", linewidth=1.4)
    top.set_rmax(rmax)
    top.set_title("targets at the last step (range m, bearing)" if walks else "targets (range m, bearing)", fontsize=9)
    top.legend(loc="lower left", bbox_to_anchor=(-0.15, -0.18), fontsize=7, ncol=3, frameon=False)

    ax = fig.add_subplot(grid[0, 1])
    deg = np.degrees(track)
    for i in range(track.shape[1]):
        if i == tx:
            continue
        if i in walks:
            ax.plot(_times_for_plot(t, deg[:, i]), _unwrapped_for_plot(deg[:, i]), color="0.8", linewidth=0.7)
        else:
            ax.axhline(deg[0, i], color="0.8", linewidth=0.7)
    if tx in walks:
        ax.plot(_times_for_plot(t, deg[:, tx]), _unwrapped_for_plot(deg[:, tx]), color="tab:red", linewidth=1.4,
                label="Tx bearing (walking)")
    else:
        ax.axhline(float(deg[0, tx]), color="tab:red", linewidth=1.4, label="Tx bearing")
    ax.fill_between(t, pans - fov, pans + fov, step="mid", color="tab:green", alpha=0.12, linewidth=0, label="FoV at s$_t$")
    ax.plot(t, pans, ".", color="tab:green", markersize=3.5, label="pan angle s$_t$")
    ax.plot(_times_for_plot(t, est), _unwrapped_for_plot(est), color="tab:blue", linewidth=1.5, label="estimate $\\hat\\gamma_t$")
    if hits.any():
        ax.plot(t[hits], np.full(int(hits.sum()), 178.0), "|", color="tab:red", markersize=5, label="î$_t$ = Tx")
    ax.set_ylim(-180, 180)
    ax.set_yticks(range(-180, 181, 45))
    ax.set_xlim(0, len(est) * period)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("angle [deg]")
    ax.grid(True, linestyle=":", linewidth=0.5)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=7)
    verdict = "found" if hits.size and hits[-1] else "missed"
    fig.suptitle(f"test {episode['test_index']}, {LABELS.get(episode['algorithm'], episode['algorithm'])}: Tx {verdict} "
                 f"(target {tx} of {len(bearings)})", fontsize=11)
    fig.tight_layout()
    return fig


METRIC_LABELS = {"dr_final": "final discovery rate DR (association rule)", "time_to_dr90_s": "time to DR ≥ 0.9 [s]",
                 "in_fov_final": "Tx in FoV at the final estimate", "pod_r2": "POD regression R²",
                 "calibration_ece_final": "ECE of the final confidence",
                 "calibration_ece_final_floor": "ECE floor (if calibrated)", "calibration_ece_all": "ECE over every step",
                 "calibration_confidence_final": "mean final confidence", "decision_accuracy": "accuracy of early decisions",
                 "decision_median_s": "median time to decision [s]", "decision_p90_s": "90th percentile time to decision [s]",
                 "decision_undecided": "share undecided at the horizon"}


NEVER_REACHED = {"time_to_dr90_s": "never"}  # metrics whose null means the level was never reached, and the cell's label


def band_fields(metric: str) -> tuple[str, str] | None:
    """The row fields of a metric's 95 % interval: ``ci95_lo``/``ci95_hi`` for the final DR,
    ``<metric>_ci95_lo``/``_hi`` for a metric that reports one (e.g. ``decision_accuracy``)."""
    if metric == "dr_final":
        return "ci95_lo", "ci95_hi"
    return f"{metric}_ci95_lo", f"{metric}_ci95_hi"


def _ordered(values: list[Any]) -> list[Any]:
    """The distinct values in grid order (numbers sorted, anything else as first met)."""
    distinct = list(dict.fromkeys(values))
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in distinct):
        return sorted(distinct)
    return distinct


def study_figure(results: dict[str, Any], metric: str = "dr_final") -> Figure:
    """A study's ``metric`` against its varied parameter: one line per algorithm with its Wilson
    95 % band where the metric has one (numeric parameters on a numeric axis, others as
    categories); with two varied parameters a heat map per algorithm (first parameter on y).

    Raises
    ------
    ValueError
        More than two varied parameters, or no row with a value of ``metric``.
    """
    params = results["parameters"]
    rows = [r for r in results["rows"] if r.get(metric) is not None]
    # a row whose metric is null because the level was never reached (t90 of a DR that ends
    # below 0.9) is a result, not a hole: its heat-map cell says "never"
    never = [r for r in results["rows"] if metric in NEVER_REACHED and metric in r and r[metric] is None]
    if len(params) > 2:
        raise ValueError(f"a study figure shows one or two varied parameters; this study varies {len(params)}")
    if not rows and not (never and len(params) == 2):
        raise ValueError(f"no point reports {metric} yet")
    algorithms = [a for a in results["algorithms"] if any(r["algorithm"] == a for r in rows)]
    label = METRIC_LABELS.get(metric, metric)
    title = (f"{results['preset']}: {label}, {results['tests']} tests per point, seed {results['seed']}"
             + (" (partial)" if results.get("partial") else ""))
    if len(params) == 1:
        (name,) = params
        xs = _ordered([r[name] for r in rows])
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in xs)
        fig = _figure(figsize=(7.0, 4.2), dpi=120)
        ax = fig.subplots()
        lo_key, hi_key = band_fields(metric)
        colour = colours(results["algorithms"])
        for a in algorithms:
            mine = {r[name]: r for r in rows if r["algorithm"] == a}
            pts = [(x if numeric else i, mine[x]) for i, x in enumerate(xs) if x in mine]
            x = [p[0] for p in pts]
            line = ax.plot(x, [p[1][metric] for p in pts], marker="o", linewidth=1.8, label=LABELS.get(a, a),
                           color=colour[a])[0]
            if all(p[1].get(lo_key) is not None and p[1].get(hi_key) is not None for p in pts):
                ax.fill_between(x, [p[1][lo_key] for p in pts], [p[1][hi_key] for p in pts], color=line.get_color(), alpha=0.15,
                                linewidth=0)
        if not numeric:
            ax.set_xticks(range(len(xs)), [str(v) for v in xs])
        if metric in ("dr_final", "in_fov_final", "decision_accuracy") or metric.endswith("_final") and "ece" not in metric:
            ax.set_ylim(0.0, 1.02)
        ax.set_xlabel(name)
        ax.set_ylabel(label)
        ax.set_title(title, fontsize=10)
        ax.grid(True, linestyle=":", linewidth=0.6)
        ax.legend(fontsize=9)
        fig.tight_layout()
        return fig
    ny, nx = params
    algorithms = [a for a in results["algorithms"] if any(r["algorithm"] == a for r in rows + never)]
    ys, xs = _ordered([r[ny] for r in rows + never]), _ordered([r[nx] for r in rows + never])
    values = [r[metric] for r in rows] or [0.0, 1.0]
    vmin, vmax = (0.0, 1.0) if metric in ("dr_final", "in_fov_final") else (min(values), max(values))
    from matplotlib.patches import Rectangle

    fig = _figure(figsize=(3.2 * len(algorithms) + 1.4, max(3.6, 0.35 * len(ys) + 2.6)), dpi=120, layout="constrained")
    axes = fig.subplots(1, len(algorithms), squeeze=False)[0]
    image = None
    for ax, a in zip(axes, algorithms):
        grid = np.full((len(ys), len(xs)), np.nan)
        for r in rows:
            if r["algorithm"] == a:
                grid[ys.index(r[ny]), xs.index(r[nx])] = r[metric]
        image = ax.imshow(grid, origin="lower", aspect="auto", vmin=vmin, vmax=vmax, cmap="viridis")
        for r in never:
            if r["algorithm"] == a:
                i, j = ys.index(r[ny]), xs.index(r[nx])
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, facecolor="0.88", edgecolor="0.6", hatch="//", linewidth=0.5))
                ax.text(j, i, NEVER_REACHED[metric], ha="center", va="center", fontsize=7, color="black")
        ax.set_xticks(range(len(xs)), [f"{v:g}" if isinstance(v, float) else str(v) for v in xs], fontsize=8)
        ax.set_yticks(range(len(ys)), [f"{v:g}" if isinstance(v, float) else str(v) for v in ys], fontsize=8)
        if len(xs) * len(ys) <= 64:
            for (i, j), v in np.ndenumerate(grid):
                if not np.isnan(v):
                    ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=7,
                            color="white" if v < vmin + 0.5 * (vmax - vmin) else "black")
        ax.set_title(LABELS.get(a, a), fontsize=10)
        ax.set_xlabel(nx)
    axes[0].set_ylabel(ny)
    if image is not None:
        fig.colorbar(image, ax=list(axes), label=label, shrink=0.9)
    if any(r["algorithm"] in algorithms for r in never):
        title += "\nnever: DR does not stay at 0.9 or more by the end of the test"
    fig.suptitle(title, fontsize=10)
    return fig


def render(fig: Figure, fmt: str = "png") -> bytes:
    """The figure as PNG or SVG bytes."""
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    buf = io.BytesIO()
    with _RENDER_LOCK:
        fig.savefig(buf, format=fmt)
    return buf.getvalue()


def draw(build: Callable[[], Figure], fmt: str = "png") -> bytes:
    """Build a figure and render it, both under the render lock (text layout in matplotlib
    uses shared caches)."""
    with _RENDER_LOCK:
        return render(build(), fmt)


PlotKind = Literal["dr", "pod", "episode", "reliability", "study"]


@dataclass(frozen=True)
class PlotJob:
    """One figure to draw, as plain picklable data (what a renderer process receives).

    ``data`` by ``kind``:

    * ``"dr"``, ``"reliability"``: ``results`` (the results object of a finished campaign) and
      optionally ``name`` (the campaign's name, for the title);
    * ``"pod"``: ``scenario`` (Scenario as JSON data), ``model`` (PODModel as JSON data),
      ``truth`` (``{"rssi_dbm", "pod"}`` or None), ``title``;
    * ``"episode"``: ``scenario`` and ``episode`` (a finished episode row);
    * ``"study"``: ``results`` (a study's results object) and ``metric`` (a field of its rows).
    """

    kind: PlotKind
    fmt: str
    data: dict[str, Any]


def build_figure(job: PlotJob) -> Figure:
    """The figure a job describes."""
    d = job.data
    if job.kind == "dr":
        return dr_figure(d["results"], d.get("name"))
    if job.kind == "reliability":
        return reliability_figure(d["results"], d.get("name"))
    if job.kind == "pod":
        return pod_figure(Scenario.model_validate(d["scenario"]), d["model"], d["truth"], d.get("title", ""))
    if job.kind == "episode":
        return episode_figure(Scenario.model_validate(d["scenario"]), d["episode"])
    if job.kind == "study":
        return study_figure(d["results"], d["metric"])
    raise ValueError(f"unknown figure kind {job.kind!r}")


def draw_job(job: PlotJob) -> bytes:
    """Build and render the figure of ``job`` (PNG or SVG bytes)."""
    return draw(lambda: build_figure(job), job.fmt)


def write_dr_plot(results: dict[str, Any], path: str) -> None:
    """Write the DR figure to ``path``; the format follows the extension (.png or .svg)."""
    fmt = "svg" if str(path).lower().endswith(".svg") else "png"
    write_bytes(draw(lambda: dr_figure(results), fmt), path)


def write_reliability_plot(results: dict[str, Any], path: str) -> None:
    """Write the reliability diagram to ``path`` (.png or .svg)."""
    fmt = "svg" if str(path).lower().endswith(".svg") else "png"
    write_bytes(draw(lambda: reliability_figure(results), fmt), path)


def write_study_plot(results: dict[str, Any], metric: str, path: str) -> None:
    """Write a study's figure of ``metric`` to ``path`` (.png or .svg)."""
    fmt = "svg" if str(path).lower().endswith(".svg") else "png"
    write_bytes(draw(lambda: study_figure(results, metric), fmt), path)


def write_bytes(data: bytes, path: str) -> None:
    """Write ``data`` to ``path`` through a temporary file: never leaves a half-written file."""
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)
