"""The search for K tags at once, and one tag at a time (issue 21): compositions of the parts.

``JointSearch`` runs one episode for K tags with one camera. Per tag k it keeps the single-tag
parts that are about the tag (``composed.Parts``: Rx(iso)'s statistics ``IsoLevel``, the RF
belief over tag k's bearing, the fusion and the confidence map), fed with tag k's RF evidence
only (``tag_view``); the vision belief (the tracker over the people the camera sees and where it
has looked) is one, shared by every tag: the K beliefs are over the same camera tracks. Each
step it:

1. updates every tag's Rx(iso) statistics and RF belief with that tag's packets (or pair), and
   the shared vision belief once with the frames;
2. scores, per tag, "track i carries tag k" and "no detected track does" (``Fusion.beliefs``);
3. names, per tag, a target: on its own (``Fusion.answer``, what a single-tag search names), or,
   when the scenario says one person carries at most one tag, jointly: the MAP assignment by the
   Hungarian algorithm and the exact marginals under the constraint (``multitag``);
4. freezes a tag whose confidence reached ``stop_confidence`` (decided: its answer is final and
   it stops pulling the camera);
5. chooses one pan for every undecided tag (``pan_rule``): ``neediest`` hands the single-tag
   acquisition (warm-up sweep, probes, GP-UCB) the beliefs of the undecided tag whose "which
   person carries it" posterior has the largest entropy; ``entropy`` does the same on probe steps
   and otherwise maximises the sum of the undecided tags' GP-UCB values, each normalised to
   [0, 1] and weighted by its share of the summed entropy (``multitag.pan_weights``). The
   entropy is that of "which person carries tag k", a person the camera has not detected named
   by its bearing (``multitag.which_person_entropy``: "no detected track" is not one certain
   outcome when the bearing it leaves is wide, as for a walker the camera lost).

The episode ends when every tag is decided (``JointDecision.all_decided``) or at the horizon.
``entropy`` is the default: on the paper world with K = 3 and ``stop_confidence`` 0.95 the two
rules decide all tags in the same median time and with the same accuracy, and ``entropy`` has
the shorter tail (docs/tags.md, "Measured").

``SequentialSearch`` is the fair baseline: the single-tag search (a fresh ``Composition``, so a
fresh tracker and warm-up) for tag 0 until it is decided or its share of the remaining horizon
is spent, then tag 1, and so on; each search reads its own tag's RF evidence only.

Neither sees truth: only ``StepMeasurement`` s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Literal

import numpy as np

from ra2vipas.services.controller import _kernels, multitag
from ra2vipas.services.controller.acquisition import GPUCB, Acquisition, Beliefs
from ra2vipas.services.controller.composed import Composition, Decision, Parts, take_iso, update_rf, wrapped
from ra2vipas.services.controller.confidence import Covariates
from ra2vipas.services.controller.fusion import arc_mass, refined_argmax, softmax, softmax_and_logsumexp
from ra2vipas.services.controller.rf_belief import PacketClock
from ra2vipas.services.protocol.construct import builder
from ra2vipas.services.protocol.measurements import Advertisement, RFSample, StepMeasurement

PanRule = Literal["entropy", "neediest"]
PAN_RULES: tuple[str, ...] = ("entropy", "neediest")


#: ``StepMeasurement.model_construct`` for a tag's view (``construct.builder``: what it sets, without walking the fields)
_view = builder(StepMeasurement, "step", "pan_rad", "rf", "frames", "adverts", "rf_tags")


def _relabelled(x: RFSample | Advertisement) -> RFSample | Advertisement:
    """``x.model_copy(update={"tag": 0})``, the same object (the fields copied, ``tag`` 0 and marked
    set; no extra, no private attributes: the measurement models have neither), without pydantic's
    generic copy (~5 us a call, two a ward step)."""
    fields = dict(x.__dict__)
    fields["tag"] = 0
    copied = type(x).__new__(type(x))
    object.__setattr__(copied, "__dict__", fields)
    object.__setattr__(copied, "__pydantic_extra__", None)
    object.__setattr__(copied, "__pydantic_fields_set__", x.__pydantic_fields_set__ | {"tag"})
    object.__setattr__(copied, "__pydantic_private__", None)
    return copied


def tag_view(m: StepMeasurement, tag: int, step: int | None = None) -> StepMeasurement:
    """Tag ``tag``'s evidence of a step as a single-tag step: its pair (paper radio) or its
    advertisements, relabelled tag 0, the frames unchanged; ``step`` renumbers the step (a search
    that started later counts from its own start).

    Parameters
    ----------
    m : StepMeasurement
        The step as the rig sent it (every tag's evidence).
    tag : int
        k, the tag whose evidence is kept.
    step : int, optional
        The step index the view carries (default ``m.step``).

    Returns
    -------
    StepMeasurement
        No RF evidence at all when tag k was not heard this step.
    """
    t = int(m.step) if step is None else int(step)
    rf = m.rf
    if rf is not None:
        # the first of m.pairs() (rf, then rf_tags) naming the tag, without building the tuple
        pair = rf if rf.tag == tag else next((p for p in m.rf_tags if p.tag == tag), None)
        rf = None if pair is None else (pair if pair.tag == 0 else _relabelled(pair))
        return _view(t, m.pan_rad, rf, m.frames, (), ())
    ads = tuple(a if a.tag == 0 else _relabelled(a) for a in m.adverts if a.tag == tag)
    return _view(t, m.pan_rad, None, m.frames, ads, ())


@dataclass(frozen=True)
class TagDecision:
    """What the controller names for one tag after a step.

    Attributes
    ----------
    tag : int
        k.
    estimate_rad : float
        The bearing named as tag k's carrier (gamma_hat_t of tag k; final once decided).
    confidence : float
        The probability that the target named carries tag k (calibrated by the algorithm's map).
    raw_confidence : float
        The same under the controller's own model.
    decided_step : int or None
        The step at which the confidence reached ``stop_confidence`` (None: not decided).
    covariates : Covariates or None
        What the confidence map conditioned on for this tag (``confidence.Covariates``; what
        ``calibration.collect_joint`` fits the joint map on).
    """

    tag: int
    estimate_rad: float
    confidence: float
    raw_confidence: float
    decided_step: int | None = None
    covariates: Covariates | None = None


@dataclass(frozen=True)
class JointDecision(Decision):
    """A step's decision for K tags: the ``Decision`` fields describe tag 0 (what a single-tag
    reader reads), ``tags`` every tag, ``all_decided`` whether the episode may end."""

    tags: tuple[TagDecision, ...] = ()
    all_decided: bool = False
    lead_tag: int = 0  # the tag whose beliefs chose the pan (the neediest undecided one)


@dataclass(slots=True)
class JointBeliefs(Beliefs):
    """``Beliefs`` of the lead tag, with every tag's and their weights in the pan (``entropy``)."""

    per_tag: tuple = ()
    weights: np.ndarray | None = None


def gpucb_values(b: Beliefs, gpucb: GPUCB) -> np.ndarray:
    """a(s) = U_D(s) (J_RF(s) + sqrt(beta) sigma(s)) over the whole grid for one tag's beliefs
    (what ``GPUCB.next_pan`` maximises, ``_kernels.acquire``), as an array (``_kernels.ucb_grid``)."""
    circle = gpucb.circle
    mean, sd, amplitude, offset = b.rf.gain_prediction()
    vision = b.vision
    use_mass = vision.sees and gpucb.use_mass
    mass = np.zeros(circle.size)
    view = vision.view_frames if use_mass else mass
    if use_mass and b.post.size:
        w = int(math.floor(vision.tracks.count_limit / circle.step + 1e-9))
        # np.add.at(mass, (rint((bearing + pi) / step) % M)[:, None] + arange(-w, w + 1)) % M, max(post, 0)), compiled
        mass = _kernels.mass_grid(np.asarray(vision.tracks.bearing, dtype=float), np.asarray(b.post, dtype=float), circle.step, w,
                                  circle.size)
    value = np.empty(circle.size)
    _kernels.ucb_grid(np.asarray(mean, dtype=float), np.asarray(sd, dtype=float), float(offset), float(amplitude),
                      math.sqrt(gpucb.beta), mass, view, 2.0 * gpucb.frames_per_rf, use_mass, value)
    return value


class SummedGPUCB(Acquisition):
    """GP-UCB for several tags: argmax_s sum_k w_k a_k(s), each tag's a_k (``gpucb_values``)
    rescaled to [0, 1] and w_k its share of the summed entropy (0 once decided). Given a single
    tag's ``Beliefs`` it is ``GPUCB``.

    Parameters
    ----------
    gpucb : GPUCB
        The single-tag acquisition (grid, nu, beta, whether U_D weighs).
    """

    def __init__(self, gpucb: GPUCB) -> None:
        self.gpucb = gpucb
        self.circle = gpucb.circle

    def next_pan(self, b: Beliefs) -> tuple[float, bool]:
        weights = getattr(b, "weights", None)
        if weights is None or not getattr(b, "per_tag", ()):
            return self.gpucb.next_pan(b)
        total = np.zeros(self.circle.size)
        for w, tag_beliefs in zip(weights, b.per_tag):
            if w <= 0.0:
                continue
            _kernels.add_normalised(gpucb_values(tag_beliefs, self.gpucb), float(w), total)  # total += w (a - min a) / (max a - min a)
        return float(self.circle.angles[int(np.argmax(total))]), False


def with_summed_gpucb(acquisition: Acquisition) -> Acquisition:
    """The acquisition chain with its ``GPUCB`` (wherever in the ``then`` chain) replaced by a
    ``SummedGPUCB`` over it (the other links keep reading the lead tag's beliefs)."""
    if isinstance(acquisition, GPUCB):
        return SummedGPUCB(acquisition)
    then = getattr(acquisition, "then", None)
    if isinstance(then, Acquisition):
        acquisition.then = with_summed_gpucb(then)
    return acquisition


class JointSearch:
    """One episode of the search for K tags at once (module docstring): create it, call
    ``first_pan()``, then ``step`` for every sample.

    Parameters
    ----------
    first_pan_rad : float
        s_0.
    tags : list of Parts
        One set of parts per tag, all with the same ``vision`` (the shared camera tracks); tag
        0's ``acquisition`` chooses the pans (the others' are not used).
    rf_period_s : float
        T_RF.
    pan_rule : {"entropy", "neediest"}
        How the one pan serves the undecided tags.
    one_tag_per_person : bool
        Whether a track carries at most one tag (then the answers are a joint assignment).
    stop_confidence : float
        A tag whose confidence reaches it is decided (0: never).
    missed_bearings : bool
        A tag's entropy in the pan counts where an undetected carrier may be: the entropy of
        "which person carries tag k", an undetected person named by its bearing
        (``multitag.which_person_entropy``); False: of "which track, or none" alone, where a tag
        whose carrier no track explains (a walker the camera lost) weighs nothing however wide
        its bearing (docs/tags.md, "Measured").
    """

    def __init__(self, first_pan_rad: float, tags: list[Parts], rf_period_s: float = 0.1, pan_rule: PanRule = "entropy",
                 one_tag_per_person: bool = True, stop_confidence: float = 0.0, missed_bearings: bool = True) -> None:
        if not tags:
            raise ValueError("a joint search needs at least one tag")
        if any(p.vision is not tags[0].vision for p in tags):
            raise ValueError("every tag's parts must share one vision belief (the camera's tracks)")
        if pan_rule not in PAN_RULES:
            raise ValueError(f"unknown pan rule {pan_rule!r}: {' or '.join(PAN_RULES)}")
        self.parts = tags
        self.vision = tags[0].vision
        self.rf_period_s = float(rf_period_s)
        self.pan_rule = pan_rule
        self.one_tag_per_person = bool(one_tag_per_person)
        self.stop_confidence = float(stop_confidence)
        acquisition = tags[0].acquisition
        self.acquisition = with_summed_gpucb(acquisition) if pan_rule == "entropy" else acquisition
        self.clocks = [PacketClock(rf_period_s) for _ in tags]
        self.decided: list[TagDecision | None] = [None] * len(tags)
        self._first_pan = wrapped(first_pan_rad)
        self.missed_bearings = bool(missed_bearings)

    @property
    def n_tags(self) -> int:
        """K."""
        return len(self.parts)

    @property
    def tracks(self):
        """The shared ``BearingTracker`` (None without a camera)."""
        return self.vision.tracks

    def first_pan(self) -> float:
        """s_0, the pan angle of the first sample."""
        return self._first_pan

    def step(self, m: StepMeasurement) -> JointDecision:
        """Take step t's measurement (every tag's evidence); return s_{t+1}, each tag's answer and
        whether all are decided."""
        s, t = float(m.pan_rad), int(m.step)
        vision = self.vision
        for k, p in enumerate(self.parts):  # as Composition.step, per tag on its own evidence; the tracks once
            view = tag_view(m, k)
            packets = take_iso(p, view, self.clocks[k], self.rf_period_s)
            if k == 0 and vision.sees:
                vision.update(s, m.frames)
            update_rf(p, s, view, packets)
        scored = [p.fusion.beliefs(p.rf, vision, p.iso) for p in self.parts]
        which = self._which_track(scored)
        answers = self._answers(scored, which)
        tags: list[TagDecision] = []
        for k, (p, (estimate, raw, _post)) in enumerate(zip(self.parts, answers)):
            if self.decided[k] is not None:
                tags.append(self.decided[k])
                continue
            cov = p.confidence.covariates(estimate, p.rf, vision, p.iso)
            confidence = round(p.confidence(raw, cov), 6)
            decision = TagDecision(tag=k, estimate_rad=wrapped(estimate), confidence=confidence, raw_confidence=float(raw),
                                   covariates=cov)
            if self.stop_confidence > 0.0 and confidence >= self.stop_confidence:
                decision = replace(decision, decided_step=t)
                self.decided[k] = decision
            tags.append(decision)
        open_ = [d is None for d in self.decided]
        where_missed = None
        if self.missed_bearings and self.vision.sees:  # an undetected carrier is named by its bearing
            where_missed = self._missed_reads(scored)[0]
        weights = multitag.pan_weights(which, [not o for o in open_], self.pan_rule, where_missed)
        lead = int(weights.argmax()) if weights.any() else 0  # np.argmax, np.any without their Python wrappers
        per_tag = tuple(Beliefs(t, p.rf, vision, scored[k][0], answers[k][2], self._due(k, t)) for k, p in enumerate(self.parts))
        lead_beliefs = per_tag[lead]
        b = JointBeliefs(t, lead_beliefs.rf, vision, lead_beliefs.l_tracks, lead_beliefs.post, lead_beliefs.packet_due,
                         per_tag=per_tag, weights=weights)
        next_pan, probe = self.acquisition.next_pan(b)
        lead_parts = self.parts[lead]
        reward = vision.mass_at(s, answers[lead][2]) * lead_parts.rf.gain_at(s)
        first = tags[0]
        p0 = self.parts[0]
        cov0 = p0.confidence.covariates(first.estimate_rad, p0.rf, vision, p0.iso)
        return JointDecision(step=t, next_pan_rad=wrapped(next_pan), estimate_rad=first.estimate_rad, reward=reward, probe=probe,
                             confidence=first.confidence, raw_confidence=first.raw_confidence, tx_walks=cov0.tx_walks,
                             noise_correlation=cov0.noise_correlation, clutter_density=cov0.clutter_density,
                             crowding=cov0.crowding, tags=tuple(tags), all_decided=not any(open_), lead_tag=lead)

    def _missed_reads(self, scored) -> tuple[np.ndarray, list[float]]:
        """Per tag, softmax(l_missed) (row k of a (K, grid) array) and logsumexp(l_missed) of a
        step's ``scored`` (the pan's entropy, the joint posteriors and the answers each read them),
        computed once per ``scored`` (every tag's l_missed is over the one pan grid)."""
        kept = self._kept(scored)
        if kept[1] is None:
            where = np.empty((len(scored), scored[0][1].size))
            kept[2] = [softmax_and_logsumexp(l_missed, out=row)[1] for (_, l_missed), row in zip(scored, where)]
            kept[1] = where
        return kept[1], kept[2]

    def _track_logliks(self, scored) -> np.ndarray:
        """Every tag's l_k(i) of a step's ``scored`` as one (K, M) array, stacked once per ``scored``."""
        kept = self._kept(scored)
        if kept[3] is None:
            kept[3] = np.stack([s[0] for s in scored])
        return kept[3]

    def _kept(self, scored) -> list:
        """What ``_missed_reads`` and ``_track_logliks`` made of ``scored`` (None: not yet), kept
        until the next step's ``scored``."""
        kept = getattr(self, "_reads_kept", None)
        if kept is None or kept[0] is not scored:
            kept = self._reads_kept = [scored, None, None, None]
        return kept

    def _due(self, k: int, t: int) -> bool | None:
        clock = self.clocks[k]
        return clock.due(t + 1) if clock.last is not None else None

    def _which_track(self, scored) -> np.ndarray:
        """Each tag's posterior over "track i carries it" and "no detected track does" (K, M + 1);
        without a camera, over the grid of bearings (K, grid)."""
        if not self.vision.sees:
            return np.stack([softmax((1.0 if p.rf.exact else p.fusion.rf_weight) * p.rf.log_likelihood) for p in self.parts])
        tracks = self._track_logliks(scored)
        missed = np.array(self._missed_reads(scored)[1])
        if self._jointly():
            return multitag.exclusive_posteriors(tracks, missed)
        return multitag.independent_posteriors(tracks, missed)

    def _jointly(self) -> bool:
        """Whether the answers are a joint assignment: one person one tag, K > 1, tracks to assign."""
        return self.one_tag_per_person and self.n_tags > 1 and self.vision.sees and len(self.vision.tracks) > 0

    def _answers(self, scored, which: np.ndarray) -> list[tuple[float, float, np.ndarray]]:
        """Per tag (estimate, raw confidence, tracks' posterior): each on its own
        (``Fusion.answer``), or jointly when a person carries at most one tag (``which``: the
        marginals under that constraint, ``_which_track``)."""
        if not self._jointly():
            return [p.fusion.answer(p.rf, l_tracks, l_missed, self._first_pan) for p, (l_tracks, l_missed) in zip(self.parts, scored)]
        tracks = self._track_logliks(scored)
        m = tracks.shape[1]
        marginals = which
        half = [max(1, int(round(p.fusion.answer_window_rad / p.fusion.circle.step))) for p in self.parts]
        # the assignment weighs "missed" as the answer would: the mass of its best arc, not all of it
        missed_arc = []
        where_missed, missed_lse = self._missed_reads(scored)  # where an undetected carrier of tag k would be
        for lse, post, h in zip(missed_lse, where_missed, half):
            missed_arc.append(lse + math.log(max(arc_mass(post, int(post.argmax()), h), 1e-300)))
        assignment = multitag.joint_assignment(tracks, np.array(missed_arc))
        out = []
        for k, (p, (_, l_missed), a) in enumerate(zip(self.parts, scored, assignment)):
            post_tracks = marginals[k, :m]
            missed = where_missed[k]
            if a < m:
                estimate = float(p.fusion.where[a])
                if p.rf.listens and p.fusion.walker_answer_from_rf and p.rf.tx_walks > 0.5:
                    estimate = refined_argmax(p.fusion.circle, p.rf.log_likelihood)
                raw = float(marginals[k, a])
            else:
                estimate = refined_argmax(p.fusion.circle, l_missed)
                raw = 0.0
            # as Fusion.answer: the mass of "an undetected target near the answer" (e.g. right behind it) counts too
            raw += float(marginals[k, m]) * arc_mass(missed, p.fusion.circle.nearest(estimate), half[k])
            out.append((estimate, raw, post_tracks))
        return out

    def lobe_evidence(self) -> float | None:
        """Tag 0's RF belief's model check (``RFBelief.lobe_evidence``)."""
        return self.parts[0].rf.lobe_evidence()

    @property
    def lobe(self) -> str | None:
        """Tag 0's lobe orientation in use."""
        return self.parts[0].rf.lobe


class SequentialSearch:
    """The one-tag-at-a-time baseline: the single-tag search for tag 0, then tag 1, ..., each a
    fresh ``Composition`` reading its own tag's RF evidence only. Tag k's search ends when its
    confidence reaches ``stop_confidence`` (decided) or when it has used its share of the
    remaining horizon (the steps left over the tags left); its last answer then stands.

    Parameters
    ----------
    first_pan_rad : float
        s_0.
    new_parts : callable
        Builds the single-tag parts of a fresh search.
    n_tags : int
        K.
    steps : int
        n_test, the horizon shared by the K searches.
    rf_period_s : float
        T_RF.
    stop_confidence : float
        A search whose confidence reaches it decides its tag (0: each tag gets its share).
    """

    def __init__(self, first_pan_rad: float, new_parts: Callable[[], Parts], n_tags: int, steps: int, rf_period_s: float = 0.1,
                 stop_confidence: float = 0.0) -> None:
        self.new_parts, self.n_tags, self.steps = new_parts, int(n_tags), int(steps)
        self.rf_period_s, self.stop_confidence = float(rf_period_s), float(stop_confidence)
        self._first_pan = wrapped(first_pan_rad)
        self.answers: list[TagDecision] = [TagDecision(tag=k, estimate_rad=self._first_pan, confidence=0.0, raw_confidence=0.0)
                                           for k in range(self.n_tags)]
        self.active = 0
        self._search: Composition | None = None
        self._first_search: Composition | None = None
        self._start = 0
        self._budget = self.steps // max(self.n_tags, 1)

    def first_pan(self) -> float:
        """s_0."""
        return self._first_pan

    def step(self, m: StepMeasurement) -> JointDecision:
        """Take step t's measurement; the active tag's search reads it."""
        t = int(m.step)
        next_pan, probe, reward = float(m.pan_rad), False, 0.0
        first: Decision | None = None
        k = self.active
        if k < self.n_tags:
            if self._search is None:
                self._search = Composition(m.pan_rad, self.new_parts(), rf_period_s=self.rf_period_s)
                self._first_search = self._first_search or self._search
                self._start = t
                self._budget = max((self.steps - t) // (self.n_tags - k), 1)
            first = self._search.step(tag_view(m, k, step=t - self._start))
            next_pan, probe, reward = first.next_pan_rad, first.probe, first.reward
            decided = self.stop_confidence > 0.0 and first.confidence >= self.stop_confidence
            self.answers[k] = TagDecision(tag=k, estimate_rad=first.estimate_rad, confidence=first.confidence,
                                          raw_confidence=first.raw_confidence, decided_step=t if decided else None)
            if decided or t + 1 - self._start >= self._budget:
                self.active += 1
                self._search = None
        zero = self.answers[0]
        all_decided = all(a.decided_step is not None for a in self.answers)
        return JointDecision(step=t, next_pan_rad=wrapped(next_pan), estimate_rad=zero.estimate_rad, reward=reward, probe=probe,
                             confidence=zero.confidence, raw_confidence=zero.raw_confidence,
                             tags=tuple(self.answers), all_decided=all_decided, lead_tag=min(k, self.n_tags - 1))

    def lobe_evidence(self) -> float | None:
        """Tag 0's search's model check (``RFBelief.lobe_evidence``)."""
        return None if self._first_search is None else self._first_search.lobe_evidence()

    @property
    def lobe(self) -> str | None:
        """Tag 0's search's lobe orientation."""
        return None if self._first_search is None else self._first_search.lobe
