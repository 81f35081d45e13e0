"""The results object as tidy CSV tables: ``write_results_csv`` and its inverse.

Two tables, each a plain CSV (UTF-8, ``\\n`` line ends, one header row, no comment lines, so
``pandas.read_csv(url)`` reads it as it is):

* ``dr`` (the default): one row per algorithm x step::

      campaign_id,name,preset,seed,tests,n_targets,algorithm,step,time_s,dr,ci_lo,ci_hi
      3f2a9c0d1b7e,crowd,paper,1,50,30,ra2vipas,1,0.1,0.5,0.3,0.7
      ...

  the discovery rate DR_t and its Wilson 95 % interval;
* ``summary``: one row per algorithm: the final DR and its interval, the time to DR >= 0.9,
  the in-FoV rate, the calibration (``ece_final``, ``confidence_final``) and early-decision
  fields when the results have them, the per-tag fields of a search for several tags
  (``tag_columns``), the POD R², and ``partial`` / ``tests_recorded``.

Both start with the same columns: what was run. ``campaign_id`` and ``name``, then ``preset``,
``seed`` and ``tests``, then one column per scenario parameter that differs from the preset
(the results' ``overrides``), so rows of several campaigns concatenate into one table and the
file alone reproduces the campaign: ``ra2vipas simulate --preset P --tests N --seed S --set
NAME=VALUE ...`` with one ``--set`` per override column.
"""

from __future__ import annotations

import csv
import io
from typing import Any, Literal

CURVE_COLUMNS = ("algorithm", "step", "time_s", "dr", "ci_lo", "ci_hi")
RUN_COLUMNS = ("campaign_id", "name", "preset", "seed", "tests")
Table = Literal["dr", "summary"]
TABLES = ("dr", "summary")


def run_columns(results: dict[str, Any], ids: dict[str, Any] | None = None) -> dict[str, Any]:
    """What was run, as leading columns: ``ids`` (e.g. campaign_id and name), preset, seed,
    tests, then the overrides (parameter: value)."""
    head = dict(ids or {})
    head.update(preset=results["preset"], seed=results["seed"], tests=results["tests"])
    for name, value in (results.get("overrides") or {}).items():
        if name not in head:
            head[name] = value
    return head


