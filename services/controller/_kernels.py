"""Compiled inner loops of the controller (numba, cached on disk after the first run).

numba turns these plain loops into machine code: they run over a few dozen tracks and a grid
of a few hundred bearings, where numpy's per-call overhead would dominate the control step
(the tracker's own kernels are in ``_tracker``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2.0 * math.pi


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
def _cell(k: int, M: int) -> int:
    """k % M for k in [-M, 2 M) (a grid index one turn either side), without the integer division."""
    if k < 0:
        return k + M
    if k >= M:
        return k - M
    return k


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


@njit(cache=True, inline="always")
def _lbeta(a: float, b: float) -> float:
    return math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)


@njit(cache=True, inline="always")
def pod_evidence(k, n, alpha, beta, alpha0, beta0, outlier):
    """log of the Bayes factor of k detections in n frames for "this target is the Tx" (its POD
    ~ Beta(alpha, beta), predicted from the iso RSSI) against "it is another target" (its POD ~
    Beta(alpha0, beta0)): a ratio of beta-binomial marginals, so the binomial label noise p(1-p)/n
    (paper eq. 21) and the POD model's own uncertainty are both in it and it stays bounded."""
    if n <= 0.0:
        return 0.0
    return _pod_evidence_given(k, n, alpha, beta, alpha0, beta0, outlier, _lbeta(alpha, beta), _lbeta(alpha0, beta0))


@njit(cache=True, inline="always")
def _pod_evidence_given(k, n, alpha, beta, alpha0, beta0, outlier, lbeta, lbeta0):
    """``pod_evidence`` given its two terms that depend on no track, lbeta = _lbeta(alpha, beta) and lbeta0 =
    _lbeta(alpha0, beta0) (computed once for every track of a step: half its lgamma calls)."""
    if n <= 0.0:
        return 0.0
    k = min(max(k, 0.0), n)
    log_bf = (_lbeta(k + alpha, n - k + beta) - lbeta) - (_lbeta(k + alpha0, n - k + beta0) - lbeta0)
    # robust: with probability ``outlier`` the POD model says nothing about this Tx (shadowing,
    # a body in front of it, a detector that differs from the one trained): log((1-e) BF + e)
    if outlier <= 0.0:
        return log_bf
    if log_bf > 0.0:
        return log_bf + math.log((1.0 - outlier) + outlier * math.exp(-log_bf))
    return math.log((1.0 - outlier) * math.exp(log_bf) + outlier)


@njit(cache=True)
def add_pod_evidence(out, detections, frames, alpha, beta, alpha0, beta0, outlier):
    """out[i] += pod_evidence(detections[i], frames[i], ...) for every track (one call, not one
    per track)."""
    lbeta, lbeta0 = _lbeta(alpha, beta), _lbeta(alpha0, beta0)  # the same for every track
    for i in range(out.size):
        out[i] += _pod_evidence_given(detections[i], frames[i], alpha, beta, alpha0, beta0, outlier, lbeta, lbeta0)


@njit(cache=True)
def second_gap(bearings, estimate):
    """The second smallest |wrap(bearing - estimate)| (what sorting them and taking [1] gives;
    at least two bearings)."""
    first = np.inf
    second = np.inf
    for i in range(bearings.size):
        g = abs(_wrap(bearings[i] - estimate))
        if g < first:
            second = first
            first = g
        elif g < second:
            second = g
    return second


