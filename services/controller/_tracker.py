"""Compiled step of the bearing-only multi-target tracker (``ra2vipas.services.controller.tracks``).

Per track, an interacting-multiple-model (IMM) filter over the state x = (gamma, omega) —
bearing and angular velocity — with two models: *standing* (omega = 0, a tiny bearing random
walk) and *walking* (nearly constant angular velocity, white angular acceleration of spectral
density q). Blom & Bar-Shalom (1988); Bar-Shalom, Li & Kirubarajan, *Estimation with
Applications to Tracking and Navigation* (2001), Sec. 11.6. A standing target keeps a tight
bearing while the camera looks elsewhere; a walker's bearing is predicted forward.

The tracks live in one table, a numpy structured array of ``TRACK`` records (the first n rows
are the live tracks), plus the pairwise ``together`` counts; ``swap_remove`` is the one way a
track leaves it. ``tracker_step`` runs the stages, each its own kernel:

1. ``predict``: IMM mixing and prediction of every track;
2. ``cluster_boxes`` and ``associate``: the step's boxes clustered across its frames (the nu
   frames of a step see the same positions; two boxes of one frame are two targets), and the
   clusters assigned to tracks by global nearest neighbour on the tracks' predicted densities,
   against the density of something new;
3. ``update``: one Kalman update per model with the cluster's mean (probabilistic data
   association), then ``count_together`` (tracks seen in the same frame are two targets) and
   ``count_clutter`` (the detector's false boxes);
4. ``count_detections``: the detection counts for the POD (discounted for walkers);
5. ``give_birth``: new tracks from the clusters no track took;
6. ``confirm``: tentative tracks whose detections stand out from clutter;
7. ``merge_and_delete``: one target split in two is merged; false boxes, tracks no better than
   clutter and lost walkers are deleted.

All arrays are updated in place; ``tracker_step`` returns the new number of tracks.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2.0 * math.pi

TRACK = np.dtype([
    ("x", np.float64, (2, 2)),  # per model (standing, walking): bearing and angular velocity
    ("P", np.float64, (2, 2, 2)),  # per model: the covariance of x
    ("mu", np.float64, (2,)),  # the models' probabilities
    ("bearing", np.float64),  # the combined bearing (moment matching of the two models) ...
    ("var", np.float64),  # ... and its variance
    ("k", np.float64),  # detections in frames well inside the FoV (discounted for a walker)
    ("n_frames", np.float64),  # frames in which it was well inside the FoV (discounted likewise)
    ("n_boxes", np.float64),  # boxes it took (each weighted by the probability that it was real)
    ("det_steps", np.float64),  # steps in which it was detected (weighted likewise)
    ("misses", np.float64),  # frames in view since its last detection
    ("confirmed", np.bool_),  # a target (its detections stand out from clutter), not a tentative track
    ("id", np.int64),  # stable while the track lives, never reused
])
"""One row of the track table."""

# indices into the parameter vector ``prm``
DT, SIGMA_B, Q_STAND, Q_WALK, P_SWITCH, GATE2, COUNT_LIMIT, OCCLUSION, TAU_WALK, OMEGA0, MAX_SD, F_WALK = range(12)

# -- named thresholds (box sigma: SIGMA_B; nu: frames per step) ---------------------------------------
NEW_TARGETS_PER_RAD = 1.0
"""Density of targets not seen yet where the camera has not looked (fading as it looks there)."""
NEW_TARGET_FADE_STEPS = 2.0
"""The density of new targets at a bearing fades as exp(-frames there / (this many steps of nu frames))."""
CLUSTER_GATE_SIGMAS2 = 9.0
"""A box joins a cluster within 3 box sigmas (squared) of its mean ..."""
CLUSTER_GATE_MAX = 2.0
"""... widened by (1 + 1 / boxes) for the mean's own uncertainty: at most twice that (a lone box)."""
MIN_CLUTTER_FRAMES = 20.0
"""Explored frames before the clutter density measured is used (fewer: none assumed)."""
LONE_BOX = 1.5
"""A cluster of fewer boxes is a lone box: it may be a false one (more boxes at one spot hardly are)."""
EXPLORED_STEPS = 3.0
"""A bearing looked at for this many steps of nu frames is explored: the camera knows its targets,
so a box there that no confirmed track explains counts as clutter."""
MAX_GATE_CLUTTER = 0.5
"""The most probability of a clutter box in a track's gate that confirmation assumes."""
CLEAN_GATE_CLUTTER = 0.005
"""Below this probability of a clutter box in a gate the detector is clean: tracks confirm at once."""
CONFIRM_STEPS = 2.0
"""Steps with a detection a track needs before it can be confirmed (with clutter) ..."""
CONFIRM_NATS = 4.0
"""... and the log-likelihood ratio of its detections against clutter alone."""
FALSE_BOX_STEPS = 2.0
"""A tentative track looked at again for this many steps of nu frames and not seen is a false box."""
CLUTTER_CHECK_STEPS = 20.0
"""After this many steps of nu frames in view, a track no better than clutter is deleted."""
MERGE_SIGMAS2 = 16.0
"""Two tracks within 4 box sigmas (squared) ..."""
MERGE_TOGETHER = 0.05
"""... detected in the same frame at most this share of their boxes are one target split in two."""
LOST_WALKER = 0.5
"""A track whose walking probability exceeds this and whose bearing sd exceeds MAX_SD is lost."""
NEGLIGIBLE_DENSITY = 1e-12
"""Floor of the density of something new (a log is taken)."""


