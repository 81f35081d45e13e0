"""No silent DR 0.00: what the results say about how the rig was modelled.

Two things can make a campaign's numbers meaningless without any service failing:

* the controller modelled the rig wrongly, e.g. a dB-gain Rx(dir), whose reading *peaks* when
  aligned, under the paper's antenna model, where it *dips*: every radio algorithm then points
  away from the Tx and its DR falls far *below chance* (1/N);
* the rig is undescribed (a v1 sensors node): its controller took the hardware from the
  campaign's scenario, so the campaign was scored under the scenario's assumptions.

``dr_warnings`` finds the first from the DR alone (any campaign, in-process or on the mesh);
``rig_notes`` adds what the controllers reported per episode (``EpisodeResult.model_check``):
the lobe evidence (``Controller.lobe_evidence``: how much better the opposite lobe orientation
fits Rx(dir)'s samples) and whether each episode used a descriptor or the scenario.
"""

from __future__ import annotations

import statistics
from array import array
from collections import Counter
from typing import Any, Iterable

from ra2vipas.services.controller import registry

CHANCE_P_VALUE = 1e-3  # one-sided binomial test of "no better than below chance"
CONTRADICTION_NATS = 3.0  # lobe evidence below -this: the opposite orientation fits e^3 = 20 times better
CONTRADICTED_SHARE = 0.5  # warn when at least this share of the radio episodes is contradicted


def _other_model(rx_dir: str) -> str:
    return {"paper": "db-gain (a gain in dB: its reading peaks when aligned)",
            "db-gain": "the paper's model (a dBm value scaled by rho: its reading dips when aligned)"}.get(rx_dir, "another model")


NO_RX_DIR_BUILTINS = ("ravipas",)
"""The built-ins whose class says ``reads_rx_dir = False`` (RaViPAS uses the camera and Rx(iso)
only), named here: asking the classes loads the controllers (numba; ~0.6 s of CPU the first
time an orchestrator finishes a campaign), which the orchestrator never runs
(tests/policies/test_everywhere.py checks the two agree)."""


def radio_algorithms() -> tuple[str, ...]:
    """The built-ins that read Rx(dir) (``BuiltinPolicy.reads_rx_dir``). A user's policy is never
    counted: which cues it reads is not known here, and a below-chance DR of a policy that may
    ignore Rx(dir), or read it its own way, says nothing of how the rig's antenna was modelled."""
    return tuple(n for n in registry.BUILTINS if n not in NO_RX_DIR_BUILTINS)


def dr_warnings(results: dict[str, Any]) -> list[str]:
    """A warning when every radio algorithm's final DR is far below chance, 1/N (the Tx is one
    of N targets): pooled over the radio algorithms, P(X <= hits | tests, 1/N) < 1e-3 and the DR
    is below half of chance. Such a DR is not bad luck: the controller points *away* from the
    Tx, which is what a wrong Rx(dir) model does."""
    scenario = results.get("scenario") or {}
    n_targets = int(scenario.get("n_targets") or 0)
    tests = int(results.get("tests") or 0)
    radio = {a: block for a, block in (results.get("algorithms") or {}).items() if a in radio_algorithms()}
    if n_targets < 2 or not radio or tests < 1:
        return []
    chance = 1.0 / n_targets
    counted = {a: int(round(block["dr_final"] * tests)) for a, block in radio.items()}
    hits, trials = sum(counted.values()), tests * len(counted)
    if hits / trials >= chance / 2.0:
        return []
    from scipy.stats import binom  # here, not with the module: scipy.stats costs the orchestrator ~1 s of CPU at start

    p_value = float(binom.cdf(hits, trials, chance))
    if p_value >= CHANCE_P_VALUE:
        return []
    rx_dir = scenario.get("antenna_model", "paper")
    listed = ", ".join(f"{a} {block['dr_final']:.2f}" for a, block in radio.items())
    return [f"every radio algorithm's final DR ({listed}) is far below chance (1/N = {chance:.3g}; binomial p = {p_value:.1g}): "
            f"the controllers point away from the Tx, which is what a wrong Rx(dir) model does. The antenna model assumed is "
            f"{rx_dir!r}; if the rig's antenna is {_other_model(rx_dir)}, describe the rig (rx_dir in its descriptor) or set "
            f"antenna_model"]


