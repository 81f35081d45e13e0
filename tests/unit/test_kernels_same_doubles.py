"""The compiled shortcuts of the controller's step give the same doubles as the numpy expressions
they replaced (services/controller/_kernels.py, _tracker.py: speed without changing a result)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from numba import njit
from scipy.special import gammaln

from ra2vipas.services.controller import _kernels, _tracker, multitag, rf_filter
from ra2vipas.services.controller.acquisition import GPUCB
from ra2vipas.services.controller.fusion import arc_mass, refined_argmax, softmax, softmax_and_logsumexp
from ra2vipas.services.controller.grid import CircleGrid
from ra2vipas.services.controller.joint import SummedGPUCB, gpucb_values
from ra2vipas.services.controller.rf_filter import RxDirModel, antenna_gain, logsumexp
from ra2vipas.services.controller.tracks import BearingTracker
from ra2vipas.services.controller.vision_belief import CameraBelief, PODLookup, _per_run, _runs_of
from ra2vipas.services.protocol.angles import wrap
from ra2vipas.services.protocol.pod import PODModel


def _same(a, b) -> bool:
    return np.asarray(a, dtype=float).tobytes() == np.asarray(b, dtype=float).tobytes()


def test_wrap_and_grid_shortcuts():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-20.0, 20.0, 2000), [math.pi, -math.pi, 0.0, -0.0, 2 * math.pi, -2 * math.pi]])
    assert all(_kernels._wrap(v) == float(wrap(v)) for v in x)
    circle = CircleGrid(360)
    values = rng.normal(size=360) * 50.0
    assert all(_kernels._interp_periodic(values, float(a), circle.step) == float(circle.interp(values, np.array([a]))[0]) for a in x)
    for _ in range(200):
        b = rng.uniform(-4.0, 4.0, int(rng.integers(2, 40)))
        e = float(rng.uniform(-4.0, 4.0))
        assert _kernels.second_gap(b, e) == np.sort(np.abs(wrap(b - e)))[1]
    for _ in range(500):  # below numpy's pairwise block a sum is left to right
        w = rng.uniform(0.0, 1.0, 360) * 10.0 ** rng.integers(-30, 3, 360)
        c, h = int(rng.integers(0, 360)), int(rng.integers(1, 4))
        assert arc_mass(w, c, h) == float(w[np.arange(c - h, c + h + 1) % 360].sum())


def test_mass_and_arcs_as_numpy_indexing():
    rng = np.random.default_rng(1)
    M, step = 360, 2 * math.pi / 360
    for n in (1, 7, 40):
        b = rng.uniform(-math.pi, math.pi, n)
        post = rng.uniform(-0.1, 1.0, n)
        for w in (2, 25):
            want = np.zeros(M)
            idx = (np.rint((b + math.pi) / step).astype(np.int64) % M)[:, None] + np.arange(-w, w + 1)[None, :]
            np.add.at(want, idx % M, np.where(post > 0.0, post, 0.0)[:, None] * np.ones((1, 2 * w + 1)))
            assert _same(_kernels.mass_grid(b, post, step, w, M), want)
            marked = np.full(M, 0.2)
            _kernels.mark_arcs(marked, b, step, w, 0.9)
            want = np.full(M, 0.2)
            want[((np.rint((wrap(b) + math.pi) / step).astype(np.int64) % M)[:, None] + np.arange(-w, w + 1)[None, :]) % M] = 0.9
            assert _same(marked, want)


def test_per_run_gammaln_and_table_columns():
    rng = np.random.default_rng(2)
    frames = np.repeat(rng.choice(np.arange(20) * 8.0, 30), rng.integers(1, 25, 30))[:360]
    alpha, beta = 2.3, 5.1
    base = gammaln(alpha + beta) - gammaln(beta)
    assert _same(_per_run(frames, alpha, beta, base), gammaln(frames + beta) - gammaln(frames + alpha + beta) + base)
    circle = CircleGrid(360)
    response = RxDirModel("paper", 0.5)
    for stride in (1, 2):
        table = response.gain_table(circle, stride)
        for keep in (np.arange(100, 130), np.array([0, 5, 359])):
            assert _same(table[:, keep], antenna_gain(circle.angles[::stride, None] - circle.angles[keep][None, :], 0.5))
    pan = float(circle.angles[17]) + 1e-13
    assert _same(response.gain_over(pan, circle), antenna_gain(pan - circle.angles, 0.5))


def test_track_table_gathers():
    tracker = BearingTracker(0.5, 0.01)
    rng = np.random.default_rng(3)
    tab = tracker._tab
    tab["x"] = rng.normal(size=tab["x"].shape)
    tab["P"] = rng.normal(size=tab["P"].shape)
    tab["mu"] = rng.uniform(size=tab["mu"].shape)
    tab["det_steps"] = rng.uniform(0.0, 6.0, tab.size)
    view = np.flatnonzero(rng.uniform(size=tab.size) < 0.5)
    n = view.size
    means, sds, weights = np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2))
    _tracker.components(tab, view, means, sds, weights)
    assert _same(means, tracker._x[view, :, 0]) and _same(weights, tracker._mu[view])
    assert _same(sds, np.sqrt(np.maximum(tracker._P[view, :, 0, 0], 0.0)))
    settled = tracker._det_steps[:200] >= 3.0
    assert _tracker.settled_walkers(tab, 200) == (int(np.count_nonzero(tracker._mu[:200, 1][settled] > 0.5)), int(settled.sum()))


def test_pairwise_sum_is_numpys():
    rng = np.random.default_rng(4)
    for n in [*range(0, 300), 360, 361, 1000, 1024, 4099, 20000]:
        x = rng.standard_normal(n) * 10.0 ** rng.integers(-8, 8, n)
        assert _kernels.pairwise_sum(x, 0, n) == x.sum()
        assert n < 3 or _kernels.pairwise_sum(x, 2, n - 2) == x[2:].sum()


def _exclusive_numpy(track_loglik, missed_loglik):
    """multitag.exclusive_posteriors as it was before its sum was compiled (numpy and Python floats)."""
    tracks, missed = np.asarray(track_loglik, dtype=float), np.asarray(missed_loglik, dtype=float)
    k, m = tracks.shape
    full = np.concatenate([tracks, missed[:, None]], axis=1)
    w = np.exp(full - full.max(axis=1, keepdims=True))
    unnormalised = np.zeros_like(w)
    largest_term = 0.0
    totals = w.sum(axis=1)
    ones = np.ones(m + 1)

    def product_of(tags):
        product = w[tags[0], :m]
        for t in tags[1:]:
            product = product * w[t, :m]
        return product

    for blocks in multitag._partitions_of(k):
        mu = 1.0
        shared, values = {}, []
        for block in blocks:
            size = len(block)
            mu *= (-1.0) ** (size - 1) * math.factorial(size - 1)
            if size == 1:
                values.append(float(totals[block[0]]))
                shared[block[0]] = ones
                continue
            values.append(float(product_of(block).sum()))
            for tag in block:
                rest = np.zeros(m + 1)
                rest[:m] = product_of([t for t in block if t != tag])
                shared[tag] = rest
        term = mu * math.prod(values)
        largest_term = max(largest_term, abs(term))
        for i, block in enumerate(blocks):
            others = math.prod(v for j, v in enumerate(values) if j != i)
            for tag in block:
                unnormalised[tag] += mu * others * shared[tag]
    unnormalised *= w
    z = unnormalised.sum(axis=1)
    share = multitag.RELIABLE_SHARE
    if (unnormalised < -share * largest_term).any() or (z <= share * largest_term).any():
        return multitag._enumerated(w, m, full - full.max(axis=1, keepdims=True))
    return np.clip(unnormalised, 0.0, None) / z[:, None]


def test_exclusive_marginals_as_the_numpy_sum():
    rng = np.random.default_rng(5)
    enumerated = 0
    for trial in range(3000):
        k, m = int(rng.integers(2, 5)), int(rng.integers(1, 140 if trial % 10 == 0 else 30))
        scale = 10.0 ** rng.uniform(-1.0, 3.0)  # up to tags all but certain of one track each
        tracks, missed = rng.normal(size=(k, m)) * scale, rng.normal(size=k) * scale
        if trial % 7 == 0:  # two tags after one track
            tracks[1, 0] = tracks[0, 0] = tracks.max() + 5.0
        want, got = _exclusive_numpy(tracks, missed), multitag.exclusive_posteriors(tracks, missed)
        assert np.isfinite(got).all() and np.allclose(got.sum(axis=1), 1.0)
        assert _same(got, want)
        full = np.concatenate([tracks, missed[:, None]], axis=1)
        w = np.exp(full - full.max(axis=1, keepdims=True))
        enumerated += not _kernels.exclusive_marginals(w, m, *multitag._partition_runs(k), multitag.RELIABLE_SHARE, np.empty_like(w))
    assert enumerated > 30  # the cancelling case is exercised too


@njit
def _smeared_loglik_before(ll, mean, sd, step):
    if sd < step:
        return _kernels._interp_periodic(ll, mean, step)
    M = ll.size
    first, n = _kernels._arc(mean, 4.0 * sd, step, M)
    top = -1e300
    for j in range(n):
        k = _kernels._cell(first + j, M)
        if ll[k] > top:
            top = ll[k]
    num = 0.0
    den = 0.0
    for j in range(n):
        k = _kernels._cell(first + j, M)
        d = _kernels._wrap(-math.pi + k * step - mean)
        w = math.exp(-0.5 * (d / sd) ** 2)
        den += w
        num += w * math.exp(ll[k] - top)
    return top + math.log(max(num / den, 1e-300))


@njit
def _sample_loglik_before(ll_stand, ll_walk, means, sds, weights, step, out):
    """rf_filter.follow's kernel before the K tags shared the Gaussian windows (each component's
    weights computed in the tag's own pass), verbatim."""
    for i in range(means.shape[0]):
        top = -1e300
        comp = np.empty(2)
        for a in range(2):
            w = weights[i, a]
            if w <= 1e-3:
                comp[a] = -1e300
                continue
            ll = ll_stand if a == 0 else ll_walk
            comp[a] = math.log(w) + _smeared_loglik_before(ll, means[i, a], sds[i, a], step)
            top = max(top, comp[a])
        acc = 0.0
        for a in range(2):
            if comp[a] > -1e299:
                acc += math.exp(comp[a] - top)
        out[i] = top + math.log(acc) if acc > 0.0 else -1e300