@njit(cache=True, inline="always")
def _wrap(x: float) -> float:
    # (x + pi) % 2 pi - pi, with the common case taken without the modulo (fmod is ~20 ns): for y = x + pi
    # in [0, 2 pi) Python's float modulo (numba's the same) returns y itself (-0.0 gives +0.0, and
    # either minus pi is -pi), so the result is the same double
    y = x + math.pi
    if y >= 0.0 and y < TWO_PI:
        return y - math.pi
    return y % TWO_PI - math.pi


@njit(cache=True, inline="always")
def _combine(tr, w):
    """The combined bearing and its variance of track ``tr`` (moment matching of the two models
    weighted by ``w``)."""
    ref = tr.x[0, 0]
    total = w[0] + w[1]
    d1 = _wrap(tr.x[1, 0] - ref)
    g = (w[1] * d1) / total
    tr.bearing = _wrap(ref + g)
    tr.var = (w[0] * (tr.P[0, 0, 0] + g * g) + w[1] * (tr.P[1, 0, 0] + (d1 - g) * (d1 - g))) / total


@njit(cache=True, inline="always")
def _predict_one(tr, prm, c):
    """IMM mixing and prediction of one track (a ``TRACK`` record); writes its combined predicted
    bearing and variance, and the predicted model probabilities into ``c``."""
    x, P, mu = tr.x, tr.P, tr.mu
    dt = prm[DT]
    # mixing probabilities mu_{a|b} = Pi_ab mu_a / c_b with Pi = [[1-p01, p01], [p10, 1-p10]],
    # whose stationary law is the share of walkers seen so far (F_WALK): a track the camera
    # has not seen for long drifts towards what targets here usually do, not towards 50/50
    p01 = prm[P_SWITCH] * prm[F_WALK]
    p10 = prm[P_SWITCH] * (1.0 - prm[F_WALK])
    c[0] = (1.0 - p01) * mu[0] + p10 * mu[1]
    c[1] = p01 * mu[0] + (1.0 - p10) * mu[1]
    g_ref = x[0, 0]
    mx = np.zeros((2, 2))
    mP = np.zeros((2, 2, 2))
    for b in range(2):
        cb = max(c[b], 1e-300)
        w0 = ((1.0 - p01) if b == 0 else p01) * mu[0] / cb
        w1 = (p10 if b == 0 else (1.0 - p10)) * mu[1] / cb
        d0 = _wrap(x[0, 0] - g_ref)
        d1 = _wrap(x[1, 0] - g_ref)
        g = w0 * d0 + w1 * d1
        om = w0 * x[0, 1] + w1 * x[1, 1]
        mx[b, 0] = g
        mx[b, 1] = om
        for a in range(2):
            w = w0 if a == 0 else w1
            dg = (d0 if a == 0 else d1) - g
            do = x[a, 1] - om
            mP[b, 0, 0] += w * (P[a, 0, 0] + dg * dg)
            mP[b, 0, 1] += w * (P[a, 0, 1] + dg * do)
            mP[b, 1, 0] += w * (P[a, 1, 0] + do * dg)
            mP[b, 1, 1] += w * (P[a, 1, 1] + do * do)
    # model 0, standing: gamma' = gamma, omega' = 0
    x[0, 0] = _wrap(g_ref + mx[0, 0])
    x[0, 1] = 0.0
    P[0, 0, 0] = mP[0, 0, 0] + prm[Q_STAND] * dt
    P[0, 0, 1] = 0.0
    P[0, 1, 0] = 0.0
    P[0, 1, 1] = 0.0
    # model 1, walking: constant angular velocity, white angular acceleration
    q = prm[Q_WALK]
    p00, p01, p11 = mP[1, 0, 0], mP[1, 0, 1], mP[1, 1, 1]
    x[1, 0] = _wrap(g_ref + mx[1, 0] + mx[1, 1] * dt)
    x[1, 1] = mx[1, 1]
    P[1, 0, 0] = p00 + 2.0 * dt * p01 + dt * dt * p11 + q * dt * dt * dt / 3.0
    P[1, 0, 1] = p01 + dt * p11 + q * dt * dt / 2.0
    P[1, 1, 0] = P[1, 0, 1]
    P[1, 1, 1] = p11 + q * dt
    _combine(tr, c)


