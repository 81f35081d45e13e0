"""Several tags at once (issue 21): joint decisions over the shared camera tracks, by hand."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.special import logsumexp

from ra2vipas.services.controller.multitag import (
    IMPOSSIBLE,
    entropy,
    exclusive_posteriors,
    independent_posteriors,
    joint_assignment,
    pan_weights,
    which_person_entropy,
)

LOG = math.log


def _brute_force_marginals(tracks, missed):
    k, m = tracks.shape
    full = np.concatenate([tracks, missed[:, None]], axis=1)
    out = np.zeros_like(full)
    for a in itertools.product(range(m + 1), repeat=k):
        real = [x for x in a if x < m]
        if len(real) != len(set(real)):
            continue
        w = math.exp(sum(full[t, x] for t, x in enumerate(a)))
        for t, x in enumerate(a):
            out[t, x] += w
    return out / out.sum(axis=1, keepdims=True)


def test_one_tag_is_the_single_tag_posterior_with_or_without_the_constraint():
    tracks = np.array([[0.3, -1.0, 2.0]])
    missed = np.array([-0.5])
    independent = independent_posteriors(tracks, missed)
    assert independent.sum() == pytest.approx(1.0)
    assert np.allclose(exclusive_posteriors(tracks, missed), independent)
    assert joint_assignment(tracks, missed).tolist() == [2]


def test_two_tags_on_neighbouring_people_are_resolved_as_the_likelihoods_say():
    # people 0 and 1 stand side by side; tag A's radio favours 0 a little, tag B's favours 0 much more.
    tracks = np.array([[LOG(0.55), LOG(0.45)], [LOG(0.9), LOG(0.1)]])
    missed = np.array([LOG(1e-6)] * 2)
    # without the constraint both name person 0 (a person may carry two tags)
    assert independent_posteriors(tracks, missed)[:, :2].argmax(axis=1).tolist() == [0, 0]
    # one person, one tag: A -> 1, B -> 0 (0.45 x 0.9 > 0.55 x 0.1), and A's marginal follows
    assert joint_assignment(tracks, missed).tolist() == [1, 0]
    post = exclusive_posteriors(tracks, missed)
    assert post[0, 1] > 0.8 and post[1, 0] > 0.8


def test_the_assignment_is_joint_where_greedy_fails():
    """Greedy, tag by tag in order of confidence, takes track 0 for tag 0 (its best, 0.5) and leaves
    tag 1 and tag 2 to fight over track 1; the joint optimum gives track 0 to tag 1."""
    tracks = np.log(np.array([[0.5, 0.3, 0.2],
                              [0.45, 0.45, 0.1],
                              [0.05, 0.9, 0.05]]))
    missed = np.full(3, -30.0)
    greedy, taken = [], set()
    for t in np.argsort(-tracks.max(axis=1)):  # the most confident tag first
        best = max((i for i in range(3) if i not in taken), key=lambda i: tracks[t, i])
        taken.add(best)
        greedy.append((int(t), best))
    greedy_score = sum(tracks[t, i] for t, i in greedy)
    joint = joint_assignment(tracks, missed)
    joint_score = sum(tracks[t, i] for t, i in enumerate(joint))
    assert joint.tolist() == [2, 0, 1]
    assert joint_score > greedy_score + 0.1


def test_missed_is_open_to_every_tag():
    tracks = np.array([[-20.0, -20.0], [-20.0, -20.0]])
    missed = np.array([0.0, 0.0])
    assert joint_assignment(tracks, missed).tolist() == [2, 2]
    assert np.allclose(exclusive_posteriors(tracks, missed)[:, 2], 1.0, atol=1e-6)


def test_exact_marginals_equal_a_brute_force_sum():
    rng = np.random.default_rng(5)
    tracks = rng.normal(0, 2, size=(3, 5))
    missed = rng.normal(-1, 1, size=3)
    assert np.allclose(exclusive_posteriors(tracks, missed), _brute_force_marginals(tracks, missed), atol=1e-12)


def test_near_certain_tags_are_summed_one_by_one_where_inclusion_exclusion_would_cancel():
    # both tags all but certain of track 0: the constraint leaves mass ~1e-12 of the unconstrained sum
    tracks = np.array([[0.0, -28.0, -40.0, -45.0], [0.0, -30.0, -41.0, -45.0]])
    missed = np.array([-60.0, -60.0])
    post = exclusive_posteriors(tracks, missed)
    assert np.allclose(post, _brute_force_marginals(tracks, missed), rtol=1e-6, atol=1e-15)
    assert post[0, 1] > 0.5 and post[1, 0] > 0.5  # one of them takes track 0, the other its second best


def test_many_tags_and_tracks_match_the_brute_force_sum():
    rng = np.random.default_rng(11)
    tracks = rng.normal(0, 3, size=(4, 6))
    missed = rng.normal(-2, 1, size=4)
    assert np.allclose(exclusive_posteriors(tracks, missed), _brute_force_marginals(tracks, missed), atol=1e-12)


def test_decided_tags_stop_steering_the_pan():
    post = np.array([[0.98, 0.01, 0.01], [0.4, 0.4, 0.2], [0.6, 0.3, 0.1]])
    h = entropy(post)
    w = pan_weights(post, decided=[True, False, False])
    assert w[0] == 0.0 and w.sum() == pytest.approx(1.0)
    assert w[1] / w[2] == pytest.approx(h[1] / h[2])
    assert pan_weights(post, decided=[True, False, False], rule="neediest").tolist() == [0.0, 1.0, 0.0]
    assert pan_weights(post, decided=[True, True, True]).tolist() == [0.0, 0.0, 0.0]


def test_an_undetected_carriers_bearing_counts_in_the_entropy_that_steers_the_pan():
    """The chain rule H(person) = H(track or none) + P(none) H(bearing | none), and what it changes:
    tag 0 is sure no detected track carries it (a walker the camera lost) but Rx(dir) leaves its
    bearing spread over 40 grid cells; tag 1 hesitates between two tracks. By "which track, or
    none" alone tag 0 weighs nothing; by "which person" it leads."""
    post = np.array([[0.0, 0.0, 1.0], [0.5, 0.5, 0.0]])
    where = np.zeros((2, 360))
    where[0, 100:140] = 1.0 / 40  # tag 0's undetected carrier: anywhere in 40 cells
    where[1, 7] = 1.0  # tag 1's "none" has no mass: its bearing cannot count
    h = which_person_entropy(post, where)
    assert h == pytest.approx([math.log(40), math.log(2)])
    joint = np.full(4, 0.25)  # the chain rule against the entropy of the joint: 2 tracks + 2 bearings
    assert which_person_entropy(np.array([[0.25, 0.25, 0.5]]), np.array([[0.5, 0.5]]))[0] == pytest.approx(entropy(joint[None])[0])
    assert which_person_entropy(post).tolist() == entropy(post).tolist()
    assert pan_weights(post, decided=[False, False]).tolist() == [0.0, 1.0]
    w = pan_weights(post, decided=[False, False], where_missed=where)
    assert w[0] > w[1] and w == pytest.approx([math.log(40), math.log(2)] / np.log(80))
    assert pan_weights(post, decided=[False, False], rule="neediest", where_missed=where).tolist() == [1.0, 0.0]


