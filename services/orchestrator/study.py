"""Parameter studies (pure domain: no storage, no HTTP, no Zenoh).

A study is a base scenario (a preset and overrides), a grid of varied parameters
(``vary = {name: [values]}``; several names give their product, at most ``MAX_POINTS`` points),
the algorithms, tests per point, a seed and the campaign options. Every point of the grid is a
campaign with the same seed, so the points are paired test by test: test k of every point meets
the world drawn from (seed, k), changed only by the varied parameters.

This module expands a grid (``expand``), parses the CLI's ``NAME=a,b,c`` and ``NAME=a:b:step``
(``parse_vary``), and turns the points' results objects into the study's results object: one
row per point x algorithm (``study_results``) with every scalar field a campaign's results
report for that algorithm (final DR and its Wilson interval, t90, in-FoV, and whatever
calibration or decision fields there are, flattened as ``calibration_ece_final``, ...), the
POD fit, and the varied values.
"""

from __future__ import annotations

import csv
import io
import itertools
import re
from decimal import Decimal, InvalidOperation
from enum import Enum
from typing import Any, Iterable, Mapping, Sequence

from ra2vipas.services.protocol.scenario import (
    Scenario,
    ScenarioError,
    build_scenario,
    field_range,
    parse_value,
    suggest_parameter,
)

MAX_POINTS = 256
MAX_VARIED = 8  # parameters varied at once
MAX_STUDY_EPISODES = 200_000  # points x tests x algorithms: what one request may create

ROW_HEAD = ("point",)
ROW_CORE = ("algorithm", "tests", "dr_final", "ci95_lo", "ci95_hi", "time_to_dr90_s", "in_fov_final", "pod_r2")
PER_STEP = frozenset({"dr", "dr_ci95"})  # per-step curves: in each point's campaign results, not in the rows
NOT_METRICS = frozenset({"point", "preset", "seed", "tests", "algorithm", "campaign_id"})


class StudyError(ValueError):
    """A study cannot be built; one line naming the parameter, the value and what it accepts.
    ``where`` is ``"vary"`` or ``"overrides"`` (or ``"preset"``, ``"tests"``), ``name`` the
    parameter when there is one."""

    def __init__(self, message: str, where: str = "vary", name: str | None = None) -> None:
        super().__init__(message)
        self.where = where
        self.name = name


# -- the grid --------------------------------------------------------------------------------------

def _number(text: str, name: str) -> Decimal:
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise StudyError(f"{name}: expected {field_range(name)} in a range a:b:step, got {text.strip()!r}", name=name) from None
    if not value.is_finite():
        raise StudyError(f"{name}: expected {field_range(name)} in a range a:b:step, got {text.strip()!r}", name=name)
    return value


def parse_range(name: str, text: str) -> list[Any]:
    """``a:b:step``: a, a + step, ... up to b inclusive (exact decimal steps: 0.1:0.3:0.1 is three
    values), typed as the parameter (integers for an integer parameter)."""
    info = Scenario.model_fields[name]
    if info.annotation not in (int, float):
        raise StudyError(f"{name}: a range a:b:step needs a numeric parameter; {name} takes {field_range(name)} (list the values: a,b,c)",
                         name=name)
    parts = text.split(":")
    if len(parts) != 3:
        raise StudyError(f"{name}: a range is a:b:step, got {text!r}", name=name)
    start, stop, step = (_number(p, name) for p in parts)
    if step == 0 or (stop - start) * step < 0:
        raise StudyError(f"{name}: range {text!r} never reaches its end (step {step} from {start} to {stop})", name=name)
    count = int((stop - start) / step) + 1
    if count > MAX_POINTS:
        raise StudyError(f"{name}: range {text!r} has {count} values, more than the {MAX_POINTS} a study may have", name=name)
    values = [start + i * step for i in range(count)]
    if info.annotation is int:
        if any(v != v.to_integral_value() for v in values):
            raise StudyError(f"{name}: expected {field_range(name)}, range {text!r} gives fractions", name=name)
        return [int(v) for v in values]
    return [float(v) for v in values]