@njit(cache=True)
def swap_remove(tab, together, i, n):
    """Remove track i of the first n: the last one takes its row (and its row and column of
    ``together``). Returns the new number of tracks."""
    last = n - 1
    if i != last:
        tab[i] = tab[last]
        for q in range(n):
            together[i, q] = together[last, q]
            together[q, i] = together[q, last]
        together[i, i] = 0.0
    return last


# -- the stages ---------------------------------------------------------------------------------------
@njit(cache=True)
def predict(tab, n, prm, pred_c):
    """1. IMM prediction of the first n tracks; ``pred_c[i]``: track i's predicted model
    probabilities."""
    c = np.zeros(2)
    for i in range(n):
        _predict_one(tab[i], prm, c)
        pred_c[i, 0] = c[0]
        pred_c[i, 1] = c[1]


@njit(cache=True)
def cluster_boxes(boxes_abs, counts, sigma2):
    """2a. Cluster the step's boxes across its frames (the nu frames of a step see the same
    positions): frame by frame, each box joins the nearest cluster within 3 box sigmas that has
    no box of this frame yet (nearest pairs first), else opens a new cluster. Two boxes of one
    frame are never one cluster. Returns (mean bearing, box count, frame mask) per cluster."""
    total = boxes_abs.size
    nu = counts.size
    ref = np.empty(max(total, 1))
    off = np.zeros(max(total, 1))
    cnt = np.zeros(max(total, 1))
    frames = np.zeros((max(total, 1), nu), dtype=np.bool_)
    n_cl = 0
    gap2 = CLUSTER_GATE_SIGMAS2 * sigma2
    start = 0
    for f in range(nu):
        c = counts[f]
        if c == 0:
            continue
        done = np.zeros(c, dtype=np.bool_)
        busy = np.zeros(n_cl, dtype=np.bool_)
        n_old = n_cl
        while True:
            best = CLUSTER_GATE_MAX * gap2
            bj = -1
            bc = -1
            for j in range(c):
                if done[j]:
                    continue
                for q in range(n_old):
                    if busy[q]:
                        continue
                    d = _wrap(boxes_abs[start + j] - _wrap(ref[q] + off[q] / cnt[q]))
                    if d * d < gap2 * (1.0 + 1.0 / cnt[q]) and d * d < best:
                        best = d * d
                        bj = j
                        bc = q
            if bj < 0:
                break
            done[bj] = True
            busy[bc] = True
            off[bc] += _wrap(boxes_abs[start + bj] - ref[bc])
            cnt[bc] += 1.0
            frames[bc, f] = True
        for j in range(c):
            if not done[j]:
                ref[n_cl] = boxes_abs[start + j]
                off[n_cl] = 0.0
                cnt[n_cl] = 1.0
                frames[n_cl, f] = True
                n_cl += 1
        start += c
    mean = np.empty(n_cl)
    for q in range(n_cl):
        mean[q] = _wrap(ref[q] + off[q] / cnt[q])
    return mean, cnt[:n_cl], frames[:n_cl]