class RigChecks:
    """What the episodes' model checks say, reduced as the episodes arrive (``add``), in
    memory that does not grow with what a check carries: counts per rig and per assumed Rx(dir)
    response, and the lobe evidence of the contradicted radio episodes only (one float each)."""

    def __init__(self) -> None:
        self.total = 0
        self.with_evidence = 0  # radio episodes that reported lobe evidence
        self.scenario_rigs: Counter = Counter()  # rig -> episodes modelled from the scenario
        self.assumed: Counter = Counter()  # Rx(dir) response assumed -> episodes with lobe evidence
        self.contradicted = array("d")  # lobe evidence below -CONTRADICTION_NATS

    def add(self, rig: str | None, check: dict | None) -> None:
        """One recorded episode: the rig it ran on and its ``model_check`` (None from a v1
        controller)."""
        self.total += 1
        if check is None or check.get("sensor_model") != "descriptor":
            self.scenario_rigs[rig or "?"] += 1
        if check is not None and check.get("lobe_evidence") is not None:
            evidence = float(check["lobe_evidence"])
            self.with_evidence += 1
            self.assumed[check.get("rx_dir", "paper")] += 1
            if evidence < -CONTRADICTION_NATS:
                self.contradicted.append(evidence)

    def notes(self, results: dict[str, Any]) -> dict[str, Any]:
        """Add to ``results`` (in place; also returned) ``assumptions`` when some episodes were
        modelled from the scenario (an undescribed rig or a v1 controller): how many, on which
        rigs; and a warning when Rx(dir)'s samples contradict the assumed response in at least
        half of the radio episodes."""
        if self.scenario_rigs:
            results["assumptions"] = {
                "sensor_model": "scenario", "episodes": sum(self.scenario_rigs.values()), "of": self.total,
                "rigs": sorted(self.scenario_rigs),
                "note": "these episodes ran on undescribed rigs (or v1 controllers): their controllers took the hardware "
                        "(nu, T_RF, field of view, box noise, Rx(dir) response) from the campaign's scenario, and they were "
                        "scored under the scenario's assumptions",
            }
        warnings = list(results.get("warnings") or [])
        contradicted = self.contradicted
        if self.with_evidence and len(contradicted) >= max(1, CONTRADICTED_SHARE * self.with_evidence):
            rx_dir = self.assumed.most_common(1)[0][0]
            warnings.append(
                f"the directional RSSI contradicts the assumed Rx(dir) response {rx_dir!r} in {len(contradicted)} of "
                f"{self.with_evidence} radio episodes (the opposite lobe orientation fits their samples better, by a median of "
                f"{-statistics.median(contradicted):.1f} nats): the rig's antenna is likely {_other_model(rx_dir)}; describe the "
                f"rig (rx_dir: its model, or 'unknown' to have the controller learn it) or set antenna_model")
        if warnings:
            results["warnings"] = warnings
        return results


def rig_notes(results: dict[str, Any], checks: Iterable[tuple[str | None, dict | None]]) -> dict[str, Any]:
    """Add to ``results`` (in place; also returned) what the episodes' model checks say
    (``RigChecks.notes``). ``checks``: per recorded episode, the rig it ran on and its
    ``model_check`` (None from a v1 controller)."""
    reduced = RigChecks()
    for rig, check in checks:
        reduced.add(rig, check)
    return reduced.notes(results)


class TargetingError(ValueError):
    """A campaign contradicts the rigs it targets; ``errors`` are (field, message) pairs, one per
    conflicting field and rig."""

    def __init__(self, errors: list[tuple[str, str]]) -> None:
        super().__init__("; ".join(f"{f}: {m}" for f, m in errors))
        self.errors = errors


