"""Shared printing for the CLI: rich tables for people, one JSON line for scripts, and the
single-line error convention (exit 1 for a failed operation, 2 for bad usage)."""

from __future__ import annotations

import json
import shutil
import sys
from typing import Any, NoReturn

import typer
from rich.console import Console
from rich.table import Table

_WIDTH = max(shutil.get_terminal_size((120, 24)).columns, 100)  # pipes and CI logs get 120 columns
stdout = Console(width=_WIDTH)
stderr = Console(stderr=True)

EXIT_FAILED = 1
EXIT_USAGE = 2

REPORT_TIMES_S = (1.0, 2.0, 4.0, 8.0, 12.0)


def fail(message: str, code: int = EXIT_FAILED) -> NoReturn:
    """Print ``error: message`` on one stderr line and exit with ``code``."""
    print(f"error: {message}", file=sys.stderr)
    raise typer.Exit(code)


def print_json(obj: Any) -> None:
    """The object as one compact JSON line on stdout (the last line scripts parse)."""
    sys.stdout.write(json.dumps(obj, separators=(",", ":")) + "\n")
    sys.stdout.flush()


def dr_table(results: dict[str, Any]) -> Table:
    """DR at 1, 2, 4, 8, 12 s (those within the test), final Wilson interval, time to 0.9, in-FoV."""
    period = results["scenario"]["rf_period_s"]
    steps = results["scenario"]["steps"]
    times = [t for t in REPORT_TIMES_S if round(t / period) <= steps]
    if not times or abs(times[-1] - steps * period) > 1e-9:
        times.append(round(steps * period, 6))
    table = Table(title=f"Discovery rate DR_t, {results['preset']} ({results['tests']} tests, seed {results['seed']})")
    table.add_column("algorithm", no_wrap=True)
    for t in times:
        table.add_column(f"{t:g} s", justify="right")
    table.add_column("95% CI", justify="right", no_wrap=True)
    table.add_column("t90", justify="right")
    table.add_column("in-FoV", justify="right")
    for name, block in results["algorithms"].items():
        dr = block["dr"]
        cells = [f"{dr[max(0, min(len(dr), round(t / period)) - 1)]:.3f}" for t in times]
        lo, hi = block["ci95"]
        t90 = block["time_to_dr90_s"]
        table.add_row(name, *cells, f"{lo:.3f}–{hi:.3f}", "—" if t90 is None else f"{t90:g} s", f"{block['in_fov_final']:.3f}")
    return table


def print_results(results: dict[str, Any]) -> None:
    stdout.print(dr_table(results))
    pod = results["pod"]
    line = f"POD regression R² {pod['r2']:.4f} (trained in {pod['train_seconds']:.2f} s)"
    if results.get("steps_per_second"):
        line += f"; {results['steps_per_second']:.0f} control steps/s"
    stdout.print(line)
    stdout.print(
        "DR: paper's association rule (eq. 11) at each time; 95% CI: Wilson interval of the final DR; "
        "t90: time after which DR stays >= 0.9; in-FoV: Tx inside the FoV at the final estimate (secondary)."
    )