@njit(cache=True)
def clutter_density(clutter, count_limit):
    """False boxes per frame per radian of the FoV measured so far (0 until MIN_CLUTTER_FRAMES)."""
    if clutter[1] >= MIN_CLUTTER_FRAMES:
        return clutter[0] / max(clutter[1], 1e-9) / (2.0 * max(count_limit, 1e-3))
    return 0.0


@njit(cache=True)
def new_target_logdensity(cmean, view_grid, density_clutter, nu):
    """2b. log density of "something new" at each cluster: clutter, plus, where the camera has
    hardly looked yet, a target not seen before (about one per radian, fading as the bearing
    gets looked at)."""
    G = view_grid.size
    log_new = np.empty(cmean.size)
    for q in range(cmean.size):
        cell = int(((cmean[q] + math.pi) / TWO_PI) * G) % G
        unseen = math.exp(-view_grid[cell] / (NEW_TARGET_FADE_STEPS * nu))
        log_new[q] = math.log(max(density_clutter + NEW_TARGETS_PER_RAD * unseen, NEGLIGIBLE_DENSITY))
    return log_new


@njit(cache=True)
def associate(tab, n, cmean, ccnt, log_new, pred_c, sigma2, gate2):
    """2c. One cluster per track, best first: a cluster joins a track (within its gate) where the
    track's predicted density of the cluster's mean beats that of something new. Returns each
    cluster's track (-1: none)."""
    n_cl = cmean.size
    owner = np.full(n_cl, -1, dtype=np.int64)
    used = np.zeros(n, dtype=np.bool_)
    bearing, var, mean, P00 = np.empty(n), np.empty(n), np.empty((n, 2)), np.empty((n, 2))  # the table's columns read below
    for i in range(n):
        tr = tab[i]
        bearing[i], var[i] = tr.bearing, tr.var
        for a in range(2):
            mean[i, a], P00[i, a] = tr.x[a, 0], tr.P[a, 0, 0]
    while True:
        best = 0.0
        bq = -1
        ti = -1
        for q in range(n_cl):
            if owner[q] >= 0:
                continue
            R = sigma2 / ccnt[q]
            for i in range(n):
                if used[i]:
                    continue
                d = _wrap(cmean[q] - bearing[i])
                if d * d > gate2 * (var[i] + R):
                    continue
                dens = 0.0
                for a in range(2):
                    S = P00[i, a] + R
                    da = _wrap(cmean[q] - mean[i, a])
                    dens += pred_c[i, a] * math.exp(-0.5 * da * da / S) / math.sqrt(TWO_PI * S)
                score = math.log(max(dens, 1e-300)) - log_new[q]
                if score > best:
                    best = score
                    bq = q
                    ti = i
        if bq < 0:
            break
        owner[bq] = ti
        used[ti] = True
    return owner


@njit(cache=True)
def frames_hit(owner, cframes, capacity):
    """Per track, the frames of this step in which its cluster had a box: their number and mask."""
    nu = cframes.shape[1]
    hits = np.zeros(capacity)
    hit_in = np.zeros((capacity, nu), dtype=np.bool_)
    for q in range(owner.size):
        i = owner[q]
        if i >= 0:
            for fr in range(nu):
                if cframes[q, fr]:
                    hit_in[i, fr] = True
                    hits[i] += 1.0
    return hits, hit_in