def parse_vary(item: str) -> tuple[str, list[Any]]:
    """The CLI's ``--vary NAME=a,b,c`` (a list) or ``--vary NAME=a:b:step`` (a range), with
    values typed as the parameter takes them (``scenario.parse_value``).

    Raises
    ------
    StudyError
        No ``=``, an unknown parameter, a value that is not of the parameter's kind, an empty
        or endless range.
    """
    name, sep, text = item.partition("=")
    name = name.strip()
    if not sep or not name or not text.strip():
        raise StudyError(f"--vary expects NAME=a,b,c or NAME=a:b:step, got {item!r}")
    if name not in Scenario.model_fields:
        raise StudyError(f"unknown scenario parameter {name!r}{suggest_parameter(name)}; known: {', '.join(Scenario.model_fields)}",
                         name=name)
    if ":" in text and "," not in text:
        return name, parse_range(name, text)
    try:
        return name, [parse_value(name, v) for v in text.split(",")]
    except ScenarioError as err:
        raise StudyError(str(err), name=name) from None


def expand(preset: str, overrides: Mapping[str, Any], vary: Mapping[str, Sequence[Any]]) -> list[tuple[dict[str, Any], Scenario]]:
    """Every point of the grid, as (its varied values, its scenario), the first parameter
    varying slowest (``itertools.product`` order).

    Raises
    ------
    StudyError
        An unknown preset or parameter, a parameter both overridden and varied or with no or
        repeated values, more than ``MAX_POINTS`` points, or a point whose scenario is invalid
        (the message names the parameter, the value and what it accepts).
    """
    if not vary:
        raise StudyError("vary: give at least one parameter and its values, e.g. {\"n_targets\": [10, 20, 40]}")
    if len(vary) > MAX_VARIED:
        raise StudyError(f"vary: at most {MAX_VARIED} parameters, got {len(vary)}")
    try:
        build_scenario(preset, dict(overrides))
    except ScenarioError as err:
        where = "preset" if str(err).startswith("unknown preset") else "overrides"
        raise StudyError(str(err), where=where) from None
    size = 1
    for name, values in vary.items():
        if name not in Scenario.model_fields:
            raise StudyError(f"unknown scenario parameter {name!r}{suggest_parameter(name)}; known: {', '.join(Scenario.model_fields)}",
                             name=name)
        if name in overrides:
            raise StudyError(f"{name}: both overridden and varied; give it in one of overrides or vary", name=name)
        if not values:
            raise StudyError(f"{name}: no values to vary over", name=name)
        keys = [_key(v) for v in values]
        if len(set(keys)) != len(keys):
            dup = next(v for i, v in enumerate(values) if keys.index(keys[i]) != i)
            raise StudyError(f"{name}: the value {dup!r} is given twice", name=name)
        size *= len(values)
    if size > MAX_POINTS:
        raise StudyError(f"vary: {' x '.join(str(len(v)) for v in vary.values())} = {size} points, more than the {MAX_POINTS} "
                         "a study may have")
    names = list(vary)
    points = []
    for combo in itertools.product(*(vary[n] for n in names)):
        values = dict(zip(names, combo))
        try:
            scenario = build_scenario(preset, {**overrides, **values})
        except ScenarioError as err:
            message = str(err)
            culprit = next((n for n in names if re.search(rf"\b{n}\b", message)), None)
            raise StudyError(f"vary: {', '.join(f'{n}={v!r}' for n, v in values.items())}: {message}", name=culprit) from None
        resolved = scenario.model_dump(mode="json")
        points.append(({n: resolved[n] for n in names}, scenario))
    return points


