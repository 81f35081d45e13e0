"""Server-side figures (matplotlib, headless, PNG or SVG).

* ``dr_figure``: the DR curves of every algorithm with Wilson 95 % bands (paper Fig. 4);
* ``pod_figure``: the learned POD p_hat_D(r) against the true p_D(r) (paper Fig. 3);
* ``episode_figure``: one test of one algorithm: the targets, the FoV, the pan trajectory and
  the estimate gamma_hat_t over time.

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
from typing import Any, Callable, Literal

import numpy as np
from matplotlib.figure import Figure

from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.sensors import physics

LABELS = {"ra2vipas": "Ra²ViPAS", "rapas": "RaPAS", "ravipas": "RaViPAS", "sweep": "sweep (non-active)"}
FORMATS = ("png", "svg")
MEDIA_TYPES = {"png": "image/png", "svg": "image/svg+xml"}
MAX_SCATTER = 3000  # truth points drawn in the POD figure (a uniform subsample beyond this)

_RENDER_LOCK = threading.RLock()


def dr_figure(results: dict[str, Any]) -> Figure:
    """DR_t of every algorithm against time, with its Wilson 95 % band (paper Fig. 4)."""
    period = results["scenario"]["rf_period_s"]
    fig = Figure(figsize=(7.0, 4.2), dpi=120)
    ax = fig.subplots()
    for name, block in results["algorithms"].items():
        dr = block["dr"]
        t = [(i + 1) * period for i in range(len(dr))]
        line = ax.plot(t, dr, label=f"{LABELS.get(name, name)} (final {block['dr_final']:.3f})", linewidth=1.8)[0]
        lo = [b[0] for b in block["dr_ci95"]]
        hi = [b[1] for b in block["dr_ci95"]]
        ax.fill_between(t, lo, hi, color=line.get_color(), alpha=0.15, linewidth=0)
    ax.axhline(0.9, color="0.5", linestyle=":", linewidth=1)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlim(0.0, len(next(iter(results["algorithms"].values()))["dr"]) * period)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("discovery rate DR$_t$ (association rule)")
    r2 = results["pod"]["r2"]
    ax.set_title(f"{results['preset']}: {results['tests']} tests, seed {results['seed']}"
                 + ("" if r2 is None else f", POD R² {r2:.3f}"))
    ax.grid(True, linestyle=":", linewidth=0.6)
    ax.legend(loc="lower right", fontsize=9)
    fig.tight_layout()
    return fig


def reliability_figure(results: dict[str, Any]) -> Figure:
    """Reliability diagram of the final confidences: per bin, the share of final hits against
    the mean confidence, one line per algorithm (the diagonal is perfect calibration); ECE in
    the legend."""
    fig = Figure(figsize=(5.6, 5.0), dpi=120)
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1], color="0.6", linestyle=":", linewidth=1, label="perfectly calibrated")
    for name, block in results["algorithms"].items():
        cal = block.get("calibration")
        if not cal:
            continue
        pts = [(b["confidence"], b["accuracy"], b["n"]) for b in cal.get("reliability", []) if b["n"]]
        if not pts:
            continue
        x, y, n = zip(*pts)
        line = ax.plot(x, y, marker="o", linewidth=1.5, label=f"{LABELS.get(name, name)} (ECE {cal['ece_final']:.3f})")[0]
        total = sum(n)
        ax.scatter(x, y, s=[20 + 300 * k / total for k in n], color=line.get_color(), alpha=0.35)
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("confidence in the final answer")
    ax.set_ylabel("share of final answers that are the Tx")
    ax.set_title(f"{results['preset']}: {results['tests']} tests, seed {results['seed']}")
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
    fig = Figure(figsize=(7.0, 4.6), dpi=120)
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


def episode_figure(scenario: Scenario, episode: dict[str, Any]) -> Figure:
    """One test: the targets seen from above with the FoV at the final estimate (left), and the
    pan angle s_t, the FoV around it and the estimate gamma_hat_t against time (right)."""
    bearings = np.asarray(episode["bearings"], dtype=float)
    ranges = np.asarray(episode["ranges"], dtype=float)
    tx = int(episode["tx_index"])
    pans = np.degrees(np.asarray(episode["pans"], dtype=float))
    est = np.degrees(np.asarray(episode["estimates"], dtype=float))
    hits = np.asarray(episode["hits"], dtype=bool)
    period = scenario.rf_period_s
    t = (np.arange(len(est)) + 1) * period
    fov = scenario.fov_half_angle_deg

    fig = Figure(figsize=(11.0, 4.6), dpi=110)
    grid = fig.add_gridspec(1, 2, width_ratios=(1.0, 1.7))
    top = fig.add_subplot(grid[0, 0], projection="polar")
    others = np.arange(len(bearings)) != tx
    top.scatter(bearings[others], ranges[others], s=22, color="0.45", label="targets")
    top.scatter([bearings[tx]], [ranges[tx]], s=110, marker="*", color="tab:red", label="Tx", zorder=3)
    rmax = float(max(ranges.max(), 1.0)) * 1.1
    final = math.radians(float(est[-1]))
    wedge = np.linspace(final - math.radians(fov), final + math.radians(fov), 30)
    top.fill_between(wedge, 0, rmax, color="tab:blue", alpha=0.15, label="FoV at final $\\hat\\gamma$")
    top.plot([final, final], [0, rmax], color="tab:blue", linewidth=1.4)
    top.set_rmax(rmax)
    top.set_title("targets (range m, bearing)", fontsize=9)
    top.legend(loc="lower left", bbox_to_anchor=(-0.15, -0.18), fontsize=7, ncol=3, frameon=False)

    ax = fig.add_subplot(grid[0, 1])
    for i, b in enumerate(np.degrees(bearings)):
        if i != tx:
            ax.axhline(b, color="0.8", linewidth=0.7)
    ax.axhline(float(np.degrees(bearings[tx])), color="tab:red", linewidth=1.4, label="Tx bearing")
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


PlotKind = Literal["dr", "pod", "episode", "reliability"]


@dataclass(frozen=True)
class PlotJob:
    """One figure to draw, as plain picklable data (what a renderer process receives).

    ``data`` by ``kind``:

    * ``"dr"``, ``"reliability"``: ``results`` (the results object of a finished campaign);
    * ``"pod"``: ``scenario`` (Scenario as JSON data), ``model`` (PODModel as JSON data),
      ``truth`` (``{"rssi_dbm", "pod"}`` or None), ``title``;
    * ``"episode"``: ``scenario`` and ``episode`` (a finished episode row).
    """

    kind: PlotKind
    fmt: str
    data: dict[str, Any]


def build_figure(job: PlotJob) -> Figure:
    """The figure a job describes."""
    d = job.data
    if job.kind == "dr":
        return dr_figure(d["results"])
    if job.kind == "reliability":
        return reliability_figure(d["results"])
    if job.kind == "pod":
        return pod_figure(Scenario.model_validate(d["scenario"]), d["model"], d["truth"], d.get("title", ""))
    if job.kind == "episode":
        return episode_figure(Scenario.model_validate(d["scenario"]), d["episode"])
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


def write_bytes(data: bytes, path: str) -> None:
    """Write ``data`` to ``path`` through a temporary file: never leaves a half-written file."""
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)