@njit(cache=True)
def update(tab, n, owner, cmean, ccnt, pred_c, sigma2, density_clutter):
    """3. IMM update of each track with the mean of its cluster, by probabilistic data
    association (Bar-Shalom & Tse 1975): a lone box may be a false one (clutter density lam per
    rad); more boxes at one spot in one step hardly are. Returns, per track, the probability that
    its cluster was real and whether it had one."""
    capacity = tab.size
    n_cl = cmean.size
    lik = np.zeros(2)
    c = np.zeros(2)
    real = np.zeros(capacity)
    measured = np.zeros(capacity, dtype=np.bool_)
    for q in range(n_cl):
        if owner[q] >= 0:
            measured[owner[q]] = True
    for i in range(n):
        tr = tab[i]
        x, P, mu = tr.x, tr.P, tr.mu
        q = -1
        if measured[i]:
            for qq in range(n_cl):
                if owner[qq] == i:
                    q = qq
                    break
        if q >= 0:
            z = cmean[q]
            R = sigma2 / ccnt[q]
            lam = density_clutter if ccnt[q] < LONE_BOX else 0.0
            dens = 0.0
            for a in range(2):
                S = P[a, 0, 0] + R
                v = _wrap(z - x[a, 0])
                lik[a] = math.exp(-0.5 * v * v / S) / math.sqrt(TWO_PI * S)
                dens += pred_c[i, a] * lik[a]
            w = dens / (dens + lam) if dens + lam > 0.0 else 0.0  # P(the cluster is this target's)
            real[i] = w
            for a in range(2):
                v = _wrap(z - x[a, 0])
                S = P[a, 0, 0] + R
                K0 = P[a, 0, 0] / S
                K1 = P[a, 1, 0] / S
                x[a, 0] = _wrap(x[a, 0] + w * K0 * v)
                x[a, 1] += w * K1 * v
                p00, p01, p10, p11 = P[a, 0, 0], P[a, 0, 1], P[a, 1, 0], P[a, 1, 1]
                # PDA covariance: the updated one if real, the predicted one if not, plus the spread
                spread = w * (1.0 - w) * v * v
                P[a, 0, 0] = p00 - w * K0 * p00 + spread * K0 * K0
                P[a, 0, 1] = p01 - w * K0 * p01 + spread * K0 * K1
                P[a, 1, 0] = p10 - w * K1 * p00 + spread * K1 * K0
                P[a, 1, 1] = p11 - w * K1 * p01 + spread * K1 * K1
            s0 = pred_c[i, 0] * (lik[0] + lam)
            s1 = pred_c[i, 1] * (lik[1] + lam)
            tot = s0 + s1
            if tot > 1e-300:
                mu[0] = s0 / tot
                mu[1] = s1 / tot
            else:
                mu[0] = pred_c[i, 0]
                mu[1] = pred_c[i, 1]
            tr.n_boxes += w * ccnt[q]
            tr.det_steps += w
        else:
            mu[0] = pred_c[i, 0]
            mu[1] = pred_c[i, 1]
        c[0] = mu[0]
        c[1] = mu[1]
        _combine(tr, c)
    return real, measured


@njit(cache=True)
def count_together(together, measured, hit_in, n):
    """3b. Tracks detected in the same frame are two targets: count such frames per pair."""
    nu = hit_in.shape[1]
    for i in range(n):
        if not measured[i]:
            continue
        for j in range(n):
            if j != i and measured[j]:
                both = 0.0
                for fr in range(nu):
                    if hit_in[i, fr] and hit_in[j, fr]:
                        both += 1.0
                together[i, j] += both