def test_shared_smear_windows_give_each_tags_sample_loglik():
    rng = np.random.default_rng(6)
    circle = CircleGrid(360)
    for _ in range(40):
        n = int(rng.integers(1, 30))
        means = rng.uniform(-4.0, 4.0, (n, 2))
        sds = np.abs(rng.normal(size=(n, 2))) * 10.0 ** rng.uniform(-3.0, 0.5, (n, 2))
        weights = rng.dirichlet([1.0, 1.0], n)
        weights[rng.uniform(size=n) < 0.2, 1] = 1e-4
        assert rf_filter.smear_windows(means, sds, weights, circle)[3] is not rf_filter.smear_windows(means, sds, weights, circle)[3]
        for array in (means, sds, weights):  # the tracker's components: read-only, kept for the step
            array.flags.writeable = False
        kept = None
        for tag in range(4):  # the K tags of a step: the windows computed once (kept), each tag's own likelihoods
            ll_stand, ll_walk = rng.normal(size=360) * 5.0, rng.normal(size=360) * 5.0
            if tag:  # smooth, as a sample's likelihood over the grid is: overlapping windows share their top
                ll_stand, ll_walk = (-3.0 * (1.0 - np.cos(circle.angles - rng.uniform(-3.0, 3.0))) for _ in range(2))
            if tag == 3:  # flat where the antenna's gain is 0 (equal doubles in a row), as the paper response's is
                ll_stand, ll_walk = np.maximum(ll_stand, -2.0), np.maximum(ll_walk, -1.5)
            m, s, w, windows = rf_filter.smear_windows(means, sds, weights, circle)
            assert tag == 0 or windows is kept
            kept = windows
            out = np.empty(n)
            _kernels.track_sample_loglik(ll_stand, ll_walk, m, s, w, circle.step, *windows, out)
            want = np.empty(n)
            _sample_loglik_before(ll_stand, ll_walk, means, sds, weights, circle.step, want)
            assert _same(out, want)


