"""Several tags at once (issue 21): K beliefs over the shared camera tracks, decided jointly.

With K tags in a scene, every pan tells something about all of them: the receivers hear every
tag at every step, the camera sees every person in view. The controller keeps, per tag k, the
fused log-likelihood that camera track i carries it (l_k(i) = l_RF,k(gamma_i) + l_D,k(i), the
single-tag fusion applied to tag k's own RF evidence and POD) and of "no detected track carries
it" (the missed hypothesis, summed over the bearings no track covers). This module turns those
K rows into what the controller reports and where it looks:

* ``independent_posteriors``: each tag's posterior on its own (two tags may sit on one person:
  a person may carry two tags, the default);
* ``exclusive_posteriors`` / ``joint_assignment``: when the scenario says one person carries at
  most one tag, the posterior marginals and the MAP assignment under that constraint, solved
  jointly (the Hungarian algorithm on the K x tracks log-likelihoods,
  ``scipy.optimize.linear_sum_assignment``), never greedily tag after tag;
* ``pan_weights``: how much each tag's acquisition value counts in the one pan chosen for all
  (a decided tag, confidence above ``stop_confidence``, counts nothing), by the entropy of
  "which person carries tag k" (``which_person_entropy``: a person the camera never detected is
  named by its bearing).

numpy/scipy and one compiled kernel (the inclusion-exclusion sum, ``_kernels.exclusive_marginals``):
a unit test drives it without a network or a world.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.special import logsumexp

from ra2vipas.services.controller import _kernels

#: The inclusion-exclusion sum is trusted when every tag's total is at least this share of its
#: largest term (double precision keeps ~16 digits; below 1e-9 the cancellation could eat 7).
RELIABLE_SHARE = 1e-9
#: A track whose weight is below this share of each tag's largest weight is left out of the
#: constraint when the joint assignments are enumerated one by one.
NEGLIGIBLE = 1e-12
#: Most joint assignments enumerated (in numpy) when inclusion-exclusion cannot be trusted.
ENUMERATION_LIMIT = 200_000
#: A log-likelihood standing for "impossible" in the assignment's cost matrix: finite, as
#: ``linear_sum_assignment`` requires, and far below any real difference of log-likelihoods.
IMPOSSIBLE = -1e9

PanRule = Literal["entropy", "neediest"]


def _checked(track_loglik, missed_loglik) -> tuple[np.ndarray, np.ndarray]:
    tracks = np.asarray(track_loglik, dtype=float)
    missed = np.asarray(missed_loglik, dtype=float)
    if tracks.ndim != 2 or missed.shape != (tracks.shape[0],):
        raise ValueError(f"track_loglik must be (K, M) and missed_loglik (K,); got {tracks.shape} and {missed.shape}")
    return tracks, missed


def independent_posteriors(track_loglik, missed_loglik) -> np.ndarray:
    """Each tag's posterior over "track i carries it" (columns 0..M-1) and "no detected track
    does" (column M), on its own.

    Parameters
    ----------
    track_loglik : array of shape (K, M)
        l_k(i), tag k's fused log-likelihood of track i.
    missed_loglik : array of shape (K,)
        Tag k's log-likelihood of being carried by no detected track.

    Returns
    -------
    array of shape (K, M + 1), rows summing to 1.
    """
    tracks, missed = _checked(track_loglik, missed_loglik)
    full = np.concatenate([tracks, missed[:, None]], axis=1)
    return np.exp(full - logsumexp(full, axis=1, keepdims=True))


_LSA = None


def _linear_sum_assignment():
    """scipy's ``linear_sum_assignment``, imported on first use (scipy.optimize costs every rig ~0.3 s
    of CPU at start) and kept (an import statement per call costs ~20 us: scipy's lazy loader)."""
    global _LSA
    if _LSA is None:
        from scipy.optimize import linear_sum_assignment

        _LSA = linear_sum_assignment
    return _LSA


def joint_assignment(track_loglik, missed_loglik) -> np.ndarray:
    """The MAP assignment of tags to tracks when a track carries at most one tag.

    Maximises sum_k l_k(a_k) over assignments where no two tags share a track, "missed" (no
    detected track) being open to every tag: the Hungarian algorithm on a K x (M + K) matrix whose
    last K columns are each tag's own "missed" (Kuhn-Munkres; ``linear_sum_assignment``).

    Returns
    -------
    array of shape (K,): the track index of each tag, M for "missed".
    """
    tracks, missed = _checked(track_loglik, missed_loglik)
    k, m = tracks.shape
    gain = np.full((k, m + k), IMPOSSIBLE)  # [tracks | each tag's own "missed" on the diagonal, IMPOSSIBLE off it]
    gain[:, :m] = tracks
    tag = np.arange(k)
    gain[tag, m + tag] = missed
    rows, cols = _linear_sum_assignment()(gain, maximize=True)
    out = np.empty(k, dtype=np.int64)
    out[rows] = np.minimum(cols, m)  # np.where(cols < m, cols, m): any tag's own "missed" is column m
    return out


def exclusive_posteriors(track_loglik, missed_loglik) -> np.ndarray:
    """The posterior marginals of each tag when a track carries at most one tag.

    P(a) is proportional to prod_k w_k(a_k), w_k = exp(l_k), over the assignments a in which no
    two tags share a track ("missed", column M, may be shared); the marginal of tag k sums over
    the others. Summed exactly by inclusion-exclusion over the partitions of the tags (Moebius
    function of the partition lattice: mu = prod over blocks of (-1)^(|B|-1) (|B|-1)!), which
    costs Bell(K) x K x M (5 partitions for 3 tags) instead of (M + 1) ** K; where that sum
    cancels too much to trust in double precision (tags all but certain of one track), it is
    enumerated over the tracks that carry any weight (``_enumerated``). The sum is compiled
    (``_kernels.exclusive_marginals``), the weights exp(l_k - max l_k) numpy's.

    Returns
    -------
    array of shape (K, M + 1), rows summing to 1.
    """
    tracks, missed = _checked(track_loglik, missed_loglik)
    k, m = tracks.shape
    if k == 1 or m == 0:
        return independent_posteriors(tracks, missed)
    full = np.concatenate([tracks, missed[:, None]], axis=1)
    w = np.exp(full - full.max(axis=1, keepdims=True))  # (K, M + 1), each row's largest 1
    out = np.empty_like(w)
    if _kernels.exclusive_marginals(w, m, *_partition_runs(k), RELIABLE_SHARE, out):
        return out
    return _enumerated(w, m, full - full.max(axis=1, keepdims=True))


_PARTITIONS: dict[int, list] = {}
_RUNS: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _partition_runs(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``_partitions_of(k)`` as the runs ``_kernels.exclusive_marginals`` reads: partition p's blocks
    are ``part_start[p]:part_start[p + 1]``, block b's tags ``block_tags[block_start[b]:block_start[b + 1]]``
    (in ``_partitions``' order, which fixes the order of every product and sum), made once per K."""
    runs = _RUNS.get(k)
    if runs is None:
        part_start, block_start, block_tags = [0], [0], []
        for blocks in _partitions_of(k):
            for block in blocks:
                block_tags.extend(block)
                block_start.append(len(block_tags))
            part_start.append(len(block_start) - 1)
        runs = _RUNS[k] = tuple(np.array(a, dtype=np.int64) for a in (part_start, block_start, block_tags))
    return runs


def _partitions_of(k: int) -> list:
    """``list(_partitions(list(range(k))))``, made once per K."""
    partitions = _PARTITIONS.get(k)
    if partitions is None:
        partitions = _PARTITIONS[k] = list(_partitions(list(range(k))))
    return partitions


def _partitions(items: list[int]):
    """Every partition of ``items`` into blocks (Bell(len(items)) of them)."""
    if len(items) == 1:
        yield [items]
        return
    first, rest = items[0], items[1:]
    for smaller in _partitions(rest):
        for i in range(len(smaller)):
            yield smaller[:i] + [[first, *smaller[i]]] + smaller[i + 1:]
        yield [[first], *smaller]


def _enumerated(w: np.ndarray, m: int, log_w: np.ndarray) -> np.ndarray:
    """``exclusive_posteriors`` by summing the joint assignments one by one (in numpy), over the
    tracks some tag gives at least ``NEGLIGIBLE`` of its largest weight, at most the
    ``ENUMERATION_LIMIT``-th root of them by weight; the others are left open to every tag, as
    "missed" is (ruling out a track no tag can be on changes nothing at that share).

    ``w`` are the weights exp(``log_w``). Where every assignment the constraint allows has
    weights that underflow to 0 (tags each certain of one track, the same one, everything else
    hundreds of nats below), the same sum is taken over the log-weights (``_enumerated_in_logs``)."""
    k = w.shape[0]
    kept, rest = _enumerated_tracks(w, m)
    open_weight = w[:, m] + w[:, rest].sum(axis=1)  # (K,): missed and the tracks left open
    cols = np.concatenate([w[:, kept], open_weight[:, None]], axis=1)  # (K, c + 1)
    c = kept.size
    joint = np.ones((c + 1,) * k)
    for tag in range(k):
        shape = [1] * k
        shape[tag] = c + 1
        joint = joint * cols[tag].reshape(shape)
    joint = _excluded(joint, c, 0.0)
    out = np.stack([joint.sum(axis=tuple(ax for ax in range(k) if ax != tag)) for tag in range(k)])
    full = np.zeros_like(w)
    full[:, kept] = out[:, :c]
    with np.errstate(invalid="ignore", divide="ignore"):  # an open column of weight 0 took nothing: 0, not 0 / 0
        spread = np.where(open_weight > 0.0, out[:, c] / open_weight, 0.0)  # what the open column took, shared in proportion
    full[:, m] = w[:, m] * spread
    full[:, rest] = w[:, rest] * spread[:, None]
    total = full.sum(axis=1, keepdims=True)
    if not (total > 0.0).all():  # every allowed assignment underflowed: the same sum in logs
        return _enumerated_in_logs(log_w, kept, rest)
    return full / total


def _enumerated_tracks(w: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The tracks ``_enumerated`` sums over one by one (sorted), and the tracks it leaves open."""
    k = w.shape[0]
    strongest = w[:, :m].max(axis=0)
    order = np.argsort(-strongest, kind="stable")
    most = max(1, int(ENUMERATION_LIMIT ** (1.0 / k)) - 1)
    kept = np.sort(order[: min(most, int((strongest >= NEGLIGIBLE).sum()))])
    return kept, np.setdiff1d(np.arange(m), kept)


def _excluded(joint: np.ndarray, c: int, nothing: float) -> np.ndarray:
    """``joint`` (one axis per tag, c tracks and the open column each) with every assignment in
    which two tags share a track set to ``nothing`` (0, or -inf in logs)."""
    k = joint.ndim
    grids = np.indices((c + 1,) * k, sparse=True)
    for a in range(k):
        for b in range(a + 1, k):
            joint = np.where((grids[a] == grids[b]) & (grids[a] < c), nothing, joint)
    return joint


def _enumerated_in_logs(log_w: np.ndarray, kept: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """``_enumerated``'s sum over the same tracks, in log-weights: the marginals where every
    assignment the constraint allows is too unlikely for its weight to be a double."""
    k, width = log_w.shape
    m = width - 1
    c = kept.size
    log_open = logsumexp(np.concatenate([log_w[:, m:], log_w[:, rest]], axis=1), axis=1)  # (K,)
    cols = np.concatenate([log_w[:, kept], log_open[:, None]], axis=1)
    joint = np.zeros((c + 1,) * k)
    for tag in range(k):
        shape = [1] * k
        shape[tag] = c + 1
        joint = joint + cols[tag].reshape(shape)
    joint = _excluded(joint, c, -np.inf)
    out = np.stack([logsumexp(joint, axis=tuple(ax for ax in range(k) if ax != tag)) for tag in range(k)])
    full = np.full(log_w.shape, -np.inf)
    full[:, kept] = out[:, :c]
    spread = out[:, c] - log_open
    full[:, m] = log_w[:, m] + spread
    full[:, rest] = log_w[:, rest] + spread[:, None]
    return np.exp(full - logsumexp(full, axis=1, keepdims=True))


def entropy(posteriors) -> np.ndarray:
    """Shannon entropy [nats] of each row of a (K, C) array of posteriors."""
    p = np.ascontiguousarray(posteriors, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_p = np.log(p)
    out = np.empty(p.shape[0])
    _kernels.row_entropies(p, log_p, out)  # np.where(p > 0, -p * log_p, 0.0).sum(axis=1), compiled
    return out


def which_person_entropy(posteriors, where_missed=None) -> np.ndarray:
    """Entropy [nats] of each tag's "which person carries it" posterior, an undetected person
    named by its bearing: H(tracks, missed) + P(missed) H(bearing | missed) (the chain rule).

    ``posteriors`` (K, M + 1) is each tag's posterior over "track i carries it" and "no detected
    track does" (column M); ``where_missed`` (K, G), optional, each tag's posterior over the grid
    bearing of an undetected carrier (``Fusion.beliefs``' l_missed, normalised). Without it, the
    entropy of ``posteriors`` alone, where "missed" counts as one certain outcome however wide the
    bearing it leaves open (a walker the camera lost, found only by Rx(dir), then pulls nothing).
    """
    if where_missed is None:
        return entropy(posteriors)
    p = np.ascontiguousarray(posteriors, dtype=float)
    where = np.ascontiguousarray(where_missed, dtype=float)
    if where.ndim != 2 or where.shape[0] != p.shape[0]:
        raise ValueError(f"where_missed must be (K, G) for posteriors of {p.shape[0]} tags; got {where.shape}")
    with np.errstate(divide="ignore", invalid="ignore"):  # the two logs under one errstate (~2 us each)
        log_p, log_where = np.log(p), np.log(where)
    out = np.empty(p.shape[0])
    _kernels.which_person_entropies(p, log_p, where, log_where, out)  # entropy(p) + p[:, -1] * entropy(where), compiled
    return out


def pan_weights(posteriors, decided, rule: PanRule = "entropy", where_missed=None) -> np.ndarray:
    """How much each tag's acquisition value counts in the one pan chosen for all K.

    ``entropy``: in proportion to each undecided tag's posterior entropy (the summed entropy of
    the K "which person carries tag k" posteriors is what a pan should reduce, and a tag's share
    of it is its entropy); ``neediest``: all weight on the undecided tag with the largest
    entropy. A decided tag weighs 0; with every tag decided all weights are 0 (the episode ends).
    The entropy is ``which_person_entropy`` (with ``where_missed``: an undetected carrier's
    bearing counts; without: "which track, or none" alone).

    Returns
    -------
    array of shape (K,), summing to 1 (or all 0).
    """
    h = which_person_entropy(posteriors, where_missed)
    open_ = ~np.asarray(decided, dtype=bool)
    if h.shape != open_.shape:
        raise ValueError(f"one decided flag per tag: {open_.shape} for {h.shape[0]} tags")
    if rule not in ("entropy", "neediest") and open_.any():  # (with every tag decided, any rule gives zeros)
        raise ValueError(f"unknown pan rule {rule!r}: entropy or neediest")
    out = np.empty_like(h)
    # no tag open: zeros; neediest: out[argmax(np.where(open_, h, -inf))] = 1; entropy: w = np.where(open_, h, 0), all open
    # tags alike when w.sum() <= 0 (every open tag already certain), w / w.sum(): compiled, the same doubles
    _kernels.pan_shares(h, open_, rule == "neediest", out)
    return out
