"""What the dashboard's pages show, from database rows and results objects (pure functions and
one small accumulator; no FastAPI, no templates)."""

from __future__ import annotations

import math
import threading
from enum import Enum
from typing import Any

import numpy as np

from ra2vipas.services.orchestrator.api.views import outcome_public, trace_public
from ra2vipas.services.orchestrator.metrics import Z95
from ra2vipas.services.orchestrator.names import label, web_colours
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.protocol.angles import wrap
from ra2vipas.services.protocol.scenario import Scenario, build_scenario, field_range

MAX_POINTS = 600  # points per curve sent to a page (a longer curve is subsampled evenly, its last point kept)


def subsample(n: int, max_points: int = MAX_POINTS) -> np.ndarray:
    """Indices of at most ``max_points`` evenly spaced steps of ``n``, the last one included."""
    if n <= max_points:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_points).round().astype(int))


# -- scenario ------------------------------------------------------------------------------------

def scenario_rows(preset: str, scenario: dict[str, Any], overrides: dict[str, Any]) -> list[dict[str, Any]]:
    """Every parameter of a campaign's scenario, with the preset's value beside it and whether
    the campaign changed it (an override, or a value that differs from the preset's)."""
    try:
        base = build_scenario(preset).model_dump(mode="json")
    except ValueError:  # a preset that no longer exists: nothing to compare with
        base = {}
    rows = []
    for name, value in scenario.items():
        info = Scenario.model_fields.get(name)
        rows.append({"name": name, "value": value, "preset_value": base.get(name),
                     "changed": name in overrides or (name in base and base[name] != value),
                     "allowed": field_range(name) if info is not None else "",
                     "description": (info.description or "") if info is not None else ""})
    return rows


def parameter_inputs(preset: str) -> list[dict[str, Any]]:
    """The new-campaign form's inputs for every scenario parameter of ``preset``: its value and,
    from the scenario model, the kind of input and its bounds (open bounds marked, so the page
    refuses them as the API does)."""
    values = build_scenario(preset).model_dump(mode="json")
    out = []
    for name, info in Scenario.model_fields.items():
        item: dict[str, Any] = {"name": name, "value": values[name], "allowed": field_range(name), "description": info.description or "",
                                "min": None, "max": None, "min_open": False, "max_open": False}
        annotation = info.annotation
        if isinstance(annotation, type) and issubclass(annotation, Enum):
            item.update(kind="enum", options=[m.value for m in annotation])
        elif annotation is bool:  # a choice of the two JSON values, sent as a boolean
            item.update(kind="bool", options=["true", "false"], value="true" if values[name] else "false")
        elif annotation is str:  # a name (e.g. a channel file's): a text input, its pattern checked by the API
            item["kind"] = "text"
        else:
            item["kind"] = "int" if annotation is int else "float"
            for meta in info.metadata:
                for attr, key, is_open in (("ge", "min", False), ("gt", "min", True), ("le", "max", False), ("lt", "max", True)):
                    bound = getattr(meta, attr, None)
                    if bound is not None:
                        item[key] = bound
                        item[f"{key}_open"] = is_open
        out.append(item)
    return out


# -- results -------------------------------------------------------------------------------------

# Known fields of an algorithm's block, in the order the summary shows them, with their labels;
# any other scalar field a newer orchestrator adds is shown after them under its own name.
SUMMARY_COLUMNS = [
    ("dr_final", "final DR"),
    ("ci95", "95 % CI"),
    ("time_to_dr90_s", "t(DR ≥ 0.9) [s]"),
    ("in_fov_final", "Tx in FoV"),
    ("calibration.confidence_final", "mean final confidence"),
    ("calibration.ece_final", "ECE (final)"),
    ("calibration.ece_final_floor", "ECE if calibrated (sampling floor)"),
    ("calibration.ece_all", "ECE (all steps)"),
    ("decision.accuracy", "decision accuracy"),
    ("decision.accuracy_ci95", "its 95 % CI"),
    ("decision.median_s", "median time to decide [s]"),
    ("decision.p90_s", "p90 time to decide [s]"),
    ("decision.undecided", "undecided"),
]
_NOT_SUMMARISED = {"dr", "dr_ci95", "calibration.reliability"}


