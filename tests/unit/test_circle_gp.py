"""GP over the pan angle on the circle, with an explicit lobe basis (controller.circle_gp)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, ExpSineSquared

from ra2vipas.services.controller.circle_gp import LobeGP, circular_kernel
from ra2vipas.services.controller.policy import ControllerSettings
from ra2vipas.services.sensors import physics
from tests.conftest import angle_error, make_platform, polar_positions, small_scenario, sweep_pans

# -- kernel --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("length_scale, signal_var", [(0.3, 1.0), (1.0, 2.5), (2.0, 9.0)])
def test_circular_kernel_is_exp_sine_squared_with_period_two_pi(length_scale, signal_var):
    RNG = np.random.default_rng(0)
    a = RNG.uniform(-4, 4, 15)
    b = RNG.uniform(-4, 4, 9)
    ref = ConstantKernel(signal_var) * ExpSineSquared(length_scale=length_scale, periodicity=2 * math.pi)
    got = circular_kernel(a, b, length_scale, signal_var)
    np.testing.assert_allclose(got, ref(a[:, None], b[:, None]), rtol=1e-12, atol=1e-15)


def test_circular_kernel_is_chordal_squared_exponential():
    RNG = np.random.default_rng(1)
    a, b = RNG.uniform(-math.pi, math.pi, (2, 20))
    chord2 = np.abs(np.exp(1j * a)[:, None] - np.exp(1j * b)[None, :]) ** 2
    np.testing.assert_allclose(circular_kernel(a, b, 0.7), np.exp(-chord2 / (2 * 0.7**2)), rtol=1e-12)


@pytest.mark.parametrize("e", [1e-6, 1e-3, 0.05, 0.4])
def test_circular_kernel_treats_minus_pi_and_pi_as_neighbours(e):
    k_wrap = circular_kernel(np.array([-math.pi + e]), np.array([math.pi - e]), 0.5)[0, 0]
    k_plain = circular_kernel(np.array([0.0]), np.array([2 * e]), 0.5)[0, 0]
    assert k_wrap == pytest.approx(k_plain, rel=1e-12)
    assert circular_kernel(np.array([-math.pi]), np.array([math.pi]), 0.5)[0, 0] == pytest.approx(1.0)


def test_circular_kernel_is_periodic_symmetric_and_psd():
    RNG = np.random.default_rng(1)
    x = RNG.uniform(-math.pi, math.pi, 40)
    K = circular_kernel(x, x, 0.5, 3.0)
    np.testing.assert_allclose(K, K.T)
    np.testing.assert_allclose(np.diag(K), 3.0)
    np.testing.assert_allclose(circular_kernel(x + 2 * math.pi, x - 4 * math.pi, 0.5, 3.0), K, atol=1e-12)
    assert np.linalg.eigvalsh(K).min() > -1e-9
    # decreasing in the angular distance up to pi
    d = np.linspace(0, math.pi, 50)
    assert np.all(np.diff(circular_kernel(np.zeros(1), d, 0.5)[0]) < 0)


# -- incremental GP == batch GP --------------------------------------------------------------------------

NOISE, WIDTH, RES_L, RES_VAR = 4.0, 1.0, 0.5, 9.0


def _filled(x, z, sign=-1, grid_points=90, capacity=None, rho=0.0):
    grid = np.linspace(-math.pi, math.pi, grid_points, endpoint=False)
    gp = LobeGP(grid, NOISE, WIDTH, sign, RES_L, RES_VAR, capacity=capacity or len(x) + 5, noise_correlation=rho)
    for s, v in zip(x, z):
        gp.add(float(s), float(v))
    return gp


def _batch_gls(x, z, grid, rho=0.0):
    """For each centre: GLS (A, c) with basis [h(x - gamma), 1] and q = (z - B beta)' K^-1 (z - B beta),
    the noise AR(1) in sample order (Cov = NOISE rho^|i - j|)."""
    lag = np.abs(np.subtract.outer(np.arange(x.size), np.arange(x.size)))
    K = circular_kernel(x, x, RES_L, RES_VAR) + NOISE * rho ** lag
    Ki = np.linalg.inv(K)
    H = circular_kernel(x, grid, WIDTH)
    out = []
    for j in range(grid.size):
        B = np.column_stack([H[:, j], np.ones(x.size)])
        beta = np.linalg.solve(B.T @ Ki @ B, B.T @ Ki @ z)
        r = z - B @ beta
        out.append((beta[0], beta[1], r @ Ki @ r))
    A, c, q = map(np.array, zip(*out))
    one = np.ones(x.size)
    c_flat = (one @ Ki @ z) / (one @ Ki @ one)
    q_flat = (z - c_flat) @ Ki @ (z - c_flat)
    return A, c, q, c_flat, q_flat


@pytest.mark.parametrize("sign", [-1, 1])
def test_lobe_fit_equals_batch_gls(sign):
    RNG = np.random.default_rng(1)
    x = RNG.uniform(-math.pi, math.pi, 25)
    z = -40.0 + 8.0 * np.cos(x - 1.0) + RNG.normal(0, 2, x.size)
    gp = _filled(x, z, sign)
    loglik, A, c = gp.lobe_fit()
    A_ref, c_ref, q_ref, c_flat, q_flat = _batch_gls(x, z, gp.grid)
    right = A_ref * sign > 0
    assert right.any() and (~right).any()
    np.testing.assert_allclose(A[right], A_ref[right], rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(c[right], c_ref[right], rtol=1e-6)
    np.testing.assert_allclose(loglik[right], -0.5 * q_ref[right], rtol=1e-6)
    # a centre whose best amplitude has the wrong sign scores as "no lobe"
    np.testing.assert_array_equal(A[~right], 0.0)
    np.testing.assert_allclose(c[~right], c_flat, rtol=1e-8)
    np.testing.assert_allclose(loglik[~right], -0.5 * q_flat, rtol=1e-8)
    # adding a basis function can only explain more
    assert np.all(loglik >= -0.5 * q_flat - 1e-8)


def test_lobe_fit_with_ar1_noise_equals_batch_gls():
    """Fading correlated in time: the incremental fit is the GLS fit under the AR(1) noise
    covariance, and its evidence differs from the white-noise fit's."""
    RNG = np.random.default_rng(2)
    x = RNG.uniform(-math.pi, math.pi, 30)
    e = np.zeros(x.size)
    for i in range(1, x.size):
        e[i] = 0.8 * e[i - 1] + RNG.normal(0, 2 * math.sqrt(1 - 0.64))
    z = -40.0 - 8.0 * circular_kernel(x, np.array([1.0]), WIDTH)[:, 0] + e
    gp = _filled(x, z, -1, rho=0.8)
    loglik, A, c = gp.lobe_fit()
    A_ref, c_ref, q_ref, _, _ = _batch_gls(x, z, gp.grid, rho=0.8)
    right = A_ref < 0
    np.testing.assert_allclose(A[right], A_ref[right], rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(loglik[right], -0.5 * q_ref[right], rtol=1e-6)
    white = _filled(x, z, -1).lobe_fit()[0]
    assert np.max(np.abs(white - loglik)) > 1.0


@pytest.mark.parametrize("rho", [0.0, 0.7])
def test_extend_is_add_one_by_one_in_one_pass(rho):
    """``extend`` into an empty GP (the controller's lobe check, fitted once at the episode's end)
    is the fit of ``add`` sample by sample, up to rounding; samples added afterwards go on as
    usual."""
    RNG = np.random.default_rng(4)
    grid = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    x = np.concatenate([grid[RNG.integers(0, 90, 30)], RNG.uniform(-math.pi, math.pi, 10)])  # pans on and off the grid
    z = -40.0 + 8.0 * np.cos(x - 1.0) + RNG.normal(0, 2, x.size)
    one_by_one = _filled(x, z, -1, capacity=45, rho=rho)
    at_once = LobeGP(grid, NOISE, WIDTH, -1, RES_L, RES_VAR, capacity=45, noise_correlation=rho)
    at_once.extend(x, z)
    assert at_once.n_ == one_by_one.n_ == x.size
    for got, want in zip(at_once.lobe_fit(), one_by_one.lobe_fit()):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    for s, v in ((0.3, -41.0), (-2.0, -38.5)):
        at_once.add(s, v)
        one_by_one.add(s, v)
    for got, want in zip(at_once.lobe_fit(), one_by_one.lobe_fit()):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    mean, sd = at_once.posterior(10, -5.0, -40.0)
    np.testing.assert_allclose(mean, one_by_one.posterior(10, -5.0, -40.0)[0], rtol=1e-9)
    np.testing.assert_allclose(sd, one_by_one.posterior(10, -5.0, -40.0)[1], rtol=1e-9)


def test_changing_the_noise_correlation_refits_every_sample():
    RNG = np.random.default_rng(3)
    x = RNG.uniform(-math.pi, math.pi, 15)
    z = RNG.normal(-45, 3, 15)
    gp = _filled(x, z, -1, capacity=20)
    gp.set_noise_correlation(0.6)
    gp.add(0.3, -44.0)
    fresh = _filled(np.append(x, 0.3), np.append(z, -44.0), -1, rho=0.6)
    for got, want in zip(gp.lobe_fit(), fresh.lobe_fit()):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-10)


