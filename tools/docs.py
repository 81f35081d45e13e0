"""``make docs``: the README's result tables and figure, generated from what the code prints.

    python tools/docs.py            # rerun every documented campaign and benchmark (minutes),
                                    # write docs/results.json, the figure, and the README blocks
    python tools/docs.py --render   # only re-render the README blocks from docs/results.json
    python tools/docs.py --check    # exit 1 when the README's blocks differ from docs/results.json
    python tools/docs.py --first-tests  # add the missing ``first_tests`` records (seconds), nothing else

Each generated block of README.md sits between ``<!-- docs:NAME -->`` and ``<!-- /docs:NAME -->``
and is rendered from docs/results.json only, so the README cannot say anything the JSON does
not. tests/docs/test_readme_numbers.py checks README == render(JSON) exactly, reruns the
JSON's small ``check`` campaign, and reruns the first tests of every documented campaign (each
one's ``first_tests`` record) to show the JSON is what the current code prints.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path
from typing import Any, Callable

from ra2vipas.services.controller.registry import BUILTINS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
RESULTS = ROOT / "docs" / "results.json"
FIGURE = ROOT / "docs" / "img" / "dr-paper-200-seed1.png"

TESTS = 200
SEEDS = (1, 2, 3)
TIMES_S = (1, 2, 4, 8, 12)
ALGORITHMS = BUILTINS  # the README's columns: the built-ins, in their order
# the small campaign the test suite reruns (seconds) to show the JSON is what the code prints
CHECK = {"preset": "paper", "overrides": {"steps": 60}, "tests": 12, "seed": 1}
# the first tests of every documented campaign (robustness: of every world) that the suite reruns
FIRST_TESTS = 3
FIRST_TESTS_ROBUSTNESS = 1


# -- collecting -------------------------------------------------------------------------------------
def _untimed(results: dict[str, Any]) -> dict[str, Any]:
    out = json.loads(json.dumps(results))
    out.pop("id", None)  # names the run (null in process), as tests/conftest.py's ``untimed`` drops it
    out.pop("steps_per_second", None)
    out.pop("latency_ms", None)
    out["pod"].pop("train_seconds", None)
    return out


def _campaign_summary(results: dict[str, Any]) -> dict[str, Any]:
    """What the README shows of a campaign: DR at the documented times, final DR and CI, t90,
    in-FoV, calibration and decision blocks, the POD R²."""
    period = results["scenario"]["rf_period_s"]
    out: dict[str, Any] = {"pod_r2": results["pod"].get("r2"), "algorithms": {}}
    for name, block in results["algorithms"].items():
        at = {str(t): block["dr"][min(round(t / period), len(block["dr"])) - 1] for t in TIMES_S}
        out["algorithms"][name] = {
            "dr_at_s": at, "dr_final": block["dr_final"], "ci95": block["ci95"], "time_to_dr90_s": block["time_to_dr90_s"],
            "in_fov_final": block["in_fov_final"], "ece_final": (block.get("calibration") or {}).get("ece_final"),
            "ece_final_floor": (block.get("calibration") or {}).get("ece_final_floor"),
            **({"decision": block["decision"]} if "decision" in block else {}),
        }
    return out


def first_tests(preset: str, overrides: dict[str, Any], seed: int, tests: int, stop_confidence: float = 0.0,
                oracle: bool = False) -> dict[str, Any]:
    """Tests 0 .. ``tests``-1 of a documented campaign, rerun on their own: the POD R² (eq. 23;
    the model depends on (scenario, seed) only, so it is the whole campaign's), each
    algorithm's (and with ``oracle``, the oracle's) final hits [î = i*] (one character per
    test, "1": a hit), and per algorithm and test a digest of every step's choice î_t (eq. 11)
    and of the early decision step. Every draw of test k depends only on (seed, k), so these are
    the first tests of the documented campaign, and a change to the code that moves any of them
    moves this record; another CPU may flip one test at a near-tie (see
    ``services/orchestrator/reproducibility.py``), which the per-test digests let a check count."""
    from ra2vipas.services.orchestrator.oracle import oracle_choice
    from ra2vipas.services.orchestrator.reproducibility import choices_digest
    from ra2vipas.services.orchestrator.simulate import run_test, train_pod
    from ra2vipas.services.protocol.scenario import build_scenario

    scenario = build_scenario(preset, overrides)
    pod = train_pod(scenario, seed)
    hits: dict[str, str] = {}
    choices: dict[str, list[str]] = {}
    for name in ALGORITHMS:
        outcomes = [run_test(scenario, seed, k, name, pod.model, stop_confidence=stop_confidence) for k in range(tests)]
        hits[name] = "".join("1" if o.hits[-1] else "0" for o in outcomes)
        choices[name] = [choices_digest(o.chosen, o.decided_step) for o in outcomes]
    if oracle:
        oracle_hits = (choice == tx for choice, tx in (oracle_choice(scenario, seed, k) for k in range(tests)))
        hits["oracle"] = "".join("1" if hit else "0" for hit in oracle_hits)
    return {"tests": tests, "pod_r2": pod.r2, "final_hits": hits, "choices_sha256": choices}


def documented_campaigns(data: dict[str, Any]) -> list[tuple[str, dict[str, Any], dict[str, Any]]]:
    """Every documented campaign as (label, ``first_tests`` arguments, its entry in ``data``)."""
    out = [(f"{preset} seed {seed}", {"preset": preset, "overrides": {}, "seed": int(seed), "tests": FIRST_TESTS}, entry)
           for preset in ("paper", "dynamic") for seed, entry in data[preset].items()]
    early = data["early_decision"]
    out.append((f"paper seed {early['seed']} --stop-confidence {early['stop_confidence']}",
                {"preset": "paper", "overrides": {}, "seed": early["seed"], "tests": FIRST_TESTS,
                 "stop_confidence": early["stop_confidence"]}, early))
    robustness = data["robustness"]
    out += [(f"robustness {name}", {"preset": s["preset"], "overrides": s["overrides"], "seed": robustness["seed"],
                                    "tests": FIRST_TESTS_ROBUSTNESS, "oracle": s["dr"].get("oracle") is not None}, s)
            for name, s in robustness["scenarios"].items()]
    return out


def fill_first_tests(data: dict[str, Any], progress: Callable[[str], None] = print) -> dict[str, Any]:
    """Add the ``first_tests`` record of every documented campaign that has none (seconds),
    leaving every other number as it is; a record already there is kept (a change that moves
    it needs `make docs`), and the check campaign's record of all its tests. Raises
    ``SystemExit`` when a rerun's POD R² is not the campaign's (within the tolerance of another
    CPU): then the JSON is not what this code printed, and only `make docs` can say what it prints."""
    from ra2vipas.services.orchestrator.reproducibility import POD_R2_TOLERANCE

    check = data.get("check")
    if check is not None and "first_tests" not in check:
        progress("every test of the check campaign")
        check["first_tests"] = first_tests(check["preset"], check["overrides"], check["seed"], check["tests"])
    for label, spec, entry in documented_campaigns(data):
        if "first_tests" in entry:
            continue
        progress(f"first {spec['tests']} tests of {label}")
        record = first_tests(**spec)
        if "pod_r2" in entry and not abs(record["pod_r2"] - entry["pod_r2"]) <= POD_R2_TOLERANCE:
            raise SystemExit(f"error: {label}: POD R² {record['pod_r2']} now, {entry['pod_r2']} recorded: run `make docs`")
        entry["first_tests"] = record
    return data


def collect(progress: Callable[[str], None] = print) -> dict[str, Any]:
    """Run everything the README documents (minutes on 2 cores)."""
    import ra2vipas
    from ra2vipas.services.orchestrator.plots import dr_figure, render
    from ra2vipas.services.orchestrator.robustness import SCENARIOS
    from ra2vipas.services.orchestrator.robustness import run as run_robustness

    workers = os.cpu_count() or 1
    data: dict[str, Any] = {"tests": TESTS, "seeds": list(SEEDS), "paper": {}, "dynamic": {}}
    for seed in SEEDS:
        for preset in ("paper", "dynamic"):
            progress(f"{preset}, {TESTS} tests, seed {seed}")
            results = ra2vipas.simulate(preset=preset, tests=TESTS, seed=seed, workers=workers)
            data[preset][str(seed)] = _campaign_summary(results)
            if preset == "paper" and seed == 1:
                FIGURE.write_bytes(render(dr_figure(results), "png"))
    progress("paper with --stop-confidence 0.95, seed 1")
    early = ra2vipas.simulate(preset="paper", tests=TESTS, seed=1, stop_confidence=0.95, workers=workers)
    data["early_decision"] = {"stop_confidence": 0.95, "seed": 1, **_campaign_summary(early)}
    progress(f"bench robustness ({len(SCENARIOS)} worlds)")
    data["robustness"] = run_robustness(tests=TESTS, seed=1, workers=workers)
    progress("the check campaign")
    data["check"] = {**CHECK, "results": _untimed(ra2vipas.simulate(**CHECK, workers=1))}
    return fill_first_tests(data, progress)


# -- rendering --------------------------------------------------------------------------------------
def _f(value: Any, digits: int = 3) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def _t90(value: Any) -> str:
    return "—" if value is None else f"{value:.1f} s"


def _ece(a: dict[str, Any]) -> str:
    """The final ECE and, in brackets, the ECE a perfectly calibrated confidence would show with
    the same confidences and tests (its sampling floor)."""
    floor = a.get("ece_final_floor")
    return _f(a["ece_final"]) + ("" if floor is None else f" [{_f(floor)}]")


def _paper_table(data: dict[str, Any]) -> str:
    head = "| seed | algorithm | " + " | ".join(f"{t} s" for t in TIMES_S) + " | 95 % CI (12 s) | t(DR ≥ 0.9) | Tx in FoV | ECE (final) [if calibrated] |"
    lines = [head, "|" + "---|" * (len(TIMES_S) + 6)]
    for seed in map(str, data["seeds"]):
        for name, a in data["paper"][seed]["algorithms"].items():
            bold = name == "ra2vipas"
            cells = [_f(a["dr_at_s"][str(t)]) for t in TIMES_S]
            if bold:
                cells[-1] = f"**{cells[-1]}**"
            lines.append(f"| {seed} | {'**ra2vipas**' if bold else name} | " + " | ".join(cells)
                         + f" | {_f(a['ci95'][0])}–{_f(a['ci95'][1])} | {('**' + _t90(a['time_to_dr90_s']) + '**') if bold else _t90(a['time_to_dr90_s'])}"
                         + f" | {_f(a['in_fov_final'])} | {_ece(a)} |")
    return "\n".join(lines)


def _pod_line(data: dict[str, Any]) -> str:
    r2 = ", ".join(f"{_f(data['paper'][s]['pod_r2'])} (seed {s})" for s in map(str, data["seeds"]))
    dyn = ", ".join(f"{_f(data['dynamic'][s]['pod_r2'])} (seed {s})" for s in map(str, data["seeds"]))
    return (f"POD regression R² (paper eq. 23, against the true POD at the training samples' true RSSI): "
            f"{r2}; on `dynamic`: {dyn} (there the true POD at an RSSI is E[p_D(d) | r] under 4 dB of shadowing, "
            f"nearly flat, so R² is ill-conditioned: see above).")


def _dynamic_table(data: dict[str, Any]) -> str:
    lines = ["| seed | algorithm | 4 s | 8 s | 12 s | 95 % CI (12 s) | t(DR ≥ 0.9) | ECE (final) [if calibrated] |", "|---|---|---|---|---|---|---|---|"]
    for seed in map(str, data["seeds"]):
        for name, a in data["dynamic"][seed]["algorithms"].items():
            lines.append(f"| {seed} | {name} | {_f(a['dr_at_s']['4'])} | {_f(a['dr_at_s']['8'])} | {_f(a['dr_final'])} | "
                         f"{_f(a['ci95'][0])}–{_f(a['ci95'][1])} | {_t90(a['time_to_dr90_s'])} | {_ece(a)} |")
    return "\n".join(lines)


def _early_line(data: dict[str, Any]) -> str:
    e = data["early_decision"]
    d = e["algorithms"]["ra2vipas"]["decision"]
    return (f"With `--stop-confidence {e['stop_confidence']}` (paper, {data['tests']} tests, seed {e['seed']}) Ra²ViPAS decides "
            f"after a median {_f(d['median_s'], 1)} s (90th percentile {_f(d['p90_s'], 1)} s; {_f(d['undecided'], 3)} of the tests "
            f"never that sure), and its answers are right {_f(d['accuracy'])} of the time "
            f"(95 % CI {_f(d['accuracy_ci95'][0])}–{_f(d['accuracy_ci95'][1])}).")


def _robustness_table(data: dict[str, Any]) -> str:
    r = data["robustness"]
    lines = ["| world | overrides | " + " | ".join(ALGORITHMS) + " | oracle | Ra²ViPAS − best single cue (95 % CI) | Ra²ViPAS / oracle |",
             "|---" * (len(ALGORITHMS) + 5) + "|"]
    from ra2vipas.services.orchestrator.robustness import SCENARIOS
    # the worlds in the order the benchmark defines them (docs/results.json stores its keys sorted)
    order = sorted(r["scenarios"], key=lambda name: (list(SCENARIOS).index(name) if name in SCENARIOS else len(SCENARIOS), name))
    for name in order:
        s = r["scenarios"][name]
        dr = s["dr"]
        over = ", ".join(f"{k}={v}" for k, v in s["overrides"].items()) or "—"
        lo, hi = s["difference_ci95"]
        mark = "" if s["not_worse"] else " ✗"
        lines.append(f"| {name} ({s['preset']}) | {over} | " + " | ".join(_f(dr.get(a)) for a in (*ALGORITHMS, "oracle"))
                     + f" | {s['difference']:+.3f} [{lo:+.3f}, {hi:+.3f}] vs {s['best_single_cue']}{mark} | {_f(s['ra2vipas_over_oracle'])} |")
    return "\n".join(lines)


BLOCKS: dict[str, Callable[[dict[str, Any]], str]] = {
    "paper-table": _paper_table,
    "paper-pod": _pod_line,
    "early-decision": _early_line,
    "dynamic-table": _dynamic_table,
    "robustness-table": _robustness_table,
}


def render(data: dict[str, Any]) -> dict[str, str]:
    return {name: make(data) for name, make in BLOCKS.items()}


_BLOCK = re.compile(r"(<!-- docs:(?P<name>[a-z-]+) -->)(?P<body>.*?)(<!-- /docs:(?P=name) -->)", re.S)


def blocks_of(text: str) -> dict[str, str]:
    return {m.group("name"): m.group("body").strip("\n") for m in _BLOCK.finditer(text)}


def apply(text: str, rendered: dict[str, str]) -> str:
    missing = set(rendered) - set(blocks_of(text))
    if missing:
        raise SystemExit(f"error: README.md has no <!-- docs:{sorted(missing)[0]} --> block")
    return _BLOCK.sub(lambda m: m.group(1) + "\n" + rendered[m.group("name")] + "\n" + m.group(4), text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--render", action="store_true", help="only re-render the README blocks from docs/results.json")
    mode.add_argument("--check", action="store_true", help="exit 1 if the README blocks differ from docs/results.json")
    mode.add_argument("--first-tests", action="store_true",
                      help="add the missing first_tests records to docs/results.json (seconds), nothing else")
    args = parser.parse_args(argv)
    if args.first_tests:
        data = fill_first_tests(json.loads(RESULTS.read_text()), lambda what: print(f"docs: {what}", file=sys.stderr))
        RESULTS.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
        return 0
    if args.check or args.render:
        data = json.loads(RESULTS.read_text())
    else:
        data = collect(lambda what: print(f"docs: {what}", file=sys.stderr))
        RESULTS.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
        data = json.loads(RESULTS.read_text())  # render what is stored (sorted keys), as --check does
    text = README.read_text()
    new = apply(text, render(data))
    if args.check:
        if new != text:
            print("error: README.md's generated blocks differ from docs/results.json: run `make docs` (or tools/docs.py --render)",
                  file=sys.stderr)
            return 1
        return 0
    README.write_text(new)
    return 0


if __name__ == "__main__":  # the workers of a multi-core simulate need this guard
    sys.exit(main())