def _flatten(block: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in block.items():
        name = prefix + key
        if isinstance(value, dict):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = value
    return out


def _shown(value: Any) -> bool:
    """Scalars and [lo, hi] pairs go in the summary table; longer lists are curves."""
    return value is None or isinstance(value, (int, float, str, bool)) or (
        isinstance(value, list) and len(value) == 2 and all(isinstance(v, (int, float)) for v in value))


def fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    if isinstance(value, list):
        return "–".join(fmt(v, digits) for v in value)
    return str(value)


def summary_table(results: dict[str, Any]) -> dict[str, Any]:
    """The summary of a results object: one row per algorithm, the known columns (those whose
    fields exist in some block) then any unknown scalar field, every value formatted."""
    blocks = {name: _flatten(block) for name, block in results.get("algorithms", {}).items()}
    present = set().union(*blocks.values()) if blocks else set()
    columns = [(key, title) for key, title in SUMMARY_COLUMNS if key in present]
    known = {key for key, _ in SUMMARY_COLUMNS} | _NOT_SUMMARISED
    extra = sorted(k for k in present - known if all(_shown(b.get(k)) for b in blocks.values()) and not k.startswith("tags."))
    columns += [(key, key) for key in extra]
    rows = [{"algorithm": name, "label": label(name), "cells": [fmt(flat.get(key)) for key, _ in columns]}
            for name, flat in blocks.items()]
    return {"columns": [title for _, title in columns], "keys": [key for key, _ in columns], "rows": rows}


def tags_table(results: dict[str, Any]) -> dict[str, Any] | None:
    """A search for several tags (issue 21): per algorithm, one row per tag k (its final DR
    against its carrier, Wilson interval, time to 0.9, final ECE, median time to decide) and one
    for "all found" (with the time until the last tag was decided); None for one tag."""
    rows = []
    for name, block in results.get("algorithms", {}).items():
        tags = block.get("tags")
        if not tags:
            continue
        for k, tag in enumerate(tags["per_tag"]):
            rows.append({"label": label(name), "tag": str(k),
                         "cells": [fmt(tag["dr_final"]), fmt(tag["ci95"]), fmt(tag["time_to_dr90_s"], 1),
                                   fmt((tag.get("calibration") or {}).get("ece_final")),
                                   fmt((tag.get("decision") or {}).get("median_s"), 2)]})
        found = tags["all_found"]
        rows.append({"label": label(name), "tag": f"all (mean per tag {fmt(tags['mean_tag_dr_final'])})",
                     "cells": [fmt(found["dr_final"]), fmt(found["ci95"]), fmt(found["time_to_dr90_s"], 1), "—",
                               fmt((tags.get("all_decided") or {}).get("median_s"), 2)]})
    if not rows:
        return None
    return {"columns": ["final DR", "95 % CI", "t90 [s]", "ECE final", "median time to decide [s]"], "rows": rows}


def dr_curves(results: dict[str, Any], max_points: int = MAX_POINTS) -> dict[str, Any]:
    """The DR curves of a finished campaign as the page's chart takes them: time axis and, per
    algorithm, its label and colour (``names.web_colours``) and DR_t with its Wilson band
    (subsampled to ``max_points``)."""
    period = results["scenario"]["rf_period_s"]
    algorithms = {}
    steps = 0
    colour = web_colours(results["algorithms"])
    for name, block in results["algorithms"].items():
        steps = len(block["dr"])
        keep = subsample(steps, max_points)
        algorithms[name] = {"label": label(name), "color": colour[name], "n": results["tests"],
                            "dr": [block["dr"][i] for i in keep],
                            "lo": [block["dr_ci95"][i][0] for i in keep],
                            "hi": [block["dr_ci95"][i][1] for i in keep]}
    keep = subsample(steps, max_points)
    return {"t": [round((i + 1) * period, 10) for i in keep], "algorithms": algorithms}


class LiveDR:
    """DR_t with Wilson bands over the tests finished so far, per algorithm, updated
    incrementally from the store (each recorded episode is read once), for the curves that
    grow while a campaign runs. Thread-safe; one per campaign, shared by every viewer."""

    def __init__(self, cid: str, algorithms: list[str], steps: int, rf_period_s: float) -> None:
        self.cid = cid
        self.steps = steps
        self.period = rf_period_s
        self.successes = {a: np.zeros(steps) for a in algorithms}
        self.counts = {a: 0 for a in algorithms}
        self.after: tuple[float, int, str] | None = None
        self._lock = threading.Lock()

    def update(self, store: Store, chunk: int = 2000) -> int:
        """Read what was recorded since the last update (in chunks, so the store's lock is
        never held for long); return how many episodes were added."""
        added = 0
        with self._lock:
            while True:
                rows = store.done_hits(self.cid, self.after, limit=chunk)
                for finished_at, test_index, algorithm, hits in rows:
                    if algorithm in self.successes and len(hits) == self.steps:
                        self.successes[algorithm] += np.asarray(hits, dtype=float)
                        self.counts[algorithm] += 1
                        added += 1
                    self.after = (finished_at, test_index, algorithm)
                if len(rows) < chunk:
                    return added

    def snapshot(self, max_points: int = MAX_POINTS) -> dict[str, Any]:
        """The curves now (an algorithm without a finished test has empty lists)."""
        keep = subsample(self.steps, max_points)
        out = {}
        colour = web_colours(self.successes)
        with self._lock:
            for name, k in self.successes.items():
                n = self.counts[name]
                if n == 0:
                    out[name] = {"label": label(name), "color": colour[name], "n": 0, "dr": [], "lo": [], "hi": []}
                    continue
                p = k[keep] / n
                lo, hi = _wilson(k[keep], n)
                out[name] = {"label": label(name), "color": colour[name], "n": n, "dr": np.round(p, 6).tolist(), "lo": np.round(lo, 6).tolist(),
                             "hi": np.round(hi, 6).tolist()}
        return {"t": [round((i + 1) * self.period, 10) for i in keep], "algorithms": out}


def _wilson(successes: np.ndarray, trials: int, z: float = Z95) -> tuple[np.ndarray, np.ndarray]:
    """``metrics.wilson_interval`` on an array of success counts (same formula, same edge cases)."""
    p = successes / trials
    den = 1.0 + z * z / trials
    centre = (p + z * z / (2 * trials)) / den
    half = z * np.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / den
    lo = np.where(successes <= 0, 0.0, np.maximum(0.0, centre - half))
    hi = np.where(successes >= trials, 1.0, np.minimum(1.0, centre + half))
    return lo, hi


# -- per-test table ------------------------------------------------------------------------------

def test_rows(rows: list[dict[str, Any]], algorithms: list[str], rf_period_s: float) -> list[dict[str, Any]]:
    """``Store.test_page`` rows grouped by test: the Tx's index and one outcome per algorithm."""
    tests: dict[int, dict[str, Any]] = {}
    for row in rows:
        o = outcome_public(row, rf_period_s)
        t = tests.setdefault(o.test_index, {"test_index": o.test_index, "tx_index": o.tx_index, "outcomes": {}})
        if t["tx_index"] is None:
            t["tx_index"] = o.tx_index
        t["outcomes"][o.algorithm] = o
    return [{**t, "cells": [t["outcomes"].get(a) for a in algorithms]} for t in tests.values()]


# -- POD -----------------------------------------------------------------------------------------

def pod_series(scenario: dict[str, Any], model: dict[str, Any], truth: dict[str, Any] | None, max_samples: int = 1500) -> dict[str, Any]:
    """The POD figure's data (paper Fig. 3): the learned p̂_D(r) with its ±2 std band on its
    grid, the true p_D(r) on a dense grid, and the truth at the training samples (noiseless
    RSSI, true p_D; subsampled evenly beyond ``max_samples``)."""
    from ra2vipas.services.sensors import physics

    grid = np.asarray(model["rssi_grid_dbm"], dtype=float)
    mean = np.asarray(model["mean"], dtype=float)
    std = np.asarray(model["std"], dtype=float)
    lo_r, hi_r = float(grid[0]), float(grid[-1])
    samples = None
    if truth is not None and truth.get("rssi_dbm"):
        r = np.asarray(truth["rssi_dbm"], dtype=float)
        p = np.asarray(truth["pod"], dtype=float)
        keep = subsample(r.size, max_samples)
        samples = {"r": np.round(r[keep], 4).tolist(), "p": np.round(p[keep], 5).tolist(), "n": int(r.size)}
        lo_r, hi_r = min(lo_r, float(r.min())), max(hi_r, float(r.max()))
    dense = np.linspace(lo_r, hi_r, 300)
    true = physics.pod_of_rssi(Scenario.model_validate(scenario), dense)
    return {"grid": np.round(grid, 4).tolist(), "mean": np.round(mean, 5).tolist(),
            "lo": np.round(np.clip(mean - 2 * std, 0, 1), 5).tolist(), "hi": np.round(np.clip(mean + 2 * std, 0, 1), 5).tolist(),
            "dense": np.round(dense, 4).tolist(), "true": np.round(true, 5).tolist(), "samples": samples}


# -- episode -------------------------------------------------------------------------------------

def episode_data(row: dict[str, Any], scenario: dict[str, Any]) -> dict[str, Any]:
    """One finished test as the episode page animates it: per step the pan angle, the estimate,
    î_t, hit, reward, confidence and the estimate's error to the Tx's bearing at that step
    (degrees); the targets (walkers with their per-step bearings and ranges); the FoV."""
    trace = trace_public(row, scenario["rf_period_s"])
    steps = trace.steps
    tx = next(t for t in trace.targets if t.is_tx)
    tx_bearing = np.asarray(tx.bearings_rad[:len(steps)] if tx.bearings_rad else [tx.bearing_rad] * len(steps), dtype=float)
    est = np.asarray([s.gamma_hat_rad for s in steps], dtype=float)
    error = np.degrees(np.abs(wrap(est - tx_bearing))) if steps else np.zeros(0)
    return {
        "campaign_id": trace.campaign_id, "test_index": trace.test_index, "algorithm": trace.algorithm, "label": label(trace.algorithm),
        "rig": trace.rig, "tx_index": trace.tx_index, "fov_half_rad": math.radians(scenario["fov_half_angle_deg"]),
        "rf_period_s": scenario["rf_period_s"], "decided_step": row.get("decided_step"),
        "t": [s.time_s for s in steps], "pan": [round(s.pan_rad, 6) for s in steps], "est": [round(s.gamma_hat_rad, 6) for s in steps],
        "i_hat": [s.i_hat for s in steps], "hit": [s.hit for s in steps], "reward": [round(s.reward, 6) for s in steps],
        "confidence": [s.confidence for s in steps] if any(s.confidence is not None for s in steps) else None,
        "error_deg": np.round(error, 3).tolist(),
        "targets": [{"index": t.index, "bearing": round(t.bearing_rad, 6), "range": round(t.range_m, 4), "is_tx": t.is_tx,
                     "bearings": t.bearings_rad, "ranges": t.ranges_m} for t in trace.targets],
    }


# -- reliability diagram -------------------------------------------------------------------------

def reliability_series(results: dict[str, Any]) -> dict[str, Any] | None:
    """The reliability diagram's data (``calibration.reliability`` bins of the final
    confidences): per algorithm that has them, the non-empty bins' mean confidence, accuracy and
    count, and its final-step ECE; None when no algorithm carries bins."""
    out = {}
    colour = web_colours(results.get("algorithms", {}))
    for name, block in results.get("algorithms", {}).items():
        cal = block.get("calibration") or {}
        bins = [b for b in cal.get("reliability") or [] if b.get("n") and b.get("confidence") is not None]
        if not bins:
            continue
        bins.sort(key=lambda b: b["confidence"])
        out[name] = {"label": label(name), "color": colour[name], "ece": cal.get("ece_final"), "confidence": [b["confidence"] for b in bins],
                     "accuracy": [b["accuracy"] for b in bins], "n": [b["n"] for b in bins]}
    return {"algorithms": out} if out else None


# -- studies -------------------------------------------------------------------------------------

# metrics offered first (in this order) when a study's rows have them; any other numeric field follows
STUDY_METRICS = ["dr_final", "time_to_dr90_s", "in_fov_final", "pod_r2", "calibration_confidence_final", "calibration_ece_final",
                 "calibration_ece_final_floor",
                 "calibration_ece_all", "decision_accuracy", "decision_median_s", "decision_p90_s", "decision_undecided"]
# the results table's columns after the point's values, algorithm and tests
STUDY_COLUMNS = [("dr_final", "final DR (95 % CI)"), ("time_to_dr90_s", "t(DR ≥ 0.9) [s]"), ("in_fov_final", "Tx in FoV"),
                 ("pod_r2", "POD R²"), ("calibration_ece_final", "ECE (final)"), ("decision_accuracy", "decision accuracy"),
                 ("decision_median_s", "median time to decide [s]")]


def _is_band(key: str) -> bool:
    return key in ("ci95_lo", "ci95_hi") or key.endswith(("_ci95_lo", "_ci95_hi"))


def study_metrics(rows: list[dict[str, Any]], parameters: list[str]) -> list[dict[str, str]]:
    """The metrics a study's plot can show: numeric fields of its rows other than the varied
    values and the interval bounds, the known ones first; each with its label."""
    from ra2vipas.services.orchestrator.plots import METRIC_LABELS
    from ra2vipas.services.orchestrator.study import metrics_of

    known = [m for m in metrics_of(rows, parameters) if not _is_band(m)]
    ordered = [m for m in STUDY_METRICS if m in known] + [m for m in known if m not in STUDY_METRICS]
    return [{"key": m, "label": METRIC_LABELS.get(m, m)} for m in ordered]


def study_chart(results: dict[str, Any]) -> dict[str, Any]:
    """What the study page's plot draws: the varied parameters and their values in grid order,
    the algorithms with their labels and colours, the metrics and the rows (each row's varied values, its
    algorithm, the tests it rests on and its numeric fields, interval bounds included)."""
    params = results["parameters"]
    rows = []
    for r in results["rows"]:
        keep = {k: v for k, v in r.items() if k in params or k in ("point", "algorithm", "tests")
                or (isinstance(v, (int, float)) and not isinstance(v, bool))}
        rows.append(keep)
    return {"parameters": params, "vary": results["vary"], "partial": results["partial"], "status": results["status"],
            "algorithms": {a: label(a) for a in results["algorithms"]}, "colors": web_colours(results["algorithms"]), "metrics": study_metrics(results["rows"], params), "rows": rows}


def study_table(points: list[dict[str, Any]], results: dict[str, Any]) -> dict[str, Any]:
    """The study page's results table: one group per point (its values, campaign, status and
    progress) with one row per algorithm that has recorded tests (final DR with its interval,
    t90, in-FoV, POD R², and the calibration and decision fields when the rows carry them)."""
    rows = results["rows"]
    present = {k for r in rows for k, v in r.items() if v is not None}
    columns = [(key, title) for key, title in STUDY_COLUMNS if key in present or key in ("dr_final", "time_to_dr90_s", "pod_r2")]
    by_point: dict[int, list[dict[str, Any]]] = {}
    for r in rows:
        cells = []
        for key, _ in columns:
            if key == "dr_final":
                cells.append(f"{fmt(r.get('dr_final'))} ({fmt([r.get('ci95_lo'), r.get('ci95_hi')])})")
            else:
                cells.append(fmt(r.get(key)))
        by_point.setdefault(r["point"], []).append({"algorithm": r["algorithm"], "label": label(r["algorithm"]), "tests": r["tests"],
                                                    "cells": cells})
    groups = [{**p, "rows": by_point.get(p["point"], [])} for p in points]
    return {"columns": [title for _, title in columns], "parameters": results["parameters"], "groups": groups,
            "algorithms": results["algorithms"]}