def test_one_exp_for_softmax_and_logsumexp_and_the_views_runs_once():
    rng = np.random.default_rng(7)
    for _ in range(200):
        x = rng.normal(size=int(rng.integers(1, 400))) * 10.0 ** rng.uniform(-2.0, 3.0)
        post, lse = softmax_and_logsumexp(x)
        assert _same(post, softmax(x)) and lse == logsumexp(x)
    camera = CameraBelief(CircleGrid(360), 0.39, 0.01, 0.1, 10, None)
    for step in range(30):  # the K tags of a step share the runs of the view counts; each its own POD
        camera.view_frames[rng.integers(0, 300):][: rng.integers(1, 60)] += 10.0
        camera.view_recent *= 0.88
        camera.view_recent[rng.integers(0, 300):][: rng.integers(1, 60)] += 10.0
        camera._steps = step
        for alpha, beta in rng.uniform(0.3, 9.0, (3, 2)):
            base = gammaln(alpha + beta) - gammaln(beta)
            stand, walk = camera.miss_loglik(alpha, beta)
            assert _same(stand, _per_run(camera.view_frames, alpha, beta, base))
            assert _same(walk, _per_run(camera.view_recent, alpha, beta, base))


def test_walking_filter_update_as_the_numpy_expressions():
    rng = np.random.default_rng(8)
    for n in (360, 359, 64):
        x, k = rng.random(n), np.fft.rfft(rng.random(n))
        assert _same(rf_filter.convolve_periodic(x, k), np.fft.irfft(np.fft.rfft(x) * k, n=n))
    p = rng.normal(size=360) * 1e-17
    p[[3, 70, 200]] = [-0.0, np.nan, 0.0]
    ll = rng.normal(size=360)
    want_p = np.maximum(p, 0.0)
    want_p /= want_p.sum()
    shifted = np.empty(360)
    assert _kernels.clip_normalise(p, ll, shifted) == ll.max() and _same(p, want_p) and _same(shifted, ll - ll.max())
    rff = rf_filter.RFBearingFilter(CircleGrid(360), RxDirModel("paper", 0.5), 3.0, 0.1)
    for _ in range(50):
        rff._walk = np.log(rng.dirichlet(np.full(360, 0.3)) + 1e-300)
        ll_stand, ll_walk = rng.normal(size=360) * 4.0, rng.normal(size=360) * 4.0
        static = rff._static.copy()
        walk, steps = rff._walk, int(rng.integers(1, 4))
        prior = np.exp(walk - walk.max())  # _absorb as it was, in numpy
        predicted = np.maximum(np.fft.irfft(np.fft.rfft(prior) * rff._kernel_fft**steps, n=360), 0.0)
        predicted /= predicted.sum()
        top = ll_walk.max()
        joint = predicted * np.exp(ll_walk - top)
        c = float(joint.sum())
        log_c = float(top + math.log(max(c, 1e-300)))
        rff._absorb(ll_stand, ll_walk, steps)
        assert _same(rff._walk, np.log(np.maximum(joint / c, 1e-300)))
        assert _same(rff.ll_walk, ll_walk - log_c) and _same(rff._static, static + (ll_stand - log_c))


