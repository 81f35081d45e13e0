"""The results object as CSV, self-contained: ``write_results_csv`` and its inverse.

Format (UTF-8, ``\\n`` line ends)::

    # ra2vipas results (CSV v1)
    # campaign_id: "3f2a9c0d1b7e"
    # preset: "paper"
    # tests: 50
    # seed: 1
    # algorithms: ["ra2vipas","rapas","ravipas","sweep"]
    # scenario: {"rf_period_s":0.1,"frames_per_rf":10,...every parameter...}
    # pod: {"r2":0.988,"train_seconds":0.31}
    # summary: {"ra2vipas":{"dr_final":0.99,"ci95":[0.96,0.99],"time_to_dr90_s":1.1,"in_fov_final":1.0},...}
    algorithm,step,time_s,dr,ci_lo,ci_hi
    ra2vipas,1,0.1,0.5,0.3,0.7
    ...

Header lines are ``# key: <JSON>``; then one row per (algorithm, step) with the discovery
rate DR_t and its Wilson 95 % interval. The scenario (every parameter) and the seed are in the
file, so ``ra2vipas simulate --tests N --seed S --set NAME=VALUE ...`` (one ``--set`` per
scenario parameter) reproduces it.
"""

from __future__ import annotations

import csv
import io
import json
from typing import Any

HEADER = ("algorithm", "step", "time_s", "dr", "ci_lo", "ci_hi")
_SUMMARY_KEYS = ("dr_final", "ci95", "time_to_dr90_s", "in_fov_final")


def write_results_csv(results: dict[str, Any], campaign_id: str | None = None) -> str:
    period = results["scenario"]["rf_period_s"]
    meta = {
        "campaign_id": campaign_id,
        "preset": results["preset"],
        "tests": results["tests"],
        "seed": results["seed"],
        "algorithms": list(results["algorithms"]),
        "scenario": results["scenario"],
        "pod": results["pod"],
        "summary": {name: {k: block[k] for k in _SUMMARY_KEYS} for name, block in results["algorithms"].items()},
    }
    out = io.StringIO()
    out.write("# ra2vipas results (CSV v1)\n")
    for key, value in meta.items():
        out.write(f"# {key}: {json.dumps(value, separators=(',', ':'))}\n")
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(HEADER)
    for name, block in results["algorithms"].items():
        for t, (dr, (lo, hi)) in enumerate(zip(block["dr"], block["dr_ci95"])):
            writer.writerow((name, t + 1, round((t + 1) * period, 10), dr, lo, hi))
    return out.getvalue()


def read_results_csv(text: str) -> dict[str, Any]:
    """Parse a file written by ``write_results_csv``: its header values and, per algorithm,
    ``dr`` and ``dr_ci95`` per step.

    Raises
    ------
    ValueError
        Not a ra2vipas results CSV.
    """
    meta: dict[str, Any] = {}
    body: list[str] = []
    for line in text.splitlines():
        if line.startswith("# "):
            key, sep, value = line[2:].partition(": ")
            if sep:
                meta[key] = json.loads(value)
        elif line.strip():
            body.append(line)
    if not body or tuple(body[0].split(",")) != HEADER or "scenario" not in meta:
        raise ValueError("not a ra2vipas results CSV")
    curves: dict[str, dict[str, list]] = {}
    for row in csv.DictReader(body):
        block = curves.setdefault(row["algorithm"], {"dr": [], "dr_ci95": []})
        block["dr"].append(float(row["dr"]))
        block["dr_ci95"].append([float(row["ci_lo"]), float(row["ci_hi"])])
    meta["curves"] = curves
    return meta
