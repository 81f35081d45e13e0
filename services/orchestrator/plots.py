"""Server-side figures (matplotlib, headless): the DR curves of the paper's Fig. 4 with
Wilson 95 % bands."""

from __future__ import annotations

import io
import os
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

LABELS = {"ra2vipas": "Ra²ViPAS", "rapas": "RaPAS", "ravipas": "RaViPAS", "sweep": "sweep (non-active)"}


def dr_figure(results: dict[str, Any]):
    """DR_t of every algorithm against time, with its Wilson 95 % band."""
    period = results["scenario"]["rf_period_s"]
    fig, ax = plt.subplots(figsize=(7.0, 4.2), dpi=120)
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
    ax.set_title(f"{results['preset']}: {results['tests']} tests, seed {results['seed']}, POD R² {results['pod']['r2']:.3f}")
    ax.grid(True, linestyle=":", linewidth=0.6)
    ax.legend(loc="lower right", fontsize=9)
    fig.tight_layout()
    return fig


def render(fig, fmt: str = "png") -> bytes:
    """The figure as PNG or SVG bytes; the figure is closed."""
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt)
    plt.close(fig)
    return buf.getvalue()


def write_dr_plot(results: dict[str, Any], path: str) -> None:
    """Write the DR figure to ``path``; the format follows the extension (.png or .svg)."""
    fmt = "svg" if str(path).lower().endswith(".svg") else "png"
    data = render(dr_figure(results), fmt)
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)  # never leaves a half-written file behind