def test_gain_table_columns_without_a_copy_give_the_same_products():
    rng = np.random.default_rng(9)
    circle, response = CircleGrid(360), RxDirModel("paper", 0.5)
    for stride in (1, 2):
        table, squared = response.gain_table(circle, stride), response.gain_table(circle, stride, squared=True)
        assert _same(squared, table * table)
        for _ in range(1500):
            if rng.uniform() < 0.7:  # a run of cells (the posterior's support mostly is), else scattered cells
                a = int(rng.integers(0, 359))
                keep = np.arange(a, int(rng.integers(a + 1, 361)))
            else:
                keep = np.sort(rng.choice(360, int(rng.integers(1, 200)), replace=False))
            p = rng.random(keep.size)
            p /= p.sum()
            copy = np.ascontiguousarray(table[:, keep])  # what rf_filter multiplied before: a C-contiguous copy
            first = rf_filter._columns(table, keep) @ p
            assert _same(first, copy @ p) and _same(rf_filter._columns(squared, keep) @ p, (copy * copy) @ p)
            assert _same(response.mean(-40.0, rf_filter._columns(table, keep)) @ p, response.mean(-40.0, copy) @ p)


def test_joint_reads_as_the_numpy_expressions():
    rng = np.random.default_rng(10)
    rff = rf_filter.RFBearingFilter(CircleGrid(360), RxDirModel("paper", 0.5), 3.0, 0.1)
    for sample in range(100):
        rff._static, rff._walk = rng.normal(size=360) * 20.0, np.log(rng.dirichlet(np.full(360, 0.3)) + 1e-300)
        rff.walk_prior, rff.n = float(rng.uniform(0.01, 0.99)), sample
        stand = rff._static - rff._log_m + math.log(1.0 - rff.walk_prior)  # as the filter computed them in numpy
        walk = rff._walk + math.log(rff.walk_prior)
        joint = np.logaddexp(stand, walk)
        s, w = logsumexp(stand), logsumexp(walk)
        assert _same(rff.log_joint_stand, stand) and _same(rff.log_joint_walk, walk)
        assert _same(rff.log_posterior(), joint - logsumexp(joint))
        assert rff.p_walk == 1.0 / (1.0 + math.exp(min(max(s - w, -50.0), 50.0)))