@njit(cache=True)
def count_clutter(tab, owner, cmean, ccnt, view_grid, pan, count_limit, nu, clutter):
    """3c. Clutter: boxes that no confirmed track explains, where the camera has looked long
    enough to know the targets (a clean detector hardly does that; a cluttered one keeps doing
    it), per frame and per radian of well-explored field of view: ``clutter`` = [boxes, frames
    (times the explored share of the field of view)]."""
    G = view_grid.size
    explored_cells = 0
    fov_cells = 0
    for cell in range(G):
        b_cell = -math.pi + TWO_PI * (cell + 0.5) / G
        if abs(_wrap(b_cell - pan)) <= count_limit:
            fov_cells += 1
            if view_grid[cell] >= EXPLORED_STEPS * nu:
                explored_cells += 1
    for q in range(cmean.size):
        if owner[q] < 0 or not tab[owner[q]].confirmed:
            cell = int(((cmean[q] + math.pi) / TWO_PI) * G) % G
            if view_grid[cell] >= EXPLORED_STEPS * nu:
                clutter[0] += ccnt[q]
    clutter[1] += nu * explored_cells / max(fov_cells, 1)


@njit(cache=True)
def count_detections(tab, n, pan, prm, real, hits, nu):
    """4. Detection counts (a walker's are discounted: its POD changes with its range); a step in
    which a track may be hidden behind another one counts only if it was detected."""
    bearing, confirmed = tab["bearing"], tab["confirmed"]
    for i in range(n):
        tr = tab[i]
        keep = tr.mu[0] + tr.mu[1] * math.exp(-prm[DT] / prm[TAU_WALK])
        tr.k *= keep
        tr.n_frames *= keep
        if abs(_wrap(bearing[i] - pan)) > prm[COUNT_LIMIT]:
            continue
        hidden = False
        for j in range(n):
            if j != i and confirmed[j] and abs(_wrap(bearing[j] - bearing[i])) < prm[OCCLUSION]:
                hidden = True
                break
        if hidden and hits[i] == 0.0:  # a miss while another target stands in front may be occlusion
            continue
        tr.k += real[i] * hits[i]
        tr.n_frames += nu
        tr.misses = 0.0 if hits[i] > 0.0 else tr.misses + nu


@njit(cache=True)
def give_birth(tab, together, n, owner, cmean, ccnt, cframes, hit_in, pans, frames_per_pan, pan, prm, sigma2, next_id):
    """5. Births: a tentative track from each cluster no track took (while the table has room).
    Its past frames in view are counted from the pan history (``pans``/``frames_per_pan``, this
    step included), so its detection rate is not biased by its birth. Returns the new n."""
    capacity = tab.size
    nu = cframes.shape[1]
    for q in range(cmean.size):
        if owner[q] >= 0 or n >= capacity:
            continue
        cnt_boxes = ccnt[q]
        g = cmean[q]
        distinct = 0
        for fr in range(nu):
            if cframes[q, fr]:
                distinct += 1
                hit_in[n, fr] = True
        tr = tab[n]
        for a in range(2):
            tr.x[a, 0] = g
            tr.x[a, 1] = 0.0
            tr.P[a, 0, 0] = sigma2 / cnt_boxes
            tr.P[a, 0, 1] = 0.0
            tr.P[a, 1, 0] = 0.0
            tr.P[a, 1, 1] = 0.0 if a == 0 else prm[OMEGA0] * prm[OMEGA0]
        tr.mu[0] = 1.0 - prm[F_WALK]
        tr.mu[1] = prm[F_WALK]
        tr.bearing = g
        tr.var = sigma2 / cnt_boxes
        tr.n_boxes = cnt_boxes
        tr.det_steps = 1.0
        tr.confirmed = False
        tr.misses = 0.0
        tr.id = next_id[0]
        next_id[0] += 1
        inview = abs(_wrap(g - pan)) <= prm[COUNT_LIMIT]
        tr.k = distinct if inview else 0.0
        seen_frames = 0.0
        for p in range(pans.size - 1):  # frames in view before this step (as if it had stood there)
            if abs(_wrap(g - pans[p])) <= prm[COUNT_LIMIT]:
                seen_frames += frames_per_pan[p]
        tr.n_frames = seen_frames + (nu if inview else 0.0)
        for j in range(n):  # frames of this step in which the new track and another one were both seen
            both = 0.0
            for fr in range(nu):
                if hit_in[n, fr] and hit_in[j, fr]:
                    both += 1.0
            together[n, j] = both
            together[j, n] = both
        together[n, n] = 0.0
        n += 1
    return n