def test_posterior_equals_sklearn_gpr():
    RNG = np.random.default_rng(1)
    x = RNG.uniform(-math.pi, math.pi, 30)
    z = -40.0 + 6.0 * circular_kernel(x, np.array([2.0]), WIDTH)[:, 0] + RNG.normal(0, 2, x.size)
    gp = _filled(x, z, sign=1)
    loglik, A, c = gp.lobe_fit()
    j = int(np.argmax(loglik))
    mean, sd = gp.posterior(j, float(A[j]), float(c[j]))
    lobe = lambda s: c[j] + A[j] * circular_kernel(s, gp.grid[j : j + 1], WIDTH)[:, 0]  # noqa: E731
    gpr = GaussianProcessRegressor(
        kernel=ConstantKernel(RES_VAR, "fixed") * ExpSineSquared(RES_L, 2 * math.pi, "fixed", "fixed"),
        alpha=NOISE, optimizer=None,
    )
    gpr.fit(x[:, None], z - lobe(x))
    mu, std = gpr.predict(gp.grid[:, None], return_std=True)
    np.testing.assert_allclose(mean, mu + lobe(gp.grid), rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(sd, np.sqrt(std**2 + 1e-12), rtol=1e-6, atol=1e-6)


def test_incremental_adds_match_a_fresh_fit_at_every_size():
    RNG = np.random.default_rng(1)
    x = RNG.uniform(-math.pi, math.pi, 12)
    z = RNG.normal(-45, 3, 12)
    gp = _filled(x[:0], z[:0], sign=-1, grid_points=36, capacity=12)
    for n in range(12):
        gp.add(float(x[n]), float(z[n]))
        fresh = _filled(x[: n + 1], z[: n + 1], sign=-1, grid_points=36)
        for got, want in zip(gp.lobe_fit(), fresh.lobe_fit()):
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def test_empty_and_full():
    grid = np.linspace(-math.pi, math.pi, 20, endpoint=False)
    gp = LobeGP(grid, NOISE, WIDTH, 1, RES_L, RES_VAR, capacity=2)
    for arr in gp.lobe_fit():
        np.testing.assert_array_equal(arr, 0.0)
    mean, sd = gp.posterior(0, 0.0, -40.0)
    np.testing.assert_allclose(mean, -40.0)
    np.testing.assert_allclose(sd, math.sqrt(RES_VAR + 1e-12))
    gp.add(0.0, -40.0)
    gp.add(1.0, -41.0)
    with pytest.raises(ValueError):
        gp.add(2.0, -42.0)


def test_posterior_variance_shrinks_where_sampled():
    gp = _filled(np.full(5, 0.5), np.full(5, -40.0), grid_points=72)
    _, sd = gp.posterior(0, 0.0, -40.0)
    near = int(np.argmin(np.abs(gp.grid - 0.5)))
    far = int(np.argmin(np.abs(physics.wrap(gp.grid - 0.5 - math.pi))))
    assert sd[near] < 0.5 * sd[far]
    assert sd[far] == pytest.approx(math.sqrt(RES_VAR), rel=0.01)


# -- the profile likelihood finds the Tx ---------------------------------------------------------------------


def _lobe_peak(model: str, tx_deg: float, sign: int, noise_db: float = 0.2, n_pans: int = 36, seed: int = 0):
    sc = small_scenario(rf_noise_db=noise_db, antenna_model=model, steps=n_pans)
    layout = polar_positions([2.0, 3.5, 4.5], [tx_deg, tx_deg + 100.0, tx_deg - 140.0])
    platform = make_platform(sc, layout, tx_index=0, seed=seed)
    cfg = ControllerSettings()
    grid = np.linspace(-math.pi, math.pi, cfg.grid_points, endpoint=False)
    gp = LobeGP(grid, max(noise_db, 0.1) ** 2, cfg.lobe_width_rad, sign,
                cfg.residual_length_scale_rad, cfg.residual_std_db**2, n_pans)
    for t, pan in enumerate(sweep_pans(n_pans, start_rad=0.1)):
        gp.add(pan, platform.sense(t, pan).rf.dir_rssi_dbm)
    loglik, A, _ = gp.lobe_fit()
    j = int(np.argmax(loglik))
    return grid[j], A[j], platform.truth.tx_bearing_rad


@pytest.mark.parametrize("model, sign", [("paper", -1), ("db-gain", 1)])
@pytest.mark.parametrize("tx_deg", [0.0, 37.0, -123.0, 179.0, -179.5])
def test_profile_likelihood_peaks_at_the_tx_bearing(model, sign, tx_deg):
    peak, A, tx = _lobe_peak(model, tx_deg, sign)
    assert angle_error(peak, tx) < math.radians(3.0)
    assert A * sign > 0


@pytest.mark.parametrize("model, sign", [("paper", -1), ("db-gain", 1)])
def test_profile_likelihood_peaks_at_the_tx_with_paper_noise(model, sign):
    """Table I noise (3 dB), 72 samples: still within a few degrees."""
    errors = []
    for s, deg in enumerate([-150, -60, 20, 100, 170]):
        peak, _, tx = _lobe_peak(model, deg, sign, noise_db=3.0, n_pans=72, seed=s)
        errors.append(angle_error(peak, tx))
    assert np.median(errors) < math.radians(4.0)
    assert max(errors) < math.radians(8.0)


def test_wrong_lobe_sign_does_not_find_the_paper_tx():
    """In the paper's model z = g rho is *lowest* (most negative) when aligned: a lobe of the
    wrong sign cannot sit on the Tx, so the antenna convention matters."""
    peak, A, tx = _lobe_peak("paper", 60.0, +1)
    assert A == 0.0 or angle_error(peak, tx) > math.radians(30.0)