def _gpucb_values_numpy(b, gpucb):
    """joint.gpucb_values as it was, in numpy."""
    circle = gpucb.circle
    mean, sd, amplitude, offset = b.rf.gain_prediction()
    if amplitude != 0.0:
        value = (np.asarray(mean) - offset) / amplitude + math.sqrt(gpucb.beta) * np.asarray(sd) / abs(amplitude)
    else:
        value = np.ones(circle.size)
    vision = b.vision
    if vision.sees and gpucb.use_mass:
        mass = np.zeros(circle.size)
        if b.post.size:
            w = int(math.floor(vision.tracks.count_limit / circle.step + 1e-9))
            mass = _kernels.mass_grid(np.asarray(vision.tracks.bearing, dtype=float), np.asarray(b.post, dtype=float), circle.step, w,
                                      circle.size)
        unseen = (vision.view_frames < 2.0 * gpucb.frames_per_rf) & (mass < 1.0)
        value = value * np.where(unseen, 1.0, mass)
    return value


def test_summed_gpucb_as_the_numpy_expressions():
    rng = np.random.default_rng(11)
    circle = CircleGrid(360)
    for trial in range(300):
        gpucb = GPUCB(circle, 10, beta=float(rng.uniform(0.5, 9.0)), use_mass=trial % 5 != 0)
        per_tag = []
        for _ in range(3):
            amplitude = 0.0 if trial % 11 == 0 else float(rng.normal()) * 3.0
            prediction = (rng.uniform(size=360), rng.uniform(size=360) * 0.3, amplitude, float(rng.normal()))
            n = int(rng.integers(0, 25))
            tracks = SimpleNamespace(count_limit=0.36, bearing=rng.uniform(-math.pi, math.pi, n))
            vision = SimpleNamespace(sees=trial % 7 != 0, tracks=tracks, view_frames=rng.integers(0, 4, 360) * 10.0)
            rf = SimpleNamespace(gain_prediction=lambda prediction=prediction: prediction)
            per_tag.append(SimpleNamespace(rf=rf, vision=vision, post=rng.dirichlet(np.ones(n)) if n else np.empty(0)))
        weights = rng.dirichlet(np.ones(3))
        weights[rng.uniform(size=3) < 0.2] = 0.0
        want = np.zeros(360)
        for w, b in zip(weights, per_tag):
            want_b = _gpucb_values_numpy(b, gpucb)
            assert _same(gpucb_values(b, gpucb), want_b)
            if w > 0.0:
                lo, hi = float(want_b.min()), float(want_b.max())
                want += w * ((want_b - lo) / (hi - lo) if hi > lo else np.zeros_like(want_b))
        got = SummedGPUCB(gpucb).next_pan(SimpleNamespace(weights=weights, per_tag=per_tag))
        assert got == (float(circle.angles[int(np.argmax(want))]), False)
        total = np.zeros(360)
        for w, b in zip(weights, per_tag):
            if w > 0.0:
                _kernels.add_normalised(gpucb_values(b, gpucb), float(w), total)
        assert _same(total, want)


