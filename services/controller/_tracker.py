"""Compiled step of the bearing-only multi-target tracker (``ra2vipas.services.controller.tracks``).

Per track, an interacting-multiple-model (IMM) filter over the state x = (gamma, omega) —
bearing and angular velocity — with two models: *standing* (omega = 0, a tiny bearing random
walk) and *walking* (nearly constant angular velocity, white angular acceleration of spectral
density q). Blom & Bar-Shalom (1988); Bar-Shalom, Li & Kirubarajan, *Estimation with
Applications to Tracking and Navigation* (2001), Sec. 11.6. A standing target keeps a tight
bearing while the camera looks elsewhere; a walker's bearing is predicted forward.

Per step: IMM prediction; per frame, the step's boxes are clustered across its frames (the
nu frames of a step see the same positions; two boxes of one frame are two targets), and the
clusters are assigned to tracks by global nearest neighbour on the tracks' predicted
densities, against the density of something new; one Kalman update per model with the
cluster's mean; births from the clusters no track took;
detection counts for the POD (discounted for walkers); deletion of tracks whose bearing is
lost. All arrays are updated in place; the function returns the new number of tracks.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2.0 * math.pi
NEW_TARGETS_PER_RAD = 1.0

# indices into the per-track parameter vector ``prm``
DT, SIGMA_B, Q_STAND, Q_WALK, P_SWITCH, GATE2, COUNT_LIMIT, OCCLUSION, TAU_WALK, OMEGA0, MAX_SD, F_WALK = range(12)


@njit(cache=True, inline="always")
def _wrap(x: float) -> float:
    return (x + math.pi) % TWO_PI - math.pi


@njit(cache=True)
def _predict_imm(x, P, mu, i, prm, out_mean, out_var, c):
    """IMM mixing and prediction of track i (x: (C, 2 models, 2), P: (C, 2, 2, 2), mu: (C, 2));
    writes the combined predicted bearing and its variance, and the predicted model
    probabilities into ``c``."""
    dt = prm[DT]
    # mixing probabilities mu_{a|b} = Pi_ab mu_a / c_b with Pi = [[1-p01, p01], [p10, 1-p10]],
    # whose stationary law is the share of walkers seen so far (F_WALK): a track the camera
    # has not seen for long drifts towards what targets here usually do, not towards 50/50
    p01 = prm[P_SWITCH] * prm[F_WALK]
    p10 = prm[P_SWITCH] * (1.0 - prm[F_WALK])
    c[0] = (1.0 - p01) * mu[i, 0] + p10 * mu[i, 1]
    c[1] = p01 * mu[i, 0] + (1.0 - p10) * mu[i, 1]
    g_ref = x[i, 0, 0]
    mx = np.zeros((2, 2))
    mP = np.zeros((2, 2, 2))
    for b in range(2):
        cb = max(c[b], 1e-300)
        w0 = ((1.0 - p01) if b == 0 else p01) * mu[i, 0] / cb
        w1 = (p10 if b == 0 else (1.0 - p10)) * mu[i, 1] / cb
        d0 = _wrap(x[i, 0, 0] - g_ref)
        d1 = _wrap(x[i, 1, 0] - g_ref)
        g = w0 * d0 + w1 * d1
        om = w0 * x[i, 0, 1] + w1 * x[i, 1, 1]
        mx[b, 0] = g
        mx[b, 1] = om
        for a in range(2):
            w = w0 if a == 0 else w1
            dg = (d0 if a == 0 else d1) - g
            do = x[i, a, 1] - om
            mP[b, 0, 0] += w * (P[i, a, 0, 0] + dg * dg)
            mP[b, 0, 1] += w * (P[i, a, 0, 1] + dg * do)
            mP[b, 1, 0] += w * (P[i, a, 1, 0] + do * dg)
            mP[b, 1, 1] += w * (P[i, a, 1, 1] + do * do)
    # model 0, standing: gamma' = gamma, omega' = 0
    x[i, 0, 0] = _wrap(g_ref + mx[0, 0])
    x[i, 0, 1] = 0.0
    P[i, 0, 0, 0] = mP[0, 0, 0] + prm[Q_STAND] * dt
    P[i, 0, 0, 1] = 0.0
    P[i, 0, 1, 0] = 0.0
    P[i, 0, 1, 1] = 0.0
    # model 1, walking: constant angular velocity, white angular acceleration
    q = prm[Q_WALK]
    p00, p01, p11 = mP[1, 0, 0], mP[1, 0, 1], mP[1, 1, 1]
    x[i, 1, 0] = _wrap(g_ref + mx[1, 0] + mx[1, 1] * dt)
    x[i, 1, 1] = mx[1, 1]
    P[i, 1, 0, 0] = p00 + 2.0 * dt * p01 + dt * dt * p11 + q * dt * dt * dt / 3.0
    P[i, 1, 0, 1] = p01 + dt * p11 + q * dt * dt / 2.0
    P[i, 1, 1, 0] = P[i, 1, 0, 1]
    P[i, 1, 1, 1] = p11 + q * dt
    _combine(x, P, c, i, out_mean, out_var)


@njit(cache=True, inline="always")
def _combine(x, P, w, i, out_mean, out_var):
    """The combined bearing and its variance (moment matching of the two models)."""
    ref = x[i, 0, 0]
    total = w[0] + w[1]
    d1 = _wrap(x[i, 1, 0] - ref)
    g = (w[1] * d1) / total
    out_mean[i] = _wrap(ref + g)
    out_var[i] = (w[0] * (P[i, 0, 0, 0] + g * g) + w[1] * (P[i, 1, 0, 0] + (d1 - g) * (d1 - g))) / total


@njit(cache=True)
def _cluster_step(boxes_abs, counts, sigma2):
    """Cluster the step's boxes across its frames (the nu frames of a step see the same
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
    gap2 = 9.0 * sigma2
    start = 0
    for f in range(nu):
        c = counts[f]
        if c == 0:
            continue
        done = np.zeros(c, dtype=np.bool_)
        busy = np.zeros(n_cl, dtype=np.bool_)
        n_old = n_cl
        while True:
            best = 2.0 * gap2  # 3 sigmas of a box from a cluster mean that is itself uncertain
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
def tracker_step(pan, boxes_rel, counts, step, n, prm,
                 x, P, mu, bearing, var, omega, k, nfr, nbox, det_steps, born, confirmed, misses, together,
                 pans, frames_per_pan, clutter, view_grid, ids, next_id):
    """One step of the tracker; returns the new number of tracks.

    ``boxes_rel``: all box bearings of the step relative to the optical axis, frame by frame,
    ``counts[f]`` boxes in frame f. ``clutter`` = [boxes that would start a new track where the
    camera already knows the targets, frames (times the explored share of the field of
    view)]: their ratio over the FoV width estimates the detector's clutter density. ``misses``: frames in view since a track's last detection.
    ``view_grid``: frames the camera had taken of each bearing before this step, on a uniform
    grid over [-pi, pi) (where the camera has not looked, new targets are expected).
    ``pans``/``frames_per_pan``: the pan history including this step (a new track's past frames
    in view are counted, so its detection rate is not biased by its birth). ``ids``: a stable
    id per track (``next_id[0]`` is the next one to give out).
    """
    capacity = bearing.size
    nu = counts.size
    sigma2 = prm[SIGMA_B] * prm[SIGMA_B]
    c = np.zeros(2)
    pred_c = np.zeros((capacity, 2))
    gate2 = prm[GATE2]
    # 1. IMM prediction
    for i in range(n):
        _predict_imm(x, P, mu, i, prm, bearing, var, c)
        pred_c[i, 0] = c[0]
        pred_c[i, 1] = c[1]
    # 2. the step's boxes as clusters (one per target seen), then one cluster per track, best
    # first: a cluster joins a track where the track's predicted density of the cluster's mean
    # beats that of something new (clutter, plus, where the camera has hardly looked yet, a
    # target not seen before: about one per radian, fading as the bearing gets looked at)
    boxes_abs = np.empty(boxes_rel.size)
    for j in range(boxes_rel.size):
        boxes_abs[j] = _wrap(pan + boxes_rel[j])
    cmean, ccnt, cframes = _cluster_step(boxes_abs, counts, sigma2)
    n_cl = cmean.size
    density_clutter = clutter[0] / max(clutter[1], 1e-9) / (2.0 * max(prm[COUNT_LIMIT], 1e-3)) if clutter[1] >= 20.0 else 0.0
    G = view_grid.size
    log_new = np.empty(n_cl)
    for q in range(n_cl):
        cell = int(((cmean[q] + math.pi) / TWO_PI) * G) % G
        unseen = math.exp(-view_grid[cell] / (2.0 * nu))
        log_new[q] = math.log(max(density_clutter + NEW_TARGETS_PER_RAD * unseen, 1e-12))
    owner = np.full(n_cl, -1, dtype=np.int64)
    used = np.zeros(n, dtype=np.bool_)
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
                    S = P[i, a, 0, 0] + R
                    da = _wrap(cmean[q] - x[i, a, 0])
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
    frames_hit = np.zeros(capacity)
    hit_in = np.zeros((capacity, nu), dtype=np.bool_)
    for q in range(n_cl):
        i = owner[q]
        if i >= 0:
            for fr in range(nu):
                if cframes[q, fr]:
                    hit_in[i, fr] = True
                    frames_hit[i] += 1.0
    # 3. IMM update with the mean of the track's cluster
    lik = np.zeros(2)
    real = np.zeros(capacity)
    measured = np.zeros(capacity, dtype=np.bool_)
    for q in range(n_cl):
        if owner[q] >= 0:
            measured[owner[q]] = True
    for i in range(n):
        q = -1
        if measured[i]:
            for qq in range(n_cl):
                if owner[qq] == i:
                    q = qq
                    break
        if q >= 0:
            z = cmean[q]
            R = sigma2 / ccnt[q]
            # probabilistic data association (Bar-Shalom & Tse 1975): a lone box may be a false
            # one (clutter density lam per rad); more boxes at one spot in one step hardly are
            lam = density_clutter if ccnt[q] < 1.5 else 0.0
            dens = 0.0
            for a in range(2):
                S = P[i, a, 0, 0] + R
                v = _wrap(z - x[i, a, 0])
                lik[a] = math.exp(-0.5 * v * v / S) / math.sqrt(TWO_PI * S)
                dens += pred_c[i, a] * lik[a]
            w = dens / (dens + lam) if dens + lam > 0.0 else 0.0  # P(the cluster is this target's)
            real[i] = w
            for a in range(2):
                v = _wrap(z - x[i, a, 0])
                S = P[i, a, 0, 0] + R
                K0 = P[i, a, 0, 0] / S
                K1 = P[i, a, 1, 0] / S
                x[i, a, 0] = _wrap(x[i, a, 0] + w * K0 * v)
                x[i, a, 1] += w * K1 * v
                p00, p01, p10, p11 = P[i, a, 0, 0], P[i, a, 0, 1], P[i, a, 1, 0], P[i, a, 1, 1]
                # PDA covariance: the updated one if real, the predicted one if not, plus the spread
                spread = w * (1.0 - w) * v * v
                P[i, a, 0, 0] = p00 - w * K0 * p00 + spread * K0 * K0
                P[i, a, 0, 1] = p01 - w * K0 * p01 + spread * K0 * K1
                P[i, a, 1, 0] = p10 - w * K1 * p00 + spread * K1 * K0
                P[i, a, 1, 1] = p11 - w * K1 * p01 + spread * K1 * K1
            s0 = pred_c[i, 0] * (lik[0] + lam)
            s1 = pred_c[i, 1] * (lik[1] + lam)
            tot = s0 + s1
            if tot > 1e-300:
                mu[i, 0] = s0 / tot
                mu[i, 1] = s1 / tot
            else:
                mu[i, 0] = pred_c[i, 0]
                mu[i, 1] = pred_c[i, 1]
            nbox[i] += w * ccnt[q]
            det_steps[i] += w
        else:
            mu[i, 0] = pred_c[i, 0]
            mu[i, 1] = pred_c[i, 1]
        c[0] = mu[i, 0]
        c[1] = mu[i, 1]
        _combine(x, P, c, i, bearing, var)
        omega[i] = mu[i, 1] * x[i, 1, 1]
    # tracks detected in the same frame are two targets
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
    # clutter: boxes that no confirmed track explains, where the camera has looked long enough to know the
    # targets (a clean detector hardly does that; a cluttered one keeps doing it), per frame and
    # per radian of well-explored field of view
    explored_cells = 0
    fov_cells = 0
    for cell in range(G):
        b_cell = -math.pi + TWO_PI * (cell + 0.5) / G
        if abs(_wrap(b_cell - pan)) <= prm[COUNT_LIMIT]:
            fov_cells += 1
            if view_grid[cell] >= 3.0 * nu:
                explored_cells += 1
    for q in range(n_cl):
        if owner[q] < 0 or not confirmed[owner[q]]:
            cell = int(((cmean[q] + math.pi) / TWO_PI) * G) % G
            if view_grid[cell] >= 3.0 * nu:
                clutter[0] += ccnt[q]
    clutter[1] += nu * explored_cells / max(fov_cells, 1)
    # 4. detection counts (a walker's are discounted: its POD changes with its range); a step in
    # which a track may be hidden behind another one counts only if it was detected
    for i in range(n):
        keep = mu[i, 0] + mu[i, 1] * math.exp(-prm[DT] / prm[TAU_WALK])
        k[i] *= keep
        nfr[i] *= keep
        if abs(_wrap(bearing[i] - pan)) > prm[COUNT_LIMIT]:
            continue
        hidden = False
        for j in range(n):
            if j != i and confirmed[j] and abs(_wrap(bearing[j] - bearing[i])) < prm[OCCLUSION]:
                hidden = True
                break
        if hidden and frames_hit[i] == 0.0:  # a miss while another target stands in front may be occlusion
            continue
        k[i] += real[i] * frames_hit[i]
        nfr[i] += nu
        misses[i] = 0.0 if frames_hit[i] > 0.0 else misses[i] + nu
    # 5. births: the clusters no track took
    for q in range(n_cl):
        if owner[q] >= 0 or n >= capacity:
            continue
        cnt_boxes = ccnt[q]
        g = cmean[q]
        distinct = 0
        for fr in range(nu):
            if cframes[q, fr]:
                distinct += 1
                hit_in[n, fr] = True
        for a in range(2):
            x[n, a, 0] = g
            x[n, a, 1] = 0.0
            P[n, a, 0, 0] = sigma2 / cnt_boxes
            P[n, a, 0, 1] = 0.0
            P[n, a, 1, 0] = 0.0
            P[n, a, 1, 1] = 0.0 if a == 0 else prm[OMEGA0] * prm[OMEGA0]
        mu[n, 0] = 1.0 - prm[F_WALK]
        mu[n, 1] = prm[F_WALK]
        bearing[n] = g
        var[n] = sigma2 / cnt_boxes
        omega[n] = 0.0
        nbox[n] = cnt_boxes
        det_steps[n] = 1.0
        born[n] = step
        confirmed[n] = False
        misses[n] = 0.0
        ids[n] = next_id[0]
        next_id[0] += 1
        inview = abs(_wrap(g - pan)) <= prm[COUNT_LIMIT]
        k[n] = distinct if inview else 0.0
        seen_frames = 0.0
        for p in range(pans.size - 1):  # frames in view before this step (as if it had stood there)
            if abs(_wrap(g - pans[p])) <= prm[COUNT_LIMIT]:
                seen_frames += frames_per_pan[p]
        nfr[n] = seen_frames + (nu if inview else 0.0)
        for j in range(n):  # frames of this step in which the new track and another one were both seen
            both = 0.0
            for fr in range(nu):
                if hit_in[n, fr] and hit_in[j, fr]:
                    both += 1.0
            together[n, j] = both
            together[j, n] = both
        together[n, n] = 0.0
        n += 1
    # 6. confirmation: a track is a target once its detections stand out from what clutter
    # alone would put in its gate (a log-likelihood ratio of its detection counts, k frames with
    # a box out of n, against the clutter rate q there); while the detector has not been caught
    # inventing boxes, at once
    q_gate = min(density_clutter * 2.0 * math.sqrt(gate2) * prm[SIGMA_B], 0.5)
    clean = q_gate < 0.005
    evidence = np.zeros(n)
    for i in range(n):
        kk = min(max(k[i], 0.0), nfr[i])
        if q_gate > 0.0 and nfr[i] > 0.0:
            p_hat = max(kk / nfr[i], q_gate)
            evidence[i] = kk * math.log(p_hat / q_gate)
            if nfr[i] > kk:
                evidence[i] += (nfr[i] - kk) * math.log(max(1.0 - p_hat, 1e-12) / (1.0 - q_gate))
        else:
            evidence[i] = 1e9
        if not confirmed[i] and (clean or (det_steps[i] >= 2.0 and evidence[i] >= 4.0)):
            confirmed[i] = True
    # 7. merges (one target split in two: close, (almost) never seen in the same frame) and
    # deletions: a tentative track looked at again for two steps and not seen (a false box), a
    # track whose detections, after many frames, are no more than clutter would give, a walker
    # whose bearing is lost
    i = 0
    while i < n:
        false_box = not confirmed[i] and misses[i] >= 2.0 * nu
        only_clutter = not clean and nfr[i] >= 20.0 * nu and evidence[i] < 0.0
        drop = false_box or only_clutter or (math.sqrt(var[i]) > prm[MAX_SD] and mu[i, 1] > 0.5)
        if not drop:
            for j in range(n):
                # same target: within 4 box sigmas, and (almost) never detected in the same frame
                dij = _wrap(bearing[j] - bearing[i])
                if j != i and nbox[j] >= nbox[i] and dij * dij < 16.0 * sigma2 \
                        and together[i, j] <= 0.05 * min(nbox[i], nbox[j]):
                    # fold i into j
                    tot_b = nbox[i] + nbox[j]
                    bearing_j = _wrap(bearing[j] + _wrap(bearing[i] - bearing[j]) * nbox[i] / tot_b)
                    for a in range(2):
                        x[j, a, 0] = _wrap(x[j, a, 0] + _wrap(bearing_j - bearing[j]))
                    bearing[j] = bearing_j
                    nbox[j] = tot_b
                    k[j] += k[i]
                    nfr[j] = max(nfr[i], nfr[j])
                    det_steps[j] = max(det_steps[i], det_steps[j])
                    confirmed[j] = confirmed[j] or confirmed[i]
                    for q in range(n):
                        together[j, q] += together[i, q]
                        together[q, j] += together[q, i]
                    together[j, j] = 0.0
                    drop = True
                    break
        if drop:
            last = n - 1
            if i != last:
                x[i] = x[last]
                P[i] = P[last]
                mu[i] = mu[last]
                bearing[i] = bearing[last]
                var[i] = var[last]
                omega[i] = omega[last]
                k[i] = k[last]
                nfr[i] = nfr[last]
                nbox[i] = nbox[last]
                det_steps[i] = det_steps[last]
                born[i] = born[last]
                confirmed[i] = confirmed[last]
                misses[i] = misses[last]
                ids[i] = ids[last]
                for q in range(n):
                    together[i, q] = together[last, q]
                    together[q, i] = together[q, last]
                together[i, i] = 0.0
            n -= 1
            continue
        i += 1
    return n