def test_bad_shapes_and_rules_are_refused():
    with pytest.raises(ValueError, match="K, M"):
        independent_posteriors(np.zeros((2, 3)), np.zeros(3))
    with pytest.raises(ValueError, match="one decided flag"):
        pan_weights(np.full((2, 2), 0.5), decided=[False])
    with pytest.raises(ValueError, match="unknown pan rule"):
        pan_weights(np.full((2, 2), 0.5), decided=[False, False], rule="loudest")


def test_tags_certain_of_one_track_whose_other_assignments_underflow_still_get_marginals():
    # both tags certain of track 0, everything else 2000 nats below: every assignment the constraint allows
    # has a weight exp(-2000) = 0.0 in doubles. Exactly: one tag on track 0, the other on track 1 or "missed".
    tracks = np.array([[0.0, -2000.0], [0.0, -2000.0]])
    missed = np.array([-2000.0, -2000.0])
    post = exclusive_posteriors(tracks, missed)
    assert np.isfinite(post).all()
    assert np.allclose(post, [[0.5, 0.25, 0.25], [0.5, 0.25, 0.25]], atol=1e-12)
    # three tags, the best allowed assignment 900 nats below the unconstrained one: the brute-force sum in logs agrees
    tracks = np.array([[0.0, -800.0, -2.0], [0.0, -900.0, -1500.0], [-3.0, 0.0, -750.0]])
    missed = np.array([-760.0, -1200.0, -5.0])
    assert np.allclose(exclusive_posteriors(tracks, missed), _brute_force_in_logs(tracks - 1000.0, missed - 1000.0), atol=1e-12)


def _brute_force_in_logs(tracks, missed):
    k, m = tracks.shape
    full = np.concatenate([tracks, missed[:, None]], axis=1)
    terms = [[[] for _ in range(m + 1)] for _ in range(k)]
    for a in itertools.product(range(m + 1), repeat=k):
        real = [x for x in a if x < m]
        if len(real) == len(set(real)):
            for t, x in enumerate(a):
                terms[t][x].append(sum(full[u, y] for u, y in enumerate(a)))
    logs = np.array([[logsumexp(c) if c else -np.inf for c in row] for row in terms])
    return np.exp(logs - logsumexp(logs, axis=1, keepdims=True))


def test_the_assignment_is_the_one_the_concatenated_cost_matrix_gave():
    """``joint_assignment`` fills its K x (M + K) matrix in place; the Hungarian algorithm gets the
    matrix (and so gives the assignment, ties included) that concatenating [tracks | own missed] made."""
    from scipy.optimize import linear_sum_assignment

    rng = np.random.default_rng(5)
    for trial in range(400):
        k, m = int(rng.integers(1, 6)), int(rng.integers(0, 12))
        tracks = np.round(rng.normal(0.0, 3.0, (k, m)), 0 if trial % 3 == 0 else 6)  # rounded: ties
        missed = np.round(rng.normal(0.0, 3.0, k), 0 if trial % 3 == 0 else 6)
        own = np.full((k, k), IMPOSSIBLE)
        np.fill_diagonal(own, missed)
        gain = np.concatenate([tracks, own], axis=1)
        rows, cols = linear_sum_assignment(gain, maximize=True)
        want = np.empty(k, dtype=np.int64)
        want[rows] = np.where(cols < m, cols, m)
        assert joint_assignment(tracks, missed).tolist() == want.tolist()
