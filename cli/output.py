"""Shared printing for the CLI: rich tables for people, one JSON line for scripts, and the
single-line error convention (exit 1 for a failed operation, 2 for bad usage)."""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import time
from typing import Any, NoReturn

import typer
from rich.console import Console
from rich.markup import escape
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


def write_file(data: bytes, path: str) -> None:
    """Write ``data`` to ``path`` through a temporary file (never a half-written file); a
    failure is one stderr line and exit code 1."""
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError as err:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        fail(f"cannot write {path}: {err.strerror or err}")


def check_output(path: str | None, option: str) -> None:
    """Refuse, before any work, an output file that cannot be written: its folder is missing
    or not writable, or the path is a folder (one stderr line, exit 1). Nothing is created."""
    if path is None or path == "-":
        return
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        fail(f"{option}: cannot write {path}: it is a directory")
    if not os.path.isdir(folder):
        fail(f"{option}: cannot write {path}: no such directory {folder}")
    if not os.access(folder, os.W_OK | os.X_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        fail(f"{option}: cannot write {path}: permission denied")


def print_json(obj: Any) -> None:
    """The object as one compact JSON line on stdout (the last line scripts parse)."""
    sys.stdout.write(json.dumps(obj, separators=(",", ":")) + "\n")
    sys.stdout.flush()


def tests_text(results: dict[str, Any]) -> str:
    """``50 tests``; for partial results the tests recorded, e.g. ``PARTIAL: 16-17 of 60 tests``."""
    if not results.get("partial"):
        return f"{results['tests']} tests"
    counts = sorted(set((results.get("tests_recorded") or {}).values())) or [0]
    span = str(counts[0]) if len(counts) == 1 else f"{counts[0]}–{counts[-1]}"
    return f"PARTIAL: {span} of {results['tests']} tests"


def dr_table(results: dict[str, Any]) -> Table:
    """DR at 1, 2, 4, 8, 12 s (those within the test), final Wilson interval, time to 0.9, in-FoV."""
    period = results["scenario"]["rf_period_s"]
    steps = results["scenario"]["steps"]
    times = [t for t in REPORT_TIMES_S if round(t / period) <= steps]
    if not times or abs(times[-1] - steps * period) > 1e-9:
        times.append(round(steps * period, 6))
    over = "".join(f", {k}={v}" for k, v in (results.get("overrides") or {}).items())
    table = Table(title=f"Discovery rate DR_t, {results['preset']}{over} ({tests_text(results)}, seed {results['seed']})"
                        + (f", stop at confidence {results['stop_confidence']}" if results.get("stop_confidence") else ""))
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


def report_times(results: dict[str, Any]) -> list[float]:
    """The times the DR tables show: 1, 2, 4, 8, 12 s within the test, and its end."""
    period = results["scenario"]["rf_period_s"]
    steps = results["scenario"]["steps"]
    times = [t for t in REPORT_TIMES_S if round(t / period) <= steps]
    if not times or abs(times[-1] - steps * period) > 1e-9:
        times.append(round(steps * period, 6))
    return times


def tags_table(results: dict[str, Any]) -> Table | None:
    """A search for several tags (issue 21): per algorithm, each tag's DR_t (eq. 11 against its
    carrier) and the rate at which every tag was found, with the final Wilson interval, t90, the
    final ECE and, with early decisions, when each tag (and the last of them) was decided. None
    when no algorithm reports tags."""
    blocks = {name: b["tags"] for name, b in results["algorithms"].items() if b.get("tags")}
    if not blocks:
        return None
    period = results["scenario"]["rf_period_s"]
    times = report_times(results)
    decided = any("all_decided" in t for t in blocks.values())
    table = Table(title="Per tag: DR_t of each tag k against its carrier, and of all tags found at once",
                  caption="mean per-tag DR at the end: " + ", ".join(f"{n} {t['mean_tag_dr_final']:.3f}" for n, t in blocks.items())
                  + ("; median/p90: time until the tag (all: the last tag) was decided" if decided else ""))
    for col in ("algorithm", "tag"):
        table.add_column(col, no_wrap=True)
    for t in times:
        table.add_column(f"{t:g} s", justify="right")
    for col in ("95% CI", "t90", "ECE") + (("median", "p90", "undec.") if decided else ()):
        table.add_column(col, justify="right", no_wrap=True)

    def cells(block: dict[str, Any]) -> list[str]:
        dr = block["dr"]
        lo, hi = block["ci95"]
        t90 = block["time_to_dr90_s"]
        return ([f"{dr[max(0, min(len(dr), round(t / period)) - 1)]:.3f}" for t in times]
                + [f"{lo:.3f}–{hi:.3f}", "—" if t90 is None else f"{t90:g} s"])

    def when(d: dict[str, Any] | None) -> list[str]:
        if not decided:
            return []
        d = d or {}
        return ["—" if d.get(k) is None else (f"{d[k]:g} s" if k != "undecided" else f"{d[k]:.3f}")
                for k in ("median_s", "p90_s", "undecided")]

    for name, tags in blocks.items():
        for k, block in enumerate(tags["per_tag"]):
            ece = (block.get("calibration") or {}).get("ece_final")
            table.add_row(name, str(k), *cells(block), "—" if ece is None else f"{ece:.3f}", *when(block.get("decision")))
        table.add_row(name, "all", *cells(tags["all_found"]), "—", *when(tags.get("all_decided")))
    return table


def confidence_table(results: dict[str, Any]) -> Table | None:
    """Calibration (and early decision) per algorithm, when the results carry them."""
    blocks = results["algorithms"]
    if not any("calibration" in b or "decision" in b for b in blocks.values()):
        return None
    decided = any("decision" in b for b in blocks.values())
    title = "Confidence: calibration" + (f" and decision at {results.get('stop_confidence')}" if decided else "")
    table = Table(title=title)
    table.add_column("algorithm", no_wrap=True)
    for col in ("mean conf.", "ECE final", "ECE floor", "ECE all") + (("accuracy", "95% CI", "median", "p90", "undecided") if decided else ()):
        table.add_column(col, justify="right")

    def f(v: Any, fmt: str = "{:.3f}") -> str:
        return "—" if v is None else fmt.format(v)

    for name, b in blocks.items():
        cal = b.get("calibration") or {}
        row = [name, f(cal.get("confidence_final")), f(cal.get("ece_final")), f(cal.get("ece_final_floor")), f(cal.get("ece_all"))]
        if decided:
            d = b.get("decision") or {}
            lo, hi = d.get("accuracy_ci95") or (None, None)
            row += [f(d.get("accuracy")), "—" if lo is None else f"{lo:.3f}–{hi:.3f}", f(d.get("median_s"), "{:g} s"),
                    f(d.get("p90_s"), "{:g} s"), f(d.get("undecided"))]
        table.add_row(*row)
    return table


def paired_table(results: dict[str, Any]) -> Table | None:
    """Every pair of algorithms compared test by test (the same world in test k for each):
    the discordant tests and McNemar's exact p-value; None with fewer than two algorithms."""
    pairs = list(results.get("paired") or [])
    pairs += [{**p, "a": f"{p['a']} (all tags)", "b": f"{p['b']} (all tags)"} for p in results.get("paired_all_found") or []]
    if not pairs:
        return None
    table = Table(title="Paired comparison of the final answers (same worlds test by test; exact McNemar test)")
    for col in ("a vs b", "tests", "only a", "only b", "DR a − b", "p-value"):
        table.add_column(col, justify="left" if col == "a vs b" else "right", no_wrap=True)
    for p in pairs:
        diff = p.get("dr_difference")
        pv = p.get("p_value")
        table.add_row(f"{p['a']} vs {p['b']}", str(p["tests"]), str(p["only_a"]), str(p["only_b"]),
                      "—" if diff is None else f"{diff:+.3f}", "—" if pv is None else (f"{pv:.3g}" if pv >= 1e-4 else f"{pv:.1e}"))
    return table


def emit_results(results: dict[str, Any], plot: str | None, as_json: bool) -> None:
    """Write the DR plot if asked, then print the results: one JSON line, or the table."""
    if plot:
        from ra2vipas.services.orchestrator.plots import write_dr_plot

        try:
            write_dr_plot(results, plot)
        except OSError as err:
            fail(f"cannot write {plot}: {err.strerror or err}")
    if as_json:
        print_json(results)
    else:
        print_results(results)
        if plot:
            print(f"DR plot written to {plot}")


def print_results(results: dict[str, Any]) -> None:
    if results.get("partial"):
        recorded = ", ".join(f"{a} {n}" for a, n in (results.get("tests_recorded") or {}).items())
        stdout.print(f"partial results: the campaign stopped before its end; tests recorded: {recorded} (of {results['tests']})")
        if len(set((results.get("tests_recorded") or {}).values())) > 1:
            stdout.print("the algorithms are unpaired: they rest on different numbers of tests (different worlds); the DR "
                         "table compares unequal sets, the paired comparison only the tests both ran")
    stdout.print(dr_table(results))
    tags = tags_table(results)
    if tags is not None:
        stdout.print(tags)
    for warning in results.get("warnings") or []:
        stdout.print(f"[bold red]warning:[/] {escape(warning)}")
    if results.get("assumptions"):
        a = results["assumptions"]
        stdout.print(f"note: {a['episodes']} of {a['of']} episodes ran on undescribed rigs ({', '.join(a['rigs'])}): "
                     "modelled and scored under the scenario's assumptions")
    confidence = confidence_table(results)
    if confidence is not None:
        stdout.print(confidence)
    paired = paired_table(results)
    if paired is not None:
        stdout.print(paired)
    pod = results["pod"]
    line = f"POD regression R² {pod['r2']:.4f} (trained in {pod['train_seconds']:.2f} s)"
    if results.get("steps_per_second"):
        line += f"; {results['steps_per_second']:.0f} control steps/s"
    stdout.print(line)
    stdout.print(
        "DR: paper's association rule (eq. 11) at each time; 95% CI: Wilson interval of the final DR; "
        "t90: time after which DR stays >= 0.9; in-FoV: Tx inside the FoV at the final estimate (secondary)."
    )


# -- campaigns ---------------------------------------------------------------------------------

def _when(ts: float | None, fmt: str = "%Y-%m-%d %H:%M:%S") -> str:
    return "—" if ts is None else time.strftime(fmt, time.localtime(ts))


def _r2(pod: dict[str, Any]) -> str:
    return "—" if pod.get("r2") is None else f"{pod['r2']:.4f}"


def overrides_text(overrides: dict[str, Any] | None) -> str:
    """``n_targets=30, antenna_model=db-gain`` (``—`` for none)."""
    return ", ".join(f"{k}={v}" for k, v in (overrides or {}).items()) or "—"


def progress_text(c: dict[str, Any]) -> str:
    p = c["progress"]
    return f"{p['done']}/{p['total']}" + (f" ({p['running']} running)" if p.get("running") else "")


def campaigns_table(page: dict[str, Any]) -> Table:
    """One page of ``GET /campaigns``."""
    items = page["items"]
    first = page["offset"] + 1 if items else 0
    table = Table(title=f"Campaigns {first}–{page['offset'] + len(items)} of {page['total']}")
    for col in ("id", "name", "status", "preset", "overrides", "tests", "seed", "episodes", "POD R²", "created"):
        table.add_column(col, no_wrap=col in ("id", "status"), overflow="fold",
                         min_width=22 if col == "overrides" else None)
    for c in items:
        table.add_row(c["id"], c["name"] or "", c["status"], c["preset"], overrides_text(c.get("overrides")), str(c["tests"]),
                      str(c["seed"]), progress_text(c), _r2(c["pod"]), _when(c["created_at"], "%Y-%m-%d %H:%M"))
    return table


def campaign_tables(c: dict[str, Any]) -> list[Table]:
    """``GET /campaigns/{id}`` for people: the campaign, then its scenario (overrides marked *)."""
    about = Table(title=f"Campaign {c['id']}", show_header=False)
    about.add_column("field", style="bold")
    about.add_column("value")
    elapsed = c.get("elapsed_s")
    rows = [
        ("name", c["name"] or ""), ("status", c["status"]), ("progress", progress_text(c) + " episodes"),
        ("preset", c["preset"]), ("mode", c["mode"]), ("tests", str(c["tests"])), ("seed", str(c["seed"])),
        ("algorithms", ", ".join(c["algorithms"])), ("created", _when(c["created_at"])), ("started", _when(c["started_at"])),
        ("finished", _when(c["finished_at"])), ("elapsed", "—" if elapsed is None else f"{elapsed:.1f} s"),
        ("POD R²", _r2(c["pod"])),
        ("steps/s", "—" if not c.get("steps_per_second") else f"{c['steps_per_second']:.0f}"),
    ]
    if c.get("error"):
        rows.append(("error", c["error"]))
    for k, v in rows:
        about.add_row(k, v)
    scenario = Table(title="Scenario (* overridden)")
    scenario.add_column("parameter")
    scenario.add_column("value", justify="right")
    for name, value in c["scenario"].items():
        scenario.add_row(name + (" *" if name in c["overrides"] else ""), str(value))
    return [about, scenario]


def outcomes_table(page: dict[str, Any]) -> Table:
    """One page of ``GET /campaigns/{id}/tests``."""
    items = page["items"]
    first = page["offset"] + 1 if items else 0
    table = Table(title=f"Tests {first}–{page['offset'] + len(items)} of {page['total']}")
    for col in ("test", "algorithm", "status", "Tx", "final î", "hit", "hit rate", "first hit", "settled", "rig"):
        table.add_column(col, justify="right" if col not in ("algorithm", "status", "rig") else "left")

    def opt(v: Any, fmt: str = "{}") -> str:
        return "—" if v is None else fmt.format(v)

    for o in items:
        hit = "—" if o["final_hit"] is None else ("yes" if o["final_hit"] else "no")
        table.add_row(str(o["test_index"]), o["algorithm"], o["status"], opt(o["tx_index"]), opt(o["final_choice"]), hit,
                      opt(o["hit_rate"], "{:.2f}"), opt(o["first_hit_s"], "{:g} s"), opt(o["settled_s"], "{:g} s"), o["rig"] or "")
    return table


def trace_table(trace: dict[str, Any]) -> Table:
    """``GET /campaigns/{id}/tests/{k}/{algorithm}``: one row per step, angles in degrees. When
    the Tx walks, its bearing at each step is a column and the title gives its start and end."""
    tx = trace["tx_index"]
    target = trace["targets"][tx]
    walk = target.get("bearings_rad")
    if walk:
        n = max(1, len(trace["steps"]))
        where = (f"walking from {math.degrees(walk[0]):.1f}° ({target['ranges_m'][0]:.2f} m) to "
                 f"{math.degrees(walk[min(n, len(walk)) - 1]):.1f}° ({target['ranges_m'][min(n, len(walk)) - 1]:.2f} m)")
    else:
        where = f"at {math.degrees(target['bearing_rad']):.1f}°, {target['range_m']:.2f} m"
    table = Table(title=f"Test {trace['test_index']} ({trace['algorithm']}): the Tx is target {tx} {where}")
    for col in ("step", "time", "pan s_t", "reward", "estimate γ̂_t", *(("Tx bearing",) if walk else ()), "î_t", "hit"):
        table.add_column(col, justify="right")
    for s in trace["steps"]:
        bearing = (f"{math.degrees(walk[min(s['step'], len(walk) - 1)]):.1f}°",) if walk else ()
        table.add_row(str(s["step"]), f"{s['time_s']:g} s", f"{math.degrees(s['pan_rad']):.1f}°", f"{s['reward']:.3g}",
                      f"{math.degrees(s['gamma_hat_rad']):.1f}°", *bearing, str(s["i_hat"]), "yes" if s["hit"] else "no")
    return table


def rigs_table(body: dict[str, Any]) -> Table:
    """``GET /rigs``."""
    table = Table(title=f"Rigs (learners: {', '.join(body['learners']) or 'none'})")
    for col in ("rig", "live", "sensors", "controller", "episodes in flight", "policies", "descriptor"):
        table.add_column(col)
    for r in body["rigs"]:
        table.add_row(r["name"], "yes" if r["live"] else "no", "up" if r["sensors"] else "down",
                      "up" if r["controller"] else "down", str(r["in_flight"]), served_policies(r), describe_rig(r))
    return table


def served_policies(r: dict[str, Any]) -> str:
    """The policies a rig's controller serves, by name (``GET /rigs``: ``policies``)."""
    policies = r.get("policies")
    if policies is None:
        return "asking..." if r.get("announced") == "asking" else "-"
    from ra2vipas.services.controller.registry import BUILTINS

    served = [p["name"] for p in policies]
    if set(BUILTINS) <= set(served):  # the usual case, said briefly: the built-ins and what else
        served = ["built-ins"] + [name for name in served if name not in BUILTINS]
    names = ", ".join(served)
    return f"{names} (announces none: a 1.0/1.1 controller)" if r.get("announced") == "silent" else names


def describe_rig(r: dict[str, Any]) -> str:
    """One line of a rig's descriptor: kind, vendor/model, nu, T_RF, half-FoV, box noise, Rx(dir)
    (``=campaign`` for a configurable field), then what it fixes of the radio (1.3: pair or BLE
    adverts, box heights; 1.5: how many tags it hears) and the protocol it speaks; ``undescribed``
    for a v1 node."""
    d = r.get("descriptor")
    if d is None:
        return {"undescribed": "undescribed (v1 node: modelled from each campaign's scenario)", "asking": "asking..."}.get(
            r.get("described", "unknown"), "-")
    def show(value, fmt="{}"):
        return "=campaign" if value is None else fmt.format(value)
    rx = d.get("rx_dir")
    parts = [d["kind"], " ".join(p for p in (d.get("vendor"), d.get("model")) if p) or "-",
             f"nu {show(d.get('frames_per_rf'))}", f"T_RF {show(d.get('rf_period_s'), '{:g} s')}",
             f"half-FoV {show(d.get('fov_half_angle_deg'), '{:g} deg')}", f"box noise {show(d.get('box_bearing_noise_deg'), '{:g} deg')}",
             f"Rx(dir) {show(None if rx is None else rx['model'])}"]
    if d.get("radio") is not None:
        parts.append({"adverts": "BLE adverts", "pair": "RSSI pair"}.get(d["radio"], d["radio"]))
    if d.get("box_heights") is not None:
        parts.append("box heights" if d["box_heights"] else "no box heights")
    if d.get("tags") is not None:
        parts.append(f"hears {d['tags']} tag{'s' if d['tags'] > 1 else ''}")
    if d.get("episode_truth"):
        parts.append("knows the truth")
    parts.append(f"protocol {d.get('protocol', '1.1')}")
    return ", ".join(parts)