@njit(cache=True)
def confirm(tab, n, density_clutter, gate2, sigma_b):
    """6. Confirmation: a track is a target once its detections stand out from what clutter alone
    would put in its gate (a log-likelihood ratio of its detection counts, k frames with a box out
    of n, against the clutter rate q there); while the detector has not been caught inventing
    boxes, at once. Returns each track's log-likelihood ratio and whether the detector is clean."""
    q_gate = min(density_clutter * 2.0 * math.sqrt(gate2) * sigma_b, MAX_GATE_CLUTTER)  # 2 sqrt(gate2) sigma: the gate's width
    clean = q_gate < CLEAN_GATE_CLUTTER
    evidence = np.zeros(n)
    for i in range(n):
        tr = tab[i]
        kk = min(max(tr.k, 0.0), tr.n_frames)
        if q_gate > 0.0 and tr.n_frames > 0.0:
            p_hat = max(kk / tr.n_frames, q_gate)
            evidence[i] = kk * math.log(p_hat / q_gate)
            if tr.n_frames > kk:
                evidence[i] += (tr.n_frames - kk) * math.log(max(1.0 - p_hat, 1e-12) / (1.0 - q_gate))
        else:
            evidence[i] = 1e9
        if not tr.confirmed and (clean or (tr.det_steps >= CONFIRM_STEPS and evidence[i] >= CONFIRM_NATS)):
            tr.confirmed = True
    return evidence, clean


@njit(cache=True, inline="always")
def _merge_into(tab, together, i, j, n):
    """Fold track i into track j (weighted by their boxes)."""
    a_, b_ = tab[i], tab[j]
    tot_b = a_.n_boxes + b_.n_boxes
    bearing_j = _wrap(b_.bearing + _wrap(a_.bearing - b_.bearing) * a_.n_boxes / tot_b)
    for a in range(2):
        b_.x[a, 0] = _wrap(b_.x[a, 0] + _wrap(bearing_j - b_.bearing))
    b_.bearing = bearing_j
    b_.n_boxes = tot_b
    b_.k += a_.k
    b_.n_frames = max(a_.n_frames, b_.n_frames)
    b_.det_steps = max(a_.det_steps, b_.det_steps)
    b_.confirmed = b_.confirmed or a_.confirmed
    for q in range(n):
        together[j, q] += together[i, q]
        together[q, j] += together[q, i]
    together[j, j] = 0.0


@njit(cache=True)
def merge_and_delete(tab, together, n, evidence, clean, prm, sigma2, nu):
    """7. Merges (one target split in two: close, (almost) never seen in the same frame) and
    deletions: a tentative track looked at again for two steps and not seen (a false box), a
    track whose detections, after many frames, are no more than clutter would give, a walker
    whose bearing is lost. Returns the new n.

    ``evidence`` (``confirm``'s) stays in place when a row moves: the track that takes a deleted
    one's row is judged on the deleted one's evidence this step, as the tracker always did."""
    bearing, n_boxes = tab["bearing"], tab["n_boxes"]
    i = 0
    while i < n:
        tr = tab[i]
        false_box = not tr.confirmed and tr.misses >= FALSE_BOX_STEPS * nu
        only_clutter = not clean and tr.n_frames >= CLUTTER_CHECK_STEPS * nu and evidence[i] < 0.0
        drop = false_box or only_clutter or (math.sqrt(tr.var) > prm[MAX_SD] and tr.mu[1] > LOST_WALKER)
        if not drop:
            for j in range(n):
                # same target: within 4 box sigmas, and (almost) never detected in the same frame
                dij = _wrap(bearing[j] - bearing[i])
                if j != i and n_boxes[j] >= n_boxes[i] and dij * dij < MERGE_SIGMAS2 * sigma2 \
                        and together[i, j] <= MERGE_TOGETHER * min(n_boxes[i], n_boxes[j]):
                    _merge_into(tab, together, i, j, n)
                    drop = True
                    break
        if drop:
            n = swap_remove(tab, together, i, n)
            continue
        i += 1
    return n