def check_size(points: int, tests: int, algorithms: int) -> None:
    """At most ``MAX_STUDY_EPISODES`` episodes (points x tests x algorithms) in one study.

    Raises
    ------
    StudyError
        Too many episodes (``where`` is ``"tests"``).
    """
    episodes = points * tests * algorithms
    if episodes > MAX_STUDY_EPISODES:
        raise StudyError(f"tests: {points} points x {tests} tests x {algorithms} algorithms = {episodes} episodes, more than "
                         f"the {MAX_STUDY_EPISODES} a study may have", where="tests")


def _key(value: Any) -> tuple:
    return (type(value) is bool, value.value if isinstance(value, Enum) else value)


# -- results ---------------------------------------------------------------------------------------

def flatten(block: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """The scalar fields of an algorithm's results block, nested objects flattened with ``_``
    (``calibration.ece_final`` -> ``calibration_ece_final``) and Wilson intervals split into
    ``_lo``/``_hi`` (``ci95`` -> ``ci95_lo``, ``ci95_hi``). Per-step curves and lists of
    objects (the reliability bins) are left out: they are in the point's campaign results."""
    out: dict[str, Any] = {}
    for key, value in block.items():
        if not prefix and key in PER_STEP:
            continue
        name = prefix + key
        if isinstance(value, Mapping):
            out.update(flatten(value, name + "_"))
        elif isinstance(value, (list, tuple)):
            if key.endswith("ci95") and len(value) == 2 and all(v is None or isinstance(v, (int, float)) for v in value):
                out[name + "_lo"], out[name + "_hi"] = value
        elif value is None or isinstance(value, (bool, int, float, str)):
            out[name] = value
    return out


def point_rows(point: int, values: Mapping[str, Any], results: Mapping[str, Any], campaign_id: str | None = None,
               tests: Mapping[str, int] | None = None) -> list[dict[str, Any]]:
    """One row per algorithm of a point's results object: the point, its varied values, the
    preset and seed, the algorithm, the tests it rests on, the flattened block, the POD R² and the campaign."""
    rows = []
    pod_r2 = (results.get("pod") or {}).get("r2")
    for algorithm, block in results["algorithms"].items():
        flat = flatten(block)
        row: dict[str, Any] = {"point": point, **values}
        if "preset" in results:  # what was run (a hand-made results object may lack it)
            row.update(preset=results["preset"], seed=results["seed"])
        row.update(algorithm=algorithm, tests=(tests or {}).get(algorithm, results["tests"]))
        for key in ROW_CORE[2:-1]:
            row[key] = flat.pop(key, None)
        row["pod_r2"] = pod_r2
        row.update(flat)
        row["campaign_id"] = campaign_id
        rows.append(row)
    return rows


def metrics_of(rows: Iterable[Mapping[str, Any]], parameters: Iterable[str] = ()) -> list[str]:
    """The numeric fields of the rows a plot can show (in order of first appearance)."""
    skip = NOT_METRICS | set(parameters)
    seen: dict[str, None] = {}
    for row in rows:
        for key, value in row.items():
            if key not in skip and isinstance(value, (int, float)) and not isinstance(value, bool):
                seen.setdefault(key, None)
    return list(seen)


def study_results(meta: Mapping[str, Any], points: Sequence[Mapping[str, Any]], steps_per_second: float | None = None,
                  partial: bool = False) -> dict[str, Any]:
    """The study's results object.

    Parameters
    ----------
    meta : mapping
        ``id`` (None in-process), ``name``, ``status``, ``preset``, ``overrides``, ``vary``,
        ``algorithms``, ``tests``, ``seed``, ``mode``, ``stop_confidence``.
    points : sequence of mappings
        Per point, in grid order: ``point``, ``values``, ``campaign_id`` (None in-process),
        ``status``, ``results`` (its results object, or None if there is nothing to show yet)
        and, for a partial reduction, ``tests`` per algorithm.
    """
    rows: list[dict[str, Any]] = []
    shown = []
    for p in points:
        res = p.get("results")
        if res is not None and res.get("algorithms"):
            rows += point_rows(p["point"], p["values"], res, p.get("campaign_id"), p.get("tests"))
        shown.append({"point": p["point"], "values": dict(p["values"]), "campaign_id": p.get("campaign_id"), "status": p["status"],
                      "pod": dict(res["pod"]) if res else None,
                      "steps_per_second": res.get("steps_per_second") if res else None,
                      "paired": list(res.get("paired") or []) if res else None})
    policies: dict[str, Any] = {}
    for p in points:  # where each policy outside the built-ins came from, as its points' results say
        policies.update(((p.get("results") or {}).get("policies")) or {})
    out = {
        "id": meta.get("id"), "name": meta.get("name"), "status": meta["status"], "partial": partial,
        "preset": meta["preset"], "overrides": dict(meta["overrides"]), "vary": {k: list(v) for k, v in meta["vary"].items()},
        "parameters": list(meta["vary"]), "algorithms": list(meta["algorithms"]), "tests": meta["tests"], "seed": meta["seed"],
        "mode": meta.get("mode", "fast"), "stop_confidence": meta.get("stop_confidence") or 0.0,
        "points": shown, "rows": rows,
        "steps_per_second": None if steps_per_second is None else round(steps_per_second, 1),
    }
    if policies:  # absent when every policy is a built-in, as in a campaign's results
        out["policies"] = policies
    return out


def table_rows(results: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The study's rows as one table, columns in one order wherever the results object comes
    from (this process, or the API, whose rows list their declared fields first): ``study_id``,
    ``point``, the varied parameters, what was run (``preset``, ``seed``, one column per
    override, ``stop_confidence`` when early decisions were on), ``algorithm``, ``tests``, the
    core metrics (final DR, its Wilson interval, t90, in-FoV, POD R²), every other field in
    order of first appearance, and ``campaign_id`` last."""
    head = {"study_id": results.get("id")}
    run = {"preset": results["preset"], "seed": results["seed"], **dict(results.get("overrides") or {})}
    if results.get("stop_confidence"):
        run["stop_confidence"] = results["stop_confidence"]
    lead = [*ROW_HEAD, *results["parameters"], *run, "algorithm", "tests", *ROW_CORE[2:]]
    rest: dict[str, None] = {}
    for row in results["rows"]:
        rest.update(dict.fromkeys(k for k in row if k not in lead and k != "campaign_id"))
    columns = ["study_id", *lead, *rest, "campaign_id"]
    out = []
    for row in results["rows"]:
        full = {**head, **run, **row}
        out.append({c: full.get(c) for c in columns})
    return out


def study_columns(results: Mapping[str, Any]) -> list[str]:
    """The columns of ``table_rows`` (also when there is no row yet)."""
    rows = table_rows(results)
    if rows:
        return list(rows[0])
    run = ["preset", "seed", *(results.get("overrides") or {})] + (["stop_confidence"] if results.get("stop_confidence") else [])
    return ["study_id", *ROW_HEAD, *results["parameters"], *run, "algorithm", "tests", *ROW_CORE[2:], "campaign_id"]


def write_study_csv(results: Mapping[str, Any]) -> str:
    """The study's results as a plain CSV (one header row, no comment lines: ``pandas.read_csv``
    reads it as it is): one row per point x algorithm, the columns of ``table_rows``, so every
    row says what was run and files of several studies concatenate."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=study_columns(results), lineterminator="\n", restval="")
    writer.writeheader()
    for row in table_rows(results):
        writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
    return out.getvalue()


def status_of(counts: Mapping[str, int]) -> str:
    """A study's status from how many of its points' campaigns are in each state: queued while
    none has started, training while points train and none runs or finished, running while any
    point is unfinished; then failed if a point failed, cancelled if one was cancelled, else done."""
    n = sum(counts.values())
    active = sum(counts.get(s, 0) for s in ("queued", "training", "running"))
    if active:
        if counts.get("queued", 0) == n:
            return "queued"
        if counts.get("running", 0) or n - active:
            return "running"
        return "training"
    if counts.get("failed", 0):
        return "failed"
    if counts.get("cancelled", 0):
        return "cancelled"
    return "done"