def test_both_levels_sample_loglik_as_the_numpy_expression():
    rng = np.random.default_rng(12)
    circle = CircleGrid(360)
    rff = rf_filter.RFBearingFilter(circle, RxDirModel("paper", 0.5), 3.0, 0.1)
    for trial in range(300):
        gain = rff.response.gain_over(float(rng.uniform(-math.pi, math.pi)), circle)
        rff.rho = 0.0 if trial % 4 == 0 else float(rng.uniform(0.0, 0.95))
        rff._prev = None if trial % 3 == 0 else (rff.response.gain_over(float(rng.uniform(-3.0, 3.0)), circle), float(rng.normal(-40, 5)))
        z, levels, level_vars = float(rng.normal(-30.0, 8.0)), tuple(rng.normal(-45.0, 6.0, 2)), tuple(rng.uniform(0.01, 9.0, 2))
        got = rff._sample_logliks(z, gain, levels, level_vars)
        slope_term = rff._slope_term(gain)  # the numpy expression, both levels apart
        for level, level_var, ll in zip(levels, level_vars, got):
            assert _same(ll, rff._sample_loglik(z, gain, float(level), float(level_var), slope_term))


def test_refined_argmax_clips_as_numpy():
    rng = np.random.default_rng(13)
    circle = CircleGrid(360)
    for _ in range(3000):
        values = rng.normal(size=360) * 10.0 ** rng.uniform(-3.0, 3.0)
        j = int(np.argmax(values))
        a, b, c = values[(j - 1) % 360], values[j], values[(j + 1) % 360]
        den = a - 2.0 * b + c
        shift = 0.5 * (a - c) / den if den < 0 else 0.0
        assert refined_argmax(circle, values) == float(circle.angles[j] + np.clip(shift, -0.5, 0.5) * (2 * math.pi / 360))


def test_entropy_rows_as_the_numpy_expression():
    rng = np.random.default_rng(14)
    for _ in range(500):
        k, c = int(rng.integers(1, 5)), int(rng.integers(1, 400))
        p = rng.dirichlet(np.full(c, 0.2), k)
        p[rng.uniform(size=p.shape) < 0.1] = 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            want = np.where(p > 0, -p * np.log(p), 0.0).sum(axis=1)
        assert _same(multitag.entropy(p), want)


def test_pod_lookup_finds_the_cell_as_searchsorted():
    rng = np.random.default_rng(15)
    grid = np.sort(rng.uniform(-90.0, -20.0, 60))
    model = PODModel(rssi_grid_dbm=tuple(grid), mean=tuple(rng.uniform(0.0, 1.0, 60)), std=tuple(rng.uniform(0.0, 0.2, 60)),
                     rf_noise_db=3.0, n_train=900, frames_per_rf=10)
    lookup = PODLookup(model, 0.02)
    for rssi in [*rng.uniform(-95.0, -15.0, 3000), *grid]:
        got = lookup(float(rssi))
        if grid[0] < rssi < grid[-1]:  # what __call__ computed with numpy's searchsorted
            i = int(np.searchsorted(lookup.r, rssi)) - 1
            w = (rssi - lookup.r[i]) / (lookup.r[i + 1] - lookup.r[i])
            want = tuple(float(a[i] + w * (a[i + 1] - a[i])) for a in (lookup.mean, lookup.std, lookup.slope))
            assert got == want