@njit(cache=True, inline="always")
def _smeared(l_rf, grid_step, rf_weight, mean, sd):
    """log of sum_g N(g; mean, sd^2) exp(rf_weight l_RF(g)) dg and the g maximising the integrand."""
    M = l_rf.size
    pos = ((mean + math.pi) / grid_step) % M
    half = min(int(4.0 * sd / grid_step) + 1, M // 2)
    centre = int(math.floor(pos + 0.5)) % M
    shift = pos - math.floor(pos + 0.5)
    best = -1e300
    arg = centre
    for d in range(-half, half + 1):
        off = (d - shift) * grid_step
        v = rf_weight * l_rf[_cell(centre + d, M)] - 0.5 * off * off / (sd * sd)
        if v > best:
            best = v
            arg = _cell(centre + d, M)
    total = 0.0
    for d in range(-half, half + 1):
        off = (d - shift) * grid_step
        total += math.exp(rf_weight * l_rf[_cell(centre + d, M)] - 0.5 * off * off / (sd * sd) - best)
    return best + math.log(total * grid_step / (math.sqrt(TWO_PI) * sd)), -math.pi + arg * grid_step


@njit(cache=True)
def track_logpost(l_rf, track_rf, grid_step, rf_weight, means, sds, weights, detections, frames, alpha, beta, alpha0, beta0,
                  outlier, out, where):
    """Unnormalised log-posterior of "track i is the Tx" and where that Tx is now.

    A track's bearing is a mixture (its IMM models: ``means``, ``sds``, ``weights``, shape
    (n, 2)). A component known to a grid step is scored by the track's own l_RF
    (``track_rf[i]``, which may follow its trajectory); a wider one integrates rf_weight * l_RF
    over its bearing uncertainty (a walker the camera has not seen for a while may be anywhere
    near its prediction: Rx(dir) says where). ``where[i]`` is the bearing of the track's most
    probable component (the maximiser of its integrand for a wide one). Plus ``pod_evidence``
    of its detection counts."""
    M = l_rf.size
    wide_best = -1e300
    wide_at = 0.0
    comp = np.empty(2)
    spot = np.empty(2)
    lbeta, lbeta0 = _lbeta(alpha, beta), _lbeta(alpha0, beta0)  # pod_evidence's terms that depend on no track
    for i in range(means.shape[0]):
        top = -1e300
        for a in range(2):
            if weights[i, a] <= 1e-3:  # a model this unlikely moves nothing (and costs a window of work)
                comp[a] = -1e300
                spot[a] = means[i, a]
                continue
            if sds[i, a] < grid_step:
                comp[a] = rf_weight * track_rf[i]
                spot[a] = means[i, a]
            elif sds[i, a] > 1.0:  # lost: anywhere on the circle, as far as the track can tell
                if wide_best < -1e299:
                    total = 0.0
                    top_j = 0
                    for j in range(M):
                        if l_rf[j] > l_rf[top_j]:
                            top_j = j
                    for j in range(M):
                        total += math.exp(rf_weight * (l_rf[j] - l_rf[top_j]))
                    wide_best = rf_weight * l_rf[top_j] + math.log(total / M)
                    wide_at = -math.pi + top_j * grid_step
                comp[a] = wide_best
                spot[a] = wide_at
            else:
                comp[a], spot[a] = _smeared(l_rf, grid_step, rf_weight, means[i, a], sds[i, a])
            comp[a] += math.log(weights[i, a])
            top = max(top, comp[a])
        if top <= -1e299:  # both models negligible (cannot happen with weights summing to 1)
            comp[0] = rf_weight * track_rf[i]
            top = comp[0]
        rf = top + math.log(math.exp(comp[0] - top) + math.exp(comp[1] - top))
        where[i] = spot[0] if comp[0] >= comp[1] else spot[1]
        out[i] = rf + _pod_evidence_given(detections[i], frames[i], alpha, beta, alpha0, beta0, outlier, lbeta, lbeta0)
    return out


@njit(cache=True)
def missed_logdensity(l_rf, rf_weight, miss_stand, miss_walk, walks, log_prior, outlier, out):
    """Log-posterior of "the Tx is a target not detected (where it is now), at grid bearing
    gamma": rf_weight * l_RF(gamma) + log P(no detection in the frames that looked there | the
    Tx's POD) + the log prior of such a target in that grid cell. A Tx that stands was missed
    in every frame ever taken there (``miss_stand``), one that walks only in the recent ones
    (``miss_walk``): mixed with probability ``walks``; with probability ``outlier[j]`` the miss
    says nothing (hidden behind someone, most likely just behind a detected target, or the POD
    model is off)."""
    # neighbouring cells were mostly looked at in the same frames: a cell whose (stand, walk, outlier)
    # equal the previous cell's has its miss term (the same function of the same doubles) reused
    last_stand = last_walk = last_e = math.nan
    miss = 0.0
    for j in range(l_rf.size):
        stand = miss_stand[j]
        walk = miss_walk[j]
        e = outlier[j]
        if not (stand == last_stand and walk == last_walk and e == last_e):
            top = max(stand, walk)
            miss = top + math.log((1.0 - walks) * math.exp(stand - top) + walks * math.exp(walk - top))
            if e > 0.0:
                miss = math.log((1.0 - e) * math.exp(miss) + e)
            last_stand, last_walk, last_e = stand, walk, e
        out[j] = rf_weight * l_rf[j] + miss + log_prior


@njit(cache=True)
def t_innovations(gain, gain0, z, z0, level_stand, level_walk, rho, noise_var, level_var_stand, level_var_walk, nu, differenced,
                  var, q):
    """The arithmetic of ``RFBearingFilter._slope_term`` and ``_sample_loglik`` for the paper response
    (mean = level gain, dE z / dL = gain) and Student-t innovations, at the standing level (cells
    0..M-1 of ``var`` and ``q``) and the walking one (M..2M-1), elementwise in their order:
    slope_term = (gain - rho gain0)^2 when ``differenced`` (else gain^2), var = noise_var (1 - rho^2)
    + slope_term level_var and resid = (z - rho z0) - (level gain - rho (level gain0)) (else
    noise_var + ..., z - level gain), q = resid^2 / (nu var)."""
    M = gain.size
    a = z - rho * z0
    b = noise_var * (1.0 - rho * rho)
    for j in range(2):
        level = level_stand if j == 0 else level_walk
        level_var = level_var_stand if j == 0 else level_var_walk
        for i in range(M):
            if differenced:
                d = gain[i] - rho * gain0[i]
                slope_term = d * d
                resid = a - (level * gain[i] - rho * (level * gain0[i]))
                v = b + slope_term * level_var
            else:
                slope_term = gain[i] * gain[i]
                resid = z - level * gain[i]
                v = noise_var + slope_term * level_var
            var[j * M + i] = v
            q[j * M + i] = resid * resid / (nu * v)


@njit(cache=True)
def t_combine(log1p_q, log_var, a, c, out):
    """out = a log1p_q - 0.5 log_var + c, elementwise in that order."""
    for i in range(out.size):
        out[i] = a * log1p_q[i] - 0.5 * log_var[i] + c


@njit(cache=True)
def arc_sum(weights, centre, half):
    """weights[(centre - half .. centre + half) % M] summed left to right from +0.0: what numpy's sum
    of those (gathered) terms gives when there are fewer than 8 of them (below its pairwise block)."""
    M = weights.size
    total = 0.0
    for d in range(-half, half + 1):
        total += weights[(centre + d) % M]
    return total


@njit(cache=True)
def floored_ratio(values, c, floor, out):
    """out = np.maximum(values / c, floor) (NaN kept, as np.maximum does)."""
    for i in range(values.size):
        v = values[i] / c
        out[i] = v if (v >= floor or v != v) else floor


@njit(cache=True)
def rebase(ll_stand, ll_walk, log_c, static, out_stand, out_walk):
    """out_stand = ll_stand - log_c, out_walk = ll_walk - log_c, static += out_stand."""
    for i in range(ll_stand.size):
        s = ll_stand[i] - log_c
        out_stand[i] = s
        out_walk[i] = ll_walk[i] - log_c
        static[i] += s


@njit(cache=True)
def mass_grid(bearings, post, step, w, M):
    """mass[c] = the summed max(post_i, 0) of the tracks whose nearest cell (np.rint((bearing + pi) /
    step) % M) is within w cells of c, added track by track, cell by cell (as np.add.at does)."""
    mass = np.zeros(M)
    for i in range(bearings.size):
        p = post[i] if post[i] > 0.0 else 0.0
        c = int(np.rint((bearings[i] + math.pi) / step)) % M
        for d in range(-w, w + 1):
            mass[(c + d) % M] += p
    return mass


@njit(cache=True)
def runs(values, starts, lengths):
    """The first index and the length of each run of equal consecutive values (a NaN is a run of its
    own) into ``starts`` and ``lengths`` (room for ``values.size``); returns the number of runs."""
    n = values.size
    r = 0
    for j in range(n):
        if j == 0 or values[j] != values[j - 1]:
            starts[r] = j
            lengths[r] = 1
            r += 1
        else:
            lengths[r - 1] += 1
    return r


@njit(cache=True)
def mark_arcs(out, bearings, step, h, value):
    """out[(c + d) % M] = value for d in [-h, h], c each bearing's nearest grid cell (as
    np.rint((wrap(bearing) + pi) / step) % M)."""
    M = out.size
    for i in range(bearings.size):
        c = int(np.rint((_wrap(bearings[i]) + math.pi) / step)) % M
        for d in range(-h, h + 1):
            out[(c + d) % M] = value


@njit(cache=True)
def mass_at(bearings, post, s, limit):
    """Posterior mass of the tracks within ``limit`` of pan ``s``."""
    total = 0.0
    for i in range(bearings.size):
        if abs(_wrap(bearings[i] - s)) <= limit:
            total += post[i]
    return total


@njit(cache=True, inline="always")
def _ucb_value(mean, sd, offset, amplitude, sqrt_beta, mass, view_frames, unseen_below, use_mass):
    """a(s) at one grid pan: U_D(s) ((J_RF(s) - offset) / A + sqrt(beta) sigma(s) / |A|), 1 for the RF
    part when A = 0, U_D = 1 where the camera has looked in fewer than ``unseen_below`` frames and the
    mass is below 1 (``use_mass``; else no factor)."""
    if amplitude != 0.0:
        value = (mean - offset) / amplitude + sqrt_beta * sd / abs(amplitude)
    else:
        value = 1.0
    if use_mass:
        u = mass
        if view_frames < unseen_below and u < 1.0:
            u = 1.0
        value = value * u
    return value


@njit(cache=True)
def acquire(mean, offset, amplitude, sd, sqrt_beta, bearings, post, view_frames, unseen_below, grid_step, limit, use_mass):
    """argmax over the grid of a(s) = U_D(s) (J_RF(s) + sqrt(beta) sigma(s)) (paper eq. 25 on the
    fused objective): J_RF is the normalised lobe, U_D the posterior mass of the tracks in view
    at s (1 where the camera has not looked yet)."""
    M = mean.size
    mass = np.zeros(M)
    if use_mass:
        w = int(math.floor(limit / grid_step + 1e-9))
        for i in range(bearings.size):
            if post[i] <= 0.0:
                continue
            centre = int(round(((bearings[i] + math.pi) / grid_step))) % M
            for d in range(-w, w + 1):
                mass[(centre + d) % M] += post[i]
    best = -1e300
    arg = 0
    for j in range(M):
        value = _ucb_value(mean[j], sd[j], offset, amplitude, sqrt_beta, mass[j], view_frames[j], unseen_below, use_mass)
        if value > best:
            best = value
            arg = j
    return arg


@njit(cache=True)
def probe(grid, g1, g2, width, left):
    """The grid pan where lobes centred at g1 and g2 differ most, on one side of their midpoint."""
    mid = g1 + 0.5 * _wrap(g2 - g1)
    best = -1.0
    arg = 0
    inv = 1.0 / (width * width)
    for j in range(grid.size):
        side = _wrap(grid[j] - mid) >= 0.0
        if side == left:
            continue
        a = math.sin(0.5 * (grid[j] - g1))
        b = math.sin(0.5 * (grid[j] - g2))
        d = abs(math.exp(-2.0 * a * a * inv) - math.exp(-2.0 * b * b * inv))
        if d > best:
            best = d
            arg = j
    return arg


@njit(cache=True)
def lobe_mean_at(s, x, Li, u, o, H_col, centre, A, c, width, res_len, res_var):
    """Posterior mean of the RSSI at pan ``s`` given the lobe (centre, A, c):
    c + A h(s - centre) + k(X, s)^T L^{-T} (u - c o - A H_col)."""
    n = x.size
    a = math.sin(0.5 * (s - centre))
    mean = c + A * math.exp(-2.0 * a * a / (width * width))
    if n == 0:
        return mean
    r = np.empty(n)
    for i in range(n):
        r[i] = u[i] - c * o[i] - A * H_col[i]
    # alpha = L^{-T} r, i.e. alpha_j = sum_i Li[i, j] r_i (Li lower triangular)
    total = 0.0
    for j in range(n):
        alpha = 0.0
        for i in range(j, n):
            alpha += Li[i, j] * r[i]
        b = math.sin(0.5 * (x[j] - s))
        total += res_var * math.exp(-2.0 * b * b / (res_len * res_len)) * alpha
    return mean + total


@njit(cache=True)
def _interp_periodic(values, angle, step):
    M = values.size
    pos = ((angle + math.pi) / step) % M
    lo = int(math.floor(pos))
    frac = pos - lo
    lo = lo % M
    return values[lo] * (1.0 - frac) + values[(lo + 1) % M] * frac


@njit(cache=True, inline="always")
def _arc(mean, half_width, step, M):
    """(first cell, cells) of the grid arc within ``half_width`` of ``mean``, at most the circle (first in
    [-M / 2, M): first + j for j < cells is one turn either side at most, ``_cell``)."""
    h = min(int(half_width / step), M // 2)
    centre = int(round((mean + math.pi) / step)) % M
    return centre - h, (2 * h + 1 if 2 * h + 1 <= M else M)


@njit(cache=True)
def smear_windows(means, sds, weights, step, M, first, count, offset, den):
    """The Gaussian windows ``track_sample_loglik`` averages each track's IMM component's sample
    likelihood over (``rf_filter.follow``): for a component of weight above 1e-3 and sd of at least a
    grid step, the arc within 4 sd of its mean (at most the circle: ``_arc``) into ``first[i, a]`` and
    ``count[i, a]`` (0: no window, the component is skipped or interpolated), its weights
    exp(-(d / sd)^2 / 2) at the cells' wrapped offsets d returned end to end (``offset[i, a]``: where
    its run starts) and summed in order into ``den[i, a]``. They depend on the tracks only, so the K
    tags' filters of a step share them."""
    n = means.shape[0]
    total = 0
    for i in range(n):
        for a in range(2):
            count[i, a] = 0
            if weights[i, a] <= 1e-3 or sds[i, a] < step:
                continue
            f, c = _arc(means[i, a], 4.0 * sds[i, a], step, M)
            first[i, a] = f
            count[i, a] = c
            offset[i, a] = total
            total += c
    w = np.empty(total)
    for i in range(n):
        for a in range(2):
            c = count[i, a]
            if c == 0:
                continue
            mean = means[i, a]
            sd = sds[i, a]
            f = first[i, a]
            o = offset[i, a]
            acc = 0.0
            for j in range(c):
                k = _cell(f + j, M)
                d = _wrap(-math.pi + k * step - mean)
                v = math.exp(-0.5 * (d / sd) ** 2)
                w[o + j] = v
                acc += v
            den[i, a] = acc
    return w


@njit(cache=True)
def track_sample_loglik(ll_stand, ll_walk, means, sds, weights, step, first, count, offset, w, den, out):
    """Each track's likelihood of this RF sample if it were the Tx (rf_filter.follow): its IMM
    components (standing with the standing level, walking with the walking one), each averaged over
    its Gaussian window (``smear_windows``: top + log(max(sum_j w_j exp(ll_j - top) / den, 1e-300)),
    top the window's largest ll, the sum in the window's order; interpolated at its mean when its sd
    is below a grid step), mixed by their weights. Windows that share their top (overlapping ones
    mostly do) share each cell's exp(ll_j - top): computed once, the same double."""
    M = ll_stand.size
    n = means.shape[0]
    tops = np.empty((n, 2))
    slot = np.empty((n, 2), dtype=np.int64)
    slot_model = np.empty(2 * n, dtype=np.int64)
    slot_top = np.empty(2 * n)
    slots = 0
    for i in range(n):  # each window's top, and one slot of exps per (model, top)
        for a in range(2):
            c = count[i, a]
            if c == 0 or weights[i, a] <= 1e-3:
                continue
            ll = ll_stand if a == 0 else ll_walk
            top = -1e300
            for j in range(c):
                k = _cell(first[i, a] + j, M)
                if ll[k] > top:
                    top = ll[k]
            tops[i, a] = top
            s = 0
            while s < slots and not (slot_model[s] == a and slot_top[s] == top):
                s += 1
            if s == slots:
                slot_model[s] = a
                slot_top[s] = top
                slots += 1
            slot[i, a] = s
    exps = np.full((slots, M), np.nan)  # exp(ll_k - top) of each slot, computed when first asked
    comp = np.empty(2)
    for i in range(n):
        top_i = -1e300
        for a in range(2):
            wt = weights[i, a]
            if wt <= 1e-3:  # a model this unlikely moves nothing (and costs a window of work)
                comp[a] = -1e300
                continue
            ll = ll_stand if a == 0 else ll_walk
            c = count[i, a]
            if c == 0:  # sd below a grid step
                s_ll = _interp_periodic(ll, means[i, a], step)
            else:
                top = tops[i, a]
                row = exps[slot[i, a]]
                f = first[i, a]
                o = offset[i, a]
                num = 0.0
                last_ll = math.nan  # a cell whose ll equals the last one computed here (outside the lobe most do) reuses its exp
                last_e = math.nan
                for j in range(c):
                    k = _cell(f + j, M)
                    e = row[k]
                    if e != e:
                        v = ll[k]
                        if v == last_ll:
                            e = last_e
                        else:
                            e = math.exp(v - top)
                            last_ll = v
                            last_e = e
                        row[k] = e
                    num += w[o + j] * e
                s_ll = top + math.log(max(num / den[i, a], 1e-300))
            comp[a] = math.log(wt) + s_ll
            top_i = max(top_i, comp[a])
        acc = 0.0
        for a in range(2):
            if comp[a] > -1e299:
                acc += math.exp(comp[a] - top_i)
        out[i] = top_i + math.log(acc) if acc > 0.0 else -1e300


@njit(cache=True)
def track_where(l_rf, means, sds, weights, step, sharp, out):
    """Where the Tx is now if it is track i: its dominant IMM component's mean, or, when that is
    wider than ``sharp``, the grid bearing maximising l_RF - (d / sd)^2 / 2 within 3 sd of it (its
    prediction times what Rx(dir) says)."""
    M = l_rf.size
    for i in range(means.shape[0]):
        a = 1 if weights[i, 1] > weights[i, 0] else 0
        mean = means[i, a]
        sd = sds[i, a]
        out[i] = mean
        if sd <= sharp:
            continue
        first, n = _arc(mean, 3.0 * sd, step, M)
        best = -1e300
        for j in range(n):
            k = _cell(first + j, M)
            g = -math.pi + k * step
            d = _wrap(g - mean)
            score = l_rf[k] - 0.5 * (d / sd) ** 2
            if score > best:
                best = score
                out[i] = g


@njit(cache=True, inline="always")
def _block_sum(a, lo, n):
    """numpy's pairwise summation of a[lo:lo + n] for n <= 128: left to right from +0.0 below 8 terms,
    else eight interleaved partial sums, combined pairwise, then the terms past the last multiple of 8."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        j = lo + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True)
def pairwise_sum(a, lo, n):
    """a[lo:lo + n].sum() as numpy sums a contiguous run of doubles (its pairwise summation): up to
    128 terms ``_block_sum``; above, the left part (n // 2 less its remainder mod 8) summed, then the
    right, added. numpy recurses; this walks the same tree with a stack (numba's cached recursion is
    not safe to call from other kernels): the same double."""
    if n <= 128:
        return _block_sum(a, lo, n)
    los = np.empty(64, dtype=np.int64)
    ns = np.empty(64, dtype=np.int64)
    left = np.empty(64)
    right_pending = np.zeros(64, dtype=np.bool_)
    top = 0
    los[0] = lo
    ns[0] = n
    result = 0.0
    while top >= 0:
        if ns[top] > 128:  # descend into the left part
            half = ns[top] // 2
            half -= half % 8
            los[top + 1] = los[top]
            ns[top + 1] = half
            right_pending[top + 1] = False
            top += 1
            continue
        v = _block_sum(a, los[top], ns[top])
        top -= 1
        while top >= 0:  # hand v up: a left part opens its right sibling, a right part completes its parent
            if not right_pending[top]:
                left[top] = v
                right_pending[top] = True
                half = ns[top] // 2
                half -= half % 8
                los[top + 1] = los[top] + half
                ns[top + 1] = ns[top] - half
                right_pending[top + 1] = False
                top += 1
                break
            v = left[top] + v
            top -= 1
        if top < 0:
            result = v
    return result


@njit(cache=True)
def exclusive_marginals(w, m, part_start, block_start, block_tags, reliable_share, out):
    """The inclusion-exclusion sum of ``multitag.exclusive_posteriors`` (each tag's unnormalised
    marginal when no two tags share one of the m tracks), over the partitions of the tags given as
    runs: partition p's blocks are ``block_start[part_start[p]:part_start[p + 1] + 1]`` into
    ``block_tags``. w (K, m + 1) holds each tag's weights, column m "missed". Writes the marginals
    normalised (negatives clipped to +0.0) into ``out`` and returns 1, or returns 0 when the sum
    cancels too much to trust (a negative below, or a total at most, ``reliable_share`` of its largest
    term). Every product, sum and accumulation in the order of the numpy expression it replaced."""
    k = w.shape[0]
    cols = w.shape[1]
    totals = np.empty(k)
    for t in range(k):
        totals[t] = pairwise_sum(w[t], 0, cols)
    out[:, :] = 0.0
    largest_term = 0.0
    values = np.empty(k)
    product = np.empty(m)
    for p in range(part_start.size - 1):
        b0, b1 = part_start[p], part_start[p + 1]
        mu = 1.0
        for b in range(b0, b1):
            size = block_start[b + 1] - block_start[b]
            factorial = 1.0
            for f in range(2, size):
                factorial *= f
            mu *= (-1.0 if size % 2 == 0 else 1.0) * factorial
            if size == 1:
                values[b - b0] = totals[block_tags[block_start[b]]]
            else:  # the block's rows multiplied in order, summed
                for c in range(m):
                    product[c] = w[block_tags[block_start[b]], c]
                for r in range(block_start[b] + 1, block_start[b + 1]):
                    for c in range(m):
                        product[c] = product[c] * w[block_tags[r], c]
                values[b - b0] = pairwise_sum(product, 0, m)
        prod_all = 1.0
        for b in range(b1 - b0):
            prod_all *= values[b]
        term = mu * prod_all
        largest_term = max(largest_term, abs(term))
        for b in range(b0, b1):
            others = 1.0
            for j in range(b1 - b0):
                if j != b - b0:
                    others *= values[j]
            scale = mu * others
            size = block_start[b + 1] - block_start[b]
            for r in range(block_start[b], block_start[b + 1]):
                tag = block_tags[r]
                if size == 1:
                    for c in range(cols):
                        out[tag, c] += scale * 1.0
                    continue
                first = True  # the rest of the block's product at each track (the other tags' rows in order), 0 at "missed"
                for q in range(block_start[b], block_start[b + 1]):
                    other = block_tags[q]
                    if other == tag:
                        continue
                    if first:
                        for c in range(m):
                            product[c] = w[other, c]
                        first = False
                    else:
                        for c in range(m):
                            product[c] = product[c] * w[other, c]
                for c in range(m):
                    out[tag, c] += scale * product[c]
                out[tag, m] += scale * 0.0
    for t in range(k):
        for c in range(cols):
            out[t, c] *= w[t, c]
    z = np.empty(k)
    for t in range(k):
        z[t] = pairwise_sum(out[t], 0, cols)
    floor = reliable_share * largest_term
    for t in range(k):
        if z[t] <= floor:
            return 0
        for c in range(cols):
            if out[t, c] < -floor:
                return 0
    for t in range(k):
        for c in range(cols):
            u = out[t, c]
            out[t, c] = (u if (u > 0.0 or u != u) else 0.0) / z[t]
    return 1


@njit(cache=True, inline="always")
def _max(values):
    """values.max() as numpy gives it (NaN when any value is NaN)."""
    top = -np.inf
    for i in range(values.size):
        v = values[i]
        if v != v:
            return v
        if v > top:
            top = v
    return top


@njit(cache=True, inline="always")
def _min(values):
    """values.min() as numpy gives it (NaN when any value is NaN)."""
    low = np.inf
    for i in range(values.size):
        v = values[i]
        if v != v:
            return v
        if v < low:
            low = v
    return low


@njit(cache=True)
def less_max(values, out):
    """out = values - values.max(); returns the max."""
    top = _max(values)
    for i in range(values.size):
        out[i] = values[i] - top
    return top


@njit(cache=True)
def clip_normalise(predicted, ll, shifted):
    """The walking filter's prediction and the sample's log-likelihood made ready to multiply
    (``RFBearingFilter._absorb``): predicted = np.maximum(predicted, 0.0) (NaN kept, -0.0 to +0.0),
    then predicted /= its numpy sum, in place; shifted = ll - ll.max(); returns ll.max()."""
    n = predicted.size
    for i in range(n):
        v = predicted[i]
        predicted[i] = v if (v > 0.0 or v != v) else 0.0
    total = pairwise_sum(predicted, 0, n)
    for i in range(n):
        predicted[i] = predicted[i] / total
    return less_max(ll, shifted)


@njit(cache=True)
def times_sum(weights, values):
    """values = weights * values in place; returns their numpy sum."""
    for i in range(values.size):
        values[i] = weights[i] * values[i]
    return pairwise_sum(values, 0, values.size)


@njit(cache=True)
def joint_logs(static, log_m, c_stand, walk, c_walk, joints, shifted):
    """The filter's joint log-densities (``RFBearingFilter._joints``): joints[0] = (static - log_m) +
    c_stand (stands, gamma), joints[1] = walk + c_walk (walks, gamma), and shifted[r] = joints[r] -
    joints[r].max(); returns the two maxima (what their logsumexps start from)."""
    for i in range(static.size):
        joints[0, i] = (static[i] - log_m) + c_stand
        joints[1, i] = walk[i] + c_walk
    return less_max(joints[0], shifted[0]), less_max(joints[1], shifted[1])


@njit(cache=True)
def ucb_grid(mean, sd, offset, amplitude, sqrt_beta, mass, view_frames, unseen_below, use_mass, out):
    """a(s) = U_D(s) ((J_RF(s) - offset) / A + sqrt(beta) sigma(s) / |A|) over the grid (paper eq. 25
    on the fused objective; ``joint.gpucb_values``: ``acquire``'s objective as an array): 1 for the RF part when A = 0;
    U_D the tracks' mass in view, 1 where the camera has looked at a bearing in fewer than
    ``unseen_below`` frames and the mass there is below 1 (``use_mass``; else no factor)."""
    for i in range(mean.size):
        out[i] = _ucb_value(mean[i], sd[i], offset, amplitude, sqrt_beta, mass[i], view_frames[i], unseen_below, use_mass)


@njit(cache=True)
def add_normalised(values, weight, total):
    """total += weight * (values - min) / (max - min) (weight * 0 when max <= min; NaN as numpy's min
    and max give it)."""
    hi = _max(values)
    lo = _min(values)
    span = hi - lo
    if hi > lo:
        for i in range(values.size):
            total[i] += weight * ((values[i] - lo) / span)
    else:
        for i in range(values.size):
            total[i] += weight * 0.0


@njit(cache=True)
def row_entropies(p, log_p, out):
    """out[r] = sum over row r of -p log p (0 where p is not positive: np.where(p > 0, -p * log_p, 0)),
    each row's terms summed as numpy sums them (pairwise)."""
    cols = p.shape[1]
    terms = np.empty(cols)
    for r in range(p.shape[0]):
        for c in range(cols):
            v = p[r, c]
            terms[c] = -v * log_p[r, c] if v > 0 else 0.0
        out[r] = pairwise_sum(terms, 0, cols)


@njit(cache=True)
def which_person_entropies(p, log_p, where, log_where, out):
    """out = entropy(p) + p[:, -1] * entropy(where) (``multitag.which_person_entropy``; each row's
    entropy summed as ``row_entropies`` sums it, then the product and the sum per row, as numpy's)."""
    row_entropies(p, log_p, out)
    h_where = np.empty(where.shape[0])
    row_entropies(where, log_where, h_where)
    last = p.shape[1] - 1
    for r in range(out.size):
        out[r] = out[r] + p[r, last] * h_where[r]


@njit(cache=True)
def pan_shares(h, open_, neediest, out):
    """``multitag.pan_weights`` from the tags' entropies h and open flags: all 0 when no tag is
    open; ``neediest``: 1 at np.argmax(np.where(open_, h, -inf)) (the first largest, the first NaN
    if any, as numpy's argmax); else w = np.where(open_, h, 0.0), replaced by the open flags as
    doubles when its numpy sum is not above 0, divided by its numpy sum."""
    k = h.size
    for i in range(k):
        out[i] = 0.0
    any_open = False
    for i in range(k):
        any_open = any_open or open_[i]
    if not any_open:
        return
    if neediest:
        best = 0
        top = h[0] if open_[0] else -np.inf
        if top == top:
            for i in range(1, k):
                v = h[i] if open_[i] else -np.inf
                if not v <= top:
                    top = v
                    best = i
                    if v != v:
                        break
        out[best] = 1.0
        return
    for i in range(k):
        out[i] = h[i] if open_[i] else 0.0
    if pairwise_sum(out, 0, k) <= 0.0:
        for i in range(k):
            out[i] = 1.0 if open_[i] else 0.0
    total = pairwise_sum(out, 0, k)
    for i in range(k):
        out[i] = out[i] / total


@njit(cache=True)
def times_sum_floored(weights, values, floor):
    """values = weights * values, c = their numpy sum, then values = np.maximum(values / c, floor) in place
    (NaN kept, as np.maximum does); returns c (``times_sum`` then ``floored_ratio``, in one call)."""
    for i in range(values.size):
        values[i] = weights[i] * values[i]
    c = pairwise_sum(values, 0, values.size)
    for i in range(values.size):
        v = values[i] / c
        values[i] = v if (v >= floor or v != v) else floor
    return c


@njit(cache=True)
def log_normalise(values, exps, top, out):
    """The logsumexp of ``values`` from ``exps`` = exp(values - top) (numpy's exps): lse = top +
    log(exps' numpy sum), and out = values - lse; returns lse."""
    lse = top + math.log(pairwise_sum(exps, 0, exps.size))
    for i in range(values.size):
        out[i] = values[i] - lse
    return lse


@njit(cache=True)
def row_totals(rows):
    """The numpy sums of the two rows of a C-contiguous (2, M) array (``rows.sum(axis=1)``)."""
    return pairwise_sum(rows[0], 0, rows.shape[1]), pairwise_sum(rows[1], 0, rows.shape[1])


@njit(cache=True)
def support(post, mass, keep, out):
    """The cells where ``post`` is at least ``mass`` times its largest (np.flatnonzero(post >= mass *
    post.max())) into keep[:n], their values divided by their numpy sum into out[:n]; returns n."""
    threshold = mass * _max(post)
    n = 0
    for i in range(post.size):
        if post[i] >= threshold:
            keep[n] = i
            out[n] = post[i]
            n += 1
    total = pairwise_sum(out, 0, n)
    for i in range(n):
        out[i] = out[i] / total
    return n


@njit(cache=True)
def spread(first, second, out):
    """out = np.sqrt(np.maximum(second - first * first, 0.0)): a standard deviation from the first two
    moments (NaN kept, as np.maximum does; the square root is exactly rounded everywhere)."""
    for i in range(first.size):
        v = second[i] - first[i] * first[i]
        out[i] = math.sqrt(v if (v >= 0.0 or v != v) else 0.0)


@njit(cache=True, inline="always")
def _argmax(values, lo, n):
    """np.argmax(values[lo:lo + n]) (the first largest; the first NaN if any), n >= 1."""
    best = 0
    top = values[lo]
    if top != top:
        return 0
    for i in range(1, n):
        v = values[lo + i]
        if v != v:
            return i
        if v > top:
            top = v
            best = i
    return best


@njit(cache=True)
def normalise_exps(weights, top):
    """weights /= their numpy sum, in place; returns top + log(that sum) (``fusion.softmax_and_logsumexp``
    from weights = exp(l - top))."""
    total = pairwise_sum(weights, 0, weights.size)
    for i in range(weights.size):
        weights[i] = weights[i] / total
    return top + math.log(total)


@njit(cache=True)
def shift_both(first, second, out):
    """out = np.concatenate([first - top, second - top]), top = max(float(first.max()), float(second.max())
    if second.size else -inf) (Python's max of the two: the second only when larger)."""
    top = _max(first)
    if second.size:
        other = _max(second)
        if other > top:
            top = other
    m = first.size
    for i in range(m):
        out[i] = first[i] - top
    for i in range(second.size):
        out[m + i] = second[i] - top


@njit(cache=True)
def posterior_both(weights, m, half):
    """``Fusion.answer``'s posterior from weights = exp(l - top) of "missed" (weights[:m]) and the tracks
    (weights[m:]): both divided in place by float(weights[:m].sum() + weights[m:].sum()) (each part summed as
    numpy sums it); returns the mass of the missed part's arc of ``half`` cells either side of its argmax
    (``arc_mass``: the gathered terms summed as numpy sums them), the tracks' argmax and their largest (0 and
    NaN without a track)."""
    n = weights.size - m
    total = pairwise_sum(weights, 0, m) + pairwise_sum(weights, m, n)
    for i in range(weights.size):
        weights[i] = weights[i] / total
    centre = _argmax(weights, 0, m)
    arc = np.empty(2 * half + 1)
    for d in range(-half, half + 1):
        arc[d + half] = weights[(centre + d) % m]
    missed_mass = pairwise_sum(arc, 0, arc.size)
    if n == 0:
        return missed_mass, 0, math.nan
    return missed_mass, _argmax(weights, m, n), _max(weights[m:])


@njit(cache=True)
def miss_arguments(values, alpha, beta, out):
    """The arguments of ``CameraBelief.miss_loglik``'s gammaln calls, end to end: values + beta, then
    values + alpha + beta (left to right), then alpha + beta and beta."""
    r = values.size
    for i in range(r):
        out[i] = values[i] + beta
        out[r + i] = values[i] + alpha + beta
    out[2 * r] = alpha + beta
    out[2 * r + 1] = beta


@njit(cache=True)
def repeat_miss(g, r, lengths, out):
    """From g = gammaln(``miss_arguments``): each run's (g[i] - g[r + i]) + (g[2 r] - g[2 r + 1]) repeated over
    its length into ``out`` (``vision_belief._repeated_miss``: np.repeat(gammaln(v + beta) - gammaln(v + alpha
    + beta) + base, lengths), base = gammaln(alpha + beta) - gammaln(beta))."""
    base = g[2 * r] - g[2 * r + 1]
    k = 0
    for i in range(r):
        v = (g[i] - g[r + i]) + base
        for _ in range(lengths[i]):
            out[k] = v
            k += 1


@njit(cache=True)
def count_views(window, frames, forget, view_frames, view_recent):
    """A step's frames counted where the camera looked (``CameraBelief.update``): view_frames[window] +=
    frames; view_recent *= forget; view_recent[window] += frames (``window`` a boolean mask)."""
    for i in range(window.size):
        if window[i]:
            view_frames[i] += frames
        view_recent[i] = view_recent[i] * forget
        if window[i]:
            view_recent[i] += frames


@njit(cache=True)
def less_twice(values, first, second):
    """values = (values - first) - second, in place."""
    for i in range(values.size):
        values[i] = (values[i] - first) - second


@njit(cache=True)
def runs_of_both(first, second, values, lengths):
    """The runs (``runs``) of ``first``, then those of ``second``: each run's value (its first element) into
    ``values`` and its length into ``lengths`` (room for both sizes); returns the number of runs. What
    ``vision_belief._runs_of`` of each, concatenated, gives."""
    r = 0
    for a in range(2):
        x = first if a == 0 else second
        for j in range(x.size):
            if j == 0 or x[j] != x[j - 1]:
                values[r] = x[j]
                lengths[r] = 1
                r += 1
            else:
                lengths[r - 1] += 1
    return r
