"""The tracker's track table (``_tracker.TRACK``): one swap-remove, and the stages as kernels."""

from __future__ import annotations

import math

import numpy as np

from ra2vipas.services.controller import _tracker as tk


def _table(bearings, n_boxes=None):
    tab = np.zeros(8, dtype=tk.TRACK)
    for i, b in enumerate(bearings):
        tab[i]["bearing"] = b
        tab[i]["x"][:, 0] = b
        tab[i]["mu"] = (1.0, 0.0)
        tab[i]["n_boxes"] = 10.0 if n_boxes is None else n_boxes[i]
        tab[i]["id"] = 100 + i
    return tab


def _prm(sigma=math.radians(0.25)):
    prm = np.zeros(12)
    prm[tk.SIGMA_B], prm[tk.MAX_SD], prm[tk.COUNT_LIMIT] = sigma, math.radians(60.0), 0.3
    return prm


def test_swap_remove_moves_the_last_track_with_its_together_counts():
    tab = _table([0.1, 0.2, 0.3])
    together = np.arange(64, dtype=float).reshape(8, 8)
    n = tk.swap_remove(tab, together, 0, 3)
    assert n == 2 and tab[0]["id"] == 102 and tab[0]["bearing"] == 0.3 and tab[1]["id"] == 101
    assert together[0, 1] == 17.0 and together[1, 0] == 10.0 and together[0, 0] == 0.0  # row 2 / column 2 before
    n = tk.swap_remove(tab, together, 1, n)  # the last one: nothing moves
    assert n == 1 and tab[0]["id"] == 102


def test_two_halves_of_one_target_merge_and_two_targets_do_not():
    sigma = math.radians(0.25)
    close = 2.0 * sigma  # within 4 box sigmas
    tab = _table([0.0, close, 1.0], n_boxes=[5.0, 20.0, 20.0])
    together = np.zeros((8, 8))
    n = tk.merge_and_delete(tab, together, 3, np.full(3, 1e9), True, _prm(sigma), sigma * sigma, 10)
    assert n == 2 and sorted(tab[:n]["id"].tolist()) == [101, 102] and tab[:n]["n_boxes"].max() == 25.0
    tab = _table([0.0, close, 1.0], n_boxes=[5.0, 20.0, 20.0])
    together[0, 1] = together[1, 0] = 5.0  # seen in the same frames: two targets side by side
    n = tk.merge_and_delete(tab, together, 3, np.full(3, 1e9), True, _prm(sigma), sigma * sigma, 10)
    assert n == 3


def test_a_clean_detector_confirms_at_once_and_clutter_asks_for_evidence():
    tab = _table([0.0, 1.0])
    tab[0]["k"], tab[0]["n_frames"], tab[0]["det_steps"] = 20.0, 20.0, 3.0  # seen every frame
    tab[1]["k"], tab[1]["n_frames"], tab[1]["det_steps"] = 1.0, 20.0, 1.0  # once in 20 frames
    _, clean = tk.confirm(tab, 2, 0.0, 16.0, math.radians(0.25))
    assert clean and tab[0]["confirmed"] and tab[1]["confirmed"]
    tab = _table([0.0, 1.0])
    tab[0]["k"], tab[0]["n_frames"], tab[0]["det_steps"] = 20.0, 20.0, 3.0
    tab[1]["k"], tab[1]["n_frames"], tab[1]["det_steps"] = 1.0, 20.0, 1.0
    evidence, clean = tk.confirm(tab, 2, 5.0, 16.0, math.radians(0.25))  # 5 false boxes per frame per rad
    assert not clean and tab[0]["confirmed"] and not tab[1]["confirmed"] and evidence[0] >= tk.CONFIRM_NATS


def test_boxes_of_one_frame_are_never_one_cluster():
    sigma2 = math.radians(0.25) ** 2
    boxes = np.array([0.0, 0.001, 0.0002, 0.5])  # frame 0: two boxes 0.001 apart; frame 1: one near the first, one far
    mean, count, frames = tk.cluster_boxes(boxes, np.array([2, 2]), sigma2)
    assert mean.size == 3 and count.tolist() == [2.0, 1.0, 1.0] and frames[:, 0].tolist() == [True, True, False]