def test_filter_reads_in_fewer_passes_as_the_numpy_expressions():
    rng = np.random.default_rng(11)
    for _ in range(300):
        n = int(rng.integers(1, 800))
        values = rng.normal(size=n) * 10.0 ** rng.uniform(-3.0, 3.0)
        weights = rng.random(n) * 10.0 ** rng.uniform(-10.0, 0.0)  # the walking filter's update: prediction x exps
        got = rng.random(n) * 10.0 ** rng.uniform(-290.0, 0.0)
        mine = got.copy()
        c_want = _kernels.times_sum(weights, got)
        want = np.maximum(got / c_want, 1e-300)
        assert _kernels.times_sum_floored(weights, mine, 1e-300) == c_want and _same(mine, want)
        top = values.max()  # logsumexp and the normalised log as rf_filter computed them
        lse = top + math.log(float(np.exp(values - top).sum()))
        out = np.empty(n)
        assert _kernels.log_normalise(values, np.exp(values - top), top, out) == lse and _same(out, values - lse)
        rows = rng.normal(size=(2, n)) * 10.0 ** rng.uniform(-3.0, 3.0)
        assert _kernels.row_totals(rows) == tuple(rows.sum(axis=1).tolist())
        post = np.exp(rng.normal(size=n) * 10.0 ** rng.uniform(-1.0, 2.0))
        for mass in (1e-3, 0.5, 1.0):
            keep, p = np.empty(n, dtype=np.int64), np.empty(n)
            k = _kernels.support(post, mass, keep, p)
            want_keep = np.flatnonzero(post >= mass * post.max())
            assert np.array_equal(keep[:k], want_keep) and _same(p[:k], post[want_keep] / post[want_keep].sum())
        got = values.copy()
        _kernels.less_twice(got, 5.886104031450156, float(top))
        assert _same(got, (values - 5.886104031450156) - top)
        first, second = rng.random(n), rng.random(n)
        second[: n // 3] = first[: n // 3] ** 2  # a spread of 0, and rounding just below it
        sd = np.empty(n)
        _kernels.spread(first, second, sd)
        assert _same(sd, np.sqrt(np.maximum(second - first * first, 0.0)))


def test_fusion_answer_posterior_in_one_pass_as_the_numpy_expressions():
    rng = np.random.default_rng(12)
    for _ in range(400):
        l_missed = rng.normal(size=360) * 10.0 ** rng.uniform(-1.0, 2.5)
        l_tracks = rng.normal(size=int(rng.integers(0, 40))) * 10.0 ** rng.uniform(-1.0, 2.5) + rng.normal() * 20.0
        if l_tracks.size and rng.uniform() < 0.2:
            l_tracks[int(rng.integers(0, l_tracks.size))] = l_tracks.max()  # a tie: the first one
        half = int(rng.integers(1, 6))
        top = max(float(l_missed.max()), float(l_tracks.max()) if l_tracks.size else -np.inf)  # Fusion.answer as it was
        w_missed, w_tracks = np.exp(l_missed - top), np.exp(l_tracks - top)
        total = float(w_missed.sum() + w_tracks.sum())
        post_missed, post = w_missed / total, w_tracks / total
        weights = np.empty(360 + l_tracks.size)
        _kernels.shift_both(l_missed, l_tracks, weights)
        missed_mass, i, post_max = _kernels.posterior_both(np.exp(weights, out=weights), 360, half)
        assert _same(weights[:360], post_missed) and _same(weights[360:], post)
        assert missed_mass == arc_mass(post_missed, int(np.argmax(post_missed)), half)
        if post.size:
            assert i == int(np.argmax(post)) and post_max == float(post.max())


def test_view_counts_as_the_numpy_indexing():
    rng = np.random.default_rng(13)
    circle = CircleGrid(360)
    frames, recent = np.zeros(360), np.zeros(360)
    want_frames, want_recent = frames.copy(), recent.copy()
    for _ in range(300):
        window = circle.window(float(rng.uniform(-4.0, 4.0)), float(rng.uniform(0.05, 1.0)))
        nu = int(rng.integers(0, 12))
        _kernels.count_views(window, float(nu), 0.8824969025845955, frames, recent)
        want_frames[window] += nu  # CameraBelief.update as it was
        want_recent *= 0.8824969025845955
        want_recent[window] += nu
        assert _same(frames, want_frames) and _same(recent, want_recent)
        values, lengths = np.empty(720), np.empty(720, dtype=np.int64)
        r = _kernels.runs_of_both(frames, recent, values, lengths)
        (v1, n1), (v2, n2) = _runs_of(frames), _runs_of(recent)
        assert _same(values[:r], np.concatenate([v1, v2])) and np.array_equal(lengths[:r], np.concatenate([n1, n2]))


def test_pod_evidence_with_its_track_free_terms_once_as_per_track():
    rng = np.random.default_rng(14)

    @njit
    def per_track(detections, frames, alpha, beta, alpha0, beta0, outlier, out):  # add_pod_evidence as it was
        for i in range(out.size):
            out[i] += _kernels.pod_evidence(detections[i], frames[i], alpha, beta, alpha0, beta0, outlier)

    for _ in range(300):
        n = int(rng.integers(0, 40))
        frames = np.floor(rng.uniform(-2.0, 60.0, n))
        detections = np.floor(rng.uniform(-1.0, 1.1, n) * np.maximum(frames, 0.0))
        alpha, beta = (float(v) for v in rng.uniform(0.05, 30.0, 2))
        alpha0, beta0 = (1.0, 1.0) if rng.uniform() < 0.5 else tuple(float(v) for v in rng.uniform(0.3, 5.0, 2))
        outlier = float(rng.choice([0.0, 0.2, 0.5]))
        start = rng.normal(size=n)
        got, want = start.copy(), start.copy()
        _kernels.add_pod_evidence(got, detections, frames, alpha, beta, alpha0, beta0, outlier)
        per_track(detections, frames, alpha, beta, alpha0, beta0, outlier, want)
        assert _same(got, want)


def _pan_weights_numpy(posteriors, decided, rule="entropy", where_missed=None):
    """``multitag.pan_weights`` (with ``which_person_entropy``) as numpy computed it before ``_kernels.pan_shares``
    and ``_kernels.which_person_entropies``."""
    p = np.asarray(posteriors, dtype=float)
    h = multitag.entropy(p)
    if where_missed is not None:
        h = h + p[:, -1] * multitag.entropy(where_missed)
    open_ = ~np.asarray(decided, dtype=bool)
    out = np.zeros_like(h)
    if not open_.any():
        return h, out
    if rule == "neediest":
        out[int(np.argmax(np.where(open_, h, -np.inf)))] = 1.0
        return h, out
    weights = np.where(open_, h, 0.0)
    if weights.sum() <= 0.0:
        weights = open_.astype(float)
    return h, weights / weights.sum()


def test_pan_weights_and_which_person_entropy_as_the_numpy_expressions():
    rng = np.random.default_rng(31)
    for trial in range(3000):
        k, m, g = int(rng.integers(1, 12)), int(rng.integers(0, 40)), int(rng.integers(1, 400))
        post = rng.dirichlet(np.full(m + 1, 0.3), k)
        where = rng.dirichlet(np.full(g, 0.2), k)
        post[rng.uniform(size=post.shape) < 0.1] = 0.0
        where[rng.uniform(size=where.shape) < 0.1] = 0.0
        if trial % 7 == 0:  # certain tags: entropies 0, the weights shared equally
            post = np.zeros((k, m + 1))
            post[:, -1 if trial % 2 else 0] = 1.0
            where = np.zeros((k, g))
            where[:, 0] = 1.0
        if trial % 11 == 0:  # ties and NaN for argmax
            post[:] = post[0]
            if trial % 3 == 0:
                post[int(rng.integers(0, k)), -1] = np.nan  # with where_missed: that tag's entropy NaN
        decided = rng.uniform(size=k) < (0.0 if trial % 5 == 0 else 1.0 if trial % 13 == 0 else 0.4)
        for rule in ("entropy", "neediest"):
            for w in (None, where):
                with np.errstate(invalid="ignore"):
                    want_h, want = _pan_weights_numpy(post, list(decided), rule, w)
                    assert _same(multitag.which_person_entropy(post, w), want_h)
                    assert _same(multitag.pan_weights(post, list(decided), rule, w), want)