def curve_rows(results: dict[str, Any], ids: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """The tidy DR table: one row per algorithm x step (``run_columns`` first)."""
    head = run_columns(results, ids)
    period = results["scenario"]["rf_period_s"]
    return [{**head, "algorithm": name, "step": t + 1, "time_s": round((t + 1) * period, 10), "dr": dr, "ci_lo": lo, "ci_hi": hi}
            for name, block in results["algorithms"].items()
            for t, (dr, (lo, hi)) in enumerate(zip(block["dr"], block["dr_ci95"]))]


def summary_rows(results: dict[str, Any], ids: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """The summary table: one row per algorithm (``run_columns`` first)."""
    head = run_columns(results, ids)
    recorded = results.get("tests_recorded") or {}
    rows = []
    for name, block in results["algorithms"].items():
        row = {**head, "algorithm": name, "dr_final": block["dr_final"], "ci_lo": block["ci95"][0], "ci_hi": block["ci95"][1],
               "time_to_dr90_s": block["time_to_dr90_s"], "in_fov_final": block["in_fov_final"]}
        cal = block.get("calibration") or {}
        for key in ("ece_final", "ece_final_floor", "ece_all", "confidence_final"):
            if key in cal:
                row[key] = cal[key]
        decision = block.get("decision") or {}
        for key, value in decision.items():
            if isinstance(value, list) and len(value) == 2:  # an interval
                row[f"decision_{key}_lo"], row[f"decision_{key}_hi"] = value
            elif not isinstance(value, (list, dict)):
                row[f"decision_{key}"] = value
        row.update(tag_columns(block.get("tags")))
        row["pod_r2"] = results["pod"].get("r2")
        row["partial"] = bool(results.get("partial"))
        row["tests_recorded"] = recorded.get(name, results["tests"])
        rows.append(row)
    return rows


def tag_columns(tags: dict[str, Any] | None) -> dict[str, Any]:
    """A search for several tags (issue 21) in the summary table: the mean per-tag DR, the
    all-found rate (final, interval, time to 0.9), the time until all were decided, and per tag k
    ``tag{k}_dr_final``, its interval, ECE and median time to decision. Empty for one tag."""
    if not tags:
        return {}
    found = tags["all_found"]
    out: dict[str, Any] = {"mean_tag_dr_final": tags["mean_tag_dr_final"], "all_found_final": found["dr_final"],
                           "all_found_ci_lo": found["ci95"][0], "all_found_ci_hi": found["ci95"][1],
                           "all_found_time_to_dr90_s": found["time_to_dr90_s"]}
    for key, value in (tags.get("all_decided") or {}).items():
        out[f"all_decided_{key}"] = value
    for k, block in enumerate(tags["per_tag"]):
        out[f"tag{k}_dr_final"] = block["dr_final"]
        out[f"tag{k}_ci_lo"], out[f"tag{k}_ci_hi"] = block["ci95"]
        out[f"tag{k}_ece_final"] = (block.get("calibration") or {}).get("ece_final")
        if "decision" in block:
            out[f"tag{k}_decided_median_s"] = block["decision"].get("median_s")
    return out


def write_rows(rows: list[dict[str, Any]]) -> str:
    """Rows as CSV: the columns are the union of the rows' keys in order of first appearance;
    None is an empty cell."""
    columns: dict[str, None] = {}
    for row in rows:
        columns.update(dict.fromkeys(row))
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=list(columns), lineterminator="\n", restval="")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
    return out.getvalue()


def write_results_csv(results: dict[str, Any], campaign_id: str | None = None, name: str | None = None,
                      table: Table = "dr") -> str:
    """The ``dr`` or ``summary`` table of a results object as CSV text."""
    ids = {"campaign_id": campaign_id, "name": name}
    return write_rows(summary_rows(results, ids) if table == "summary" else curve_rows(results, ids))


def read_results_csv(text: str) -> dict[str, Any]:
    """Parse a ``dr`` table written by ``write_results_csv``: what was run (campaign_id, name,
    preset, seed, tests, the typed ``overrides`` and the resolved ``scenario``), the algorithms
    in order, and per algorithm ``dr`` and ``dr_ci95`` per step (``curves``).

    Raises
    ------
    ValueError
        Not a ra2vipas DR table (or its overrides are not valid for its preset).
    """
    from ra2vipas.services.protocol.scenario import build_scenario, parse_overrides

    rows = list(csv.DictReader(io.StringIO(text)))
    fields = list(rows[0]) if rows else []
    if not rows or fields[:len(RUN_COLUMNS)] != list(RUN_COLUMNS) or fields[-len(CURVE_COLUMNS):] != list(CURVE_COLUMNS):
        raise ValueError("not a ra2vipas results CSV (the dr table)")
    first = rows[0]
    params = fields[len(RUN_COLUMNS):-len(CURVE_COLUMNS)]
    overrides = parse_overrides([f"{p}={first[p]}" for p in params])
    curves: dict[str, dict[str, list]] = {}
    for row in rows:
        block = curves.setdefault(row["algorithm"], {"dr": [], "dr_ci95": []})
        block["dr"].append(float(row["dr"]))
        block["dr_ci95"].append([float(row["ci_lo"]), float(row["ci_hi"])])
    return {
        "campaign_id": first["campaign_id"] or None, "name": first["name"] or None, "preset": first["preset"],
        "seed": int(first["seed"]), "tests": int(first["tests"]), "overrides": overrides,
        "scenario": build_scenario(first["preset"], overrides).model_dump(mode="json"),
        "algorithms": list(curves), "curves": curves,
    }
