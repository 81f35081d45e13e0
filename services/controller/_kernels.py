"""Compiled inner loops of the controller (numba, cached on disk after the first run).

numba turns these plain loops into machine code: the tracker's per-frame assignment is a
handful of boxes against a few dozen tracks, where numpy's per-call overhead would dominate
the control step.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2.0 * math.pi


@njit(cache=True, inline="always")
def _wrap(x: float) -> float:
    return (x + math.pi) % TWO_PI - math.pi


@njit(cache=True)
def tracker_step(pan, boxes_rel, counts, bearing, nboxes, detections, frames_in_view, together, n,
                 pans, frames_per_pan, gate, merge_distance, count_limit):
    """One step of ``DetectionTracker``: returns the new number of tracks.

    ``boxes_rel`` are all box bearings of the step (relative to the optical axis), frame by
    frame; ``counts[f]`` is the number of boxes of frame f. Arrays of tracks are updated in
    place; ``pans``/``frames_per_pan`` hold the pan history including this step.
    """
    capacity = bearing.size
    nu = counts.size
    # frames in view this step, for the tracks that exist now
    for i in range(n):
        if abs(_wrap(bearing[i] - pan)) <= count_limit:
            frames_in_view[i] += nu
    used = np.zeros(capacity, dtype=np.bool_)
    start = 0
    for f in range(nu):
        c = counts[f]
        if c == 0:
            continue
        b = np.empty(c)
        for j in range(c):
            b[j] = _wrap(pan + boxes_rel[start + j])
        start += c
        # greedy one-to-one: nearest (box, track) pairs within the gate first
        taken = np.zeros(c, dtype=np.bool_)
        used[:n] = False
        frame_tracks = np.empty(c, dtype=np.int64)
        m = 0
        while True:
            best = gate
            bi = -1
            ti = -1
            for j in range(c):
                if taken[j]:
                    continue
                for i in range(n):
                    if used[i]:
                        continue
                    d = abs(_wrap(b[j] - bearing[i]))
                    if d < best:
                        best = d
                        bi = j
                        ti = i
            if bi < 0:
                break
            taken[bi] = True
            used[ti] = True
            nboxes[ti] += 1.0
            bearing[ti] = _wrap(bearing[ti] + _wrap(b[bi] - bearing[ti]) / nboxes[ti])
            if abs(_wrap(bearing[ti] - pan)) <= count_limit:
                detections[ti] += 1.0
            frame_tracks[m] = ti
            m += 1
        # boxes left over open new tracks
        for j in range(c):
            if taken[j] or n >= capacity:
                continue
            bearing[n] = b[j]
            nboxes[n] = 1.0
            detections[n] = 1.0 if abs(_wrap(b[j] - pan)) <= count_limit else 0.0
            seen = 0.0
            for p in range(pans.size):
                if abs(_wrap(b[j] - pans[p])) <= count_limit:
                    seen += frames_per_pan[p]
            frames_in_view[n] = seen
            for i in range(n + 1):
                together[n, i] = 0.0
                together[i, n] = 0.0
            used[n] = True
            frame_tracks[m] = n
            m += 1
            n += 1
        for x in range(m):
            for y in range(m):
                if x != y:
                    together[frame_tracks[x], frame_tracks[y]] += 1.0
    # merge tracks that are close and (almost) never seen in the same frame
    while n > 1:
        best = merge_distance
        bi = -1
        bj = -1
        for i in range(n):
            for j in range(i + 1, n):
                d = abs(_wrap(bearing[i] - bearing[j]))
                if d < best and together[i, j] <= 0.05 * min(nboxes[i], nboxes[j]):
                    best = d
                    bi = i
                    bj = j
        if bi < 0:
            break
        total = nboxes[bi] + nboxes[bj]
        bearing[bi] = _wrap(bearing[bi] + _wrap(bearing[bj] - bearing[bi]) * nboxes[bj] / total)
        nboxes[bi] = total
        detections[bi] += detections[bj]
        frames_in_view[bi] = max(frames_in_view[bi], frames_in_view[bj])
        for k in range(n):
            together[bi, k] += together[bj, k]
            together[k, bi] += together[k, bj]
        together[bi, bi] = 0.0
        # remove bj by moving the last track into its place
        last = n - 1
        if bj != last:
            bearing[bj] = bearing[last]
            nboxes[bj] = nboxes[last]
            detections[bj] = detections[last]
            frames_in_view[bj] = frames_in_view[last]
            for k in range(n):
                together[bj, k] = together[last, k]
                together[k, bj] = together[k, last]
            together[bj, bj] = 0.0
        n -= 1
    return n


@njit(cache=True)
def lobe_profile(hh, ho, hu, oo, ou, uu, sign, loglik, amplitude, offset):
    """Generalised least squares of (A, c) for every lobe centre (see ``LobeGP.lobe_fit``),
    written into ``loglik``, ``amplitude`` and ``offset``; returns the index of the best centre."""
    oo_safe = max(oo, 1e-12)
    q_flat = uu - ou * ou / oo_safe
    c_flat = ou / oo_safe
    best = 0
    best_ll = -1e300
    for j in range(hh.size):
        det = max(hh[j] * oo - ho[j] * ho[j], 1e-12)
        A = (oo * hu[j] - ho[j] * ou) / det
        if A * sign <= 0.0:
            loglik[j] = -0.5 * q_flat
            amplitude[j] = 0.0
            offset[j] = c_flat
        else:
            c = (hh[j] * ou - ho[j] * hu[j]) / det
            loglik[j] = -0.5 * (uu - (A * hu[j] + c * ou))
            amplitude[j] = A
            offset[j] = c
        if loglik[j] > best_ll:
            best_ll = loglik[j]
            best = j
    return best