def resolve_targeting(scenario, mode: str, rigs: list[str] | None, rig_kind: str | None, use_rig_values: bool,
                      descriptors: dict[str, Any], features: list[tuple[str, str]] | None = None,
                      protocols: dict[str, str | None] | None = None):
    """Check a new campaign against the rigs it targets; return ``(scenario, targeting)``.

    ``descriptors``: every live rig's ``RigDescriptor`` (None: undescribed). The rigs targeted
    are ``rigs`` (those of them that are live), else the live rigs of ``rig_kind``, else every
    live rig. Each targeted rig with a descriptor must agree with the scenario (and support
    ``mode``): a contradicted field is a ``TargetingError`` naming the field, the rig and both
    values, unless ``use_rig_values``, which takes the rigs' values (they must agree among
    themselves; a campaign that searches for more tags than a rig hears, descriptor ``tags``,
    searches for as many as the fewest heard). A campaign that targets no rig in particular runs on the live rigs it agrees
    with, and is refused only when it agrees with none of them. Rigs not live now are checked
    when they come up (the scheduler skips the ones that contradict the campaign).

    ``features``: the newer-than-1.0 protocol features the campaign uses, ``(feature,
    version)`` (``versions.campaign_features``); ``protocols``: the version each live rig
    speaks (None: not known yet, not checked). A targeted rig that does not speak a feature's
    version contradicts the campaign like a hardware field does (the 422 names the rig, the
    feature and both versions); ``use_rig_values`` cannot help there.

    Raises
    ------
    TargetingError
    """
    from ra2vipas.services.protocol.rig import conflicts, fewer_tags, rig_values

    if rigs:
        targeted = [r for r in rigs if r in descriptors]
    elif rig_kind:
        targeted = [r for r, d in descriptors.items() if d is not None and d.kind == rig_kind]
    else:
        targeted = list(descriptors)
    described = {r: descriptors[r] for r in sorted(targeted) if descriptors.get(r) is not None}
    values: dict[str, tuple[Any, str]] = {}
    errors: list[tuple[str, str]] = []
    if use_rig_values:
        for rig, d in described.items():
            for name, value in rig_values(d).items():
                if name in values and values[name][0] != value:
                    errors.append((f"scenario.{name}", f"rigs {values[name][1]} and {rig} disagree ({values[name][0]!r} vs {value!r}); "
                                                       f"target one of them with rigs"))
                values.setdefault(name, (value, rig))
        if errors:
            raise TargetingError(errors)
        heard = [d.tags for d in described.values() if d.tags is not None]
        lowered = fewer_tags(scenario, min(heard) if heard else None)  # no more tags than the fewest any rig hears
        if values or lowered:
            scenario = apply_rig_values_dict(scenario, {**{k: v for k, (v, _) in values.items()}, **lowered})
        if lowered:
            values["n_tags"] = (lowered["n_tags"], "")
    from ra2vipas.services.protocol.versions import describe_missing, missing_features

    found: dict[str, list[tuple[str, str]]] = {}
    for rig, d in described.items():
        for c in conflicts(d, scenario, mode):
            where = "mode" if c.field == "mode" else f"scenario.{c.field}"
            hint = "" if c.field == "mode" else " (use_rig_values takes the rig's)"
            found.setdefault(rig, []).append((where, f"rig {rig} {c.relation} {c.rig!r}, the campaign says {c.campaign!r}{hint}"))
    for rig in sorted(targeted):
        version = (protocols or {}).get(rig)
        if version is None or not features:
            continue
        for feature, needed in missing_features(version, features):
            found.setdefault(rig, []).append((feature, describe_missing(rig, version, feature, needed)))
    if found and (rigs or rig_kind or len(found) == len(targeted)):
        for rig in sorted(found):
            errors.extend(found[rig])
        raise TargetingError(errors)
    targeting = None
    if rigs or rig_kind or use_rig_values:
        targeting = {"rigs": list(rigs) if rigs else None, "rig_kind": rig_kind, "use_rig_values": bool(use_rig_values),
                     "rig_values": {k: v for k, (v, _) in values.items()}}
    return scenario, targeting


def apply_rig_values_dict(scenario, values: dict[str, Any]):
    """``scenario`` with ``values`` (scenario parameters) in place."""
    from ra2vipas.services.protocol.scenario import Scenario

    return Scenario.model_validate({**scenario.model_dump(mode="json"), **values})