@njit(cache=True)
def tracker_step(pan, boxes_rel, counts, n, prm, tab, together, pans, frames_per_pan, clutter, view_grid, next_id):
    """One step of the tracker (the stages above, in order); returns the new number of tracks.

    ``boxes_rel``: all box bearings of the step relative to the optical axis, frame by frame,
    ``counts[f]`` boxes in frame f. ``tab``: the track table (``TRACK`` records, the first n
    live), ``together[i, j]``: frames in which tracks i and j were both detected. ``clutter`` =
    [boxes that would start a new track where the camera already knows the targets, frames
    (times the explored share of the field of view)]: their ratio over the FoV width estimates
    the detector's clutter density. ``view_grid``: frames the camera had taken of each bearing
    before this step, on a uniform grid over [-pi, pi) (where the camera has not looked, new
    targets are expected). ``pans``/``frames_per_pan``: the pan history including this step.
    ``next_id[0]``: the next track id to give out.
    """
    nu = counts.size
    sigma2 = prm[SIGMA_B] * prm[SIGMA_B]
    gate2 = prm[GATE2]
    pred_c = np.zeros((tab.size, 2))
    predict(tab, n, prm, pred_c)
    boxes_abs = np.empty(boxes_rel.size)
    for j in range(boxes_rel.size):
        boxes_abs[j] = _wrap(pan + boxes_rel[j])
    cmean, ccnt, cframes = cluster_boxes(boxes_abs, counts, sigma2)
    density_clutter = clutter_density(clutter, prm[COUNT_LIMIT])
    log_new = new_target_logdensity(cmean, view_grid, density_clutter, nu)
    owner = associate(tab, n, cmean, ccnt, log_new, pred_c, sigma2, gate2)
    hits, hit_in = frames_hit(owner, cframes, tab.size)
    real, measured = update(tab, n, owner, cmean, ccnt, pred_c, sigma2, density_clutter)
    count_together(together, measured, hit_in, n)
    count_clutter(tab, owner, cmean, ccnt, view_grid, pan, prm[COUNT_LIMIT], nu, clutter)
    count_detections(tab, n, pan, prm, real, hits, nu)
    n = give_birth(tab, together, n, owner, cmean, ccnt, cframes, hit_in, pans, frames_per_pan, pan, prm, sigma2, next_id)
    evidence, clean = confirm(tab, n, density_clutter, gate2, prm[SIGMA_B])
    return merge_and_delete(tab, together, n, evidence, clean, prm, sigma2, nu)


@njit(cache=True)
def components(tab, view, means, sds, weights):
    """The tracks ``view``'s IMM components into ``means`` (x[a, 0]), ``sds`` (sqrt(max(P[a, 0, 0], 0)),
    as np.sqrt(np.maximum(., 0.0))) and ``weights`` (mu[a]), each (n, 2): the table's columns gathered
    in one pass (numpy's fancy indexing of the packed, unaligned record columns is slow)."""
    for i in range(view.size):
        tr = tab[view[i]]
        for a in range(2):
            means[i, a] = tr.x[a, 0]
            p = tr.P[a, 0, 0]
            sds[i, a] = math.sqrt(p if (p >= 0.0 or p != p) else 0.0)
            weights[i, a] = tr.mu[a]


@njit(cache=True)
def settled_walkers(tab, n):
    """(walkers, tracks) among the first n tracks detected in at least three steps (det_steps >= 3),
    walkers those whose walking model's probability exceeds 0.5."""
    walkers = 0
    settled = 0
    for i in range(n):
        if tab[i].det_steps >= 3.0:
            settled += 1
            if tab[i].mu[1] > 0.5:
                walkers += 1
    return walkers, settled
