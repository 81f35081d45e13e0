"""Self-supervised learning of the camera's probability of detection p_D(r) as a function of
the iso RSSI (paper Sec. III-A, eqs. 18-23), with the two effects the paper's footnote names
and then ignores:

* heteroscedastic labels: the empirical POD p~_j = k_j / nu has variance p(1 - p)/nu
  (eq. 21);
* noisy inputs: z_j = r_j + v_j with v_j ~ N(0, sigma_RF^2) (eq. 8), which, regressed
  naively, blurs the steep far edge of p_D and caps R^2 well below the paper's claim.

The learner never sees ranges or true RSSI; it uses the training stream's own structure:

1. **Latent RSSI smoother.** During training the Tx walks slowly (Table I), so r_j is a
   random walk. A local-level model with state-dependent diffusion q(r) = exp(a + b (r - r_c))
   and observation noise R is fitted by maximum likelihood (Kalman filter), then a
   grid forward-backward pass gives the posterior p(r_j | z_1:n) of every latent input.
2. **Deconvolution.** p_D on the RSSI grid gets a GP prior (Matern 5/2) on the warped axis
   u = exp(-b r / 2), in which the walk diffuses homogeneously (for a log-distance channel u
   is proportional to range). Each label observes the *average* of p_D under its input
   posterior, y_j = sum_g P_jg p_D(r_g) + e_j, a linear functional, so the GP posterior is
   closed-form (Rasmussen & Williams, Sec. 9.8); hyperparameters maximise its marginal
   likelihood. The per-label noise is p(1-p)/nu plus the input-induced variance
   Var[p_D(r_j)] (the McHutchon-Rasmussen correction, ref. [mchutchon2011gaussian]).
3. **Label-informed refinement.** A few EM passes in which the smoother also uses the
   detection counts as emissions, Binomial(k_j; nu, p_D(r)), sharpen the input posteriors
   where p_D is steep; the GP hyperparameters stay fixed from step 2.

**Fading.** When the receiver's noise is correlated in time (AR(1), n_j = phi n_{j-1} + v_j),
a white-noise smoother takes its slow swings for the walk and blurs p_D as badly as ignoring
the input noise would. The walk is then fitted with the noise as a second state (a two-state
Kalman filter, ``fit_fading_walk``), and since z_j = r_j + n_j fixes n_j once r_j is known,
the posterior of the inputs is still a chain over r alone, with the pairwise potential
q-walk(r_j | r_{j-1}) N((z_j - r_j) - phi (z_{j-1} - r_{j-1}); 0, R (1 - phi^2))
(``chain_posterior``). With phi below ``min_fading`` the plain model is used: a white
receiver's fit is exactly what it was.

**Shadowing.** Where the channel has shadowing, the RSSI the POD is a function of is the shadowed
one, r = g(d) + S (``world.TrainingTruth``: p*(r) = E[p_D(d) | r]), and a Tx walking through the
shadowing field makes S swing in time as the receiver's fading does (the training walk crosses its
2 m decorrelation in a few samples: S moves ~4 dB^2 per sample, the 0.5 s fading ~3). The stream z
cannot tell the two apart: on the ``dynamic`` world the fading fit takes the swings for receiver
noise (seeds 2-4: R 12.5-14.5 dB^2 against the receiver's 9, a walk 8-70 x slower than r moves),
and a model with both (walk + stationary S + AR(1) noise) gives, at its maximum likelihood, all of
them to the noise on some seeds and all to S on others. The fading fit's deconvolution then removes
the shadowing with the noise: its input posteriors are 1.4-2.2 x too narrow about a smoothed r, and
the GP fits their errors as wiggles (length scale at its bound; R^2 -4 to -8 on seeds 2-4). So when the campaign
says its channel shadows (``LearnerSettings.shadowing``, from the public sigma_S, as the range cue
reads it: ``for_scenario``), the swings stay in the latent RSSI: the white walk is fitted and only
its white noise is deconvolved; the model still reports the fading fit's noise (R, phi), what the
level the controller reads swings by. Without shadowing nothing changes.

The output is a compact ``PODModel``: mean and standard deviation of p_D on an RSSI grid.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from ra2vipas.services.learner.trained import predict, r2_score  # noqa: F401  (re-exported: scoring lives there)
from ra2vipas.services.protocol.measurements import TrainingSample
from ra2vipas.services.protocol.pod import PODModel


# SciPy's optimiser and scikit-learn's GP (with SciPy's statistics, and pandas where installed, behind
# them: ~2 s of CPU) are imported by the fits that use them, not with this module: the orchestrator, the
# CLI and ``simulate`` import it for ``predict``/``r2_score``, and a learner with its model cached never fits.
def minimize(*args, **kwargs):
    """``scipy.optimize.minimize``, imported on first use."""
    from scipy.optimize import minimize as scipy_minimize

    return scipy_minimize(*args, **kwargs)


def _matern_kernel(length_scale: float, amplitude: float):
    """amplitude * Matern(nu=5/2), scikit-learn's kernel with both parameters fixed."""
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern

    return ConstantKernel(amplitude, "fixed") * Matern(length_scale=length_scale, length_scale_bounds="fixed", nu=2.5)


@dataclass(frozen=True)
class LearnerSettings:
    """Knobs of the POD learner; the defaults are what the paper campaign uses."""

    grid_points: int = 80
    grid_margin_db: float = 3.0
    em_iterations: int = 10
    restarts: int = 2
    min_rf_noise_db: float = 0.1
    min_fading: float = 0.1  # phi below which the receiver noise is taken as white
    channel_offsets: bool = True  # packets with channels: fit each channel's offset with the walk
    shadowing: bool = False  # the campaign's channel has shadowing (sigma_S > 0): see ``fit_pod`` and ``for_scenario``

    @classmethod
    def for_scenario(cls, scenario, base: "LearnerSettings | None" = None) -> "LearnerSettings":
        """``base`` (default: the defaults) with ``shadowing`` set from the campaign's public propagation
        model: whether its ``shadowing_db`` (sigma_S, what the operator configured, as the range cue reads
        it, ``RangeModel.from_scenario``) is positive. The training stream cannot say it (``fit_pod``)."""
        return replace(base or cls(), shadowing=scenario.shadowing_db > 0.0)


class TrainingDataError(ValueError):
    """The training stream is too thin to fit p_D from (too few samples, or on BLE too few
    advertisements: a short training episode of a sparse beacon): one line saying what it had."""


MIN_TRAINING_SAMPLES = 10
MIN_TRAINING_ADVERTS = 10


@dataclass(frozen=True)
class LearnedPOD:
    """What ``fit_pod`` returns: the model and how long fitting took."""

    model: PODModel
    train_seconds: float
    diffusion: tuple[float, float, float]  # (a, b, R) of the latent RSSI walk
    fading: float = 0.0  # phi of the receiver noise's AR(1) (0: white)
    channel_offsets: dict[int, float] | None = None  # packets with channels: each channel's estimated offset [dB], centred


def detection_counts(samples: list[TrainingSample]) -> tuple[np.ndarray, np.ndarray, int]:
    """(z_j, k_j, nu): iso RSSI, number of frames with a box of the Tx, frames per sample.

    During training the camera looks at the Tx, so its boxes gather around the optical axis.
    A detector that also reports false boxes (clutter) scatters them over the field of view: a
    false box is not a detection of the Tx. ``training_clutter`` finds that out from the boxes
    themselves; where there is clutter, only boxes inside the Tx's gate count, and the chance
    that clutter alone puts a box there is corrected for by the fit (``fit_pod``).
    """
    if not samples:
        raise TrainingDataError("the training stream carries no samples")
    nu = len(samples[0].frames)
    if nu == 0 or any(len(s.frames) != nu for s in samples):
        raise ValueError("every training sample must carry the same, non-zero number of frames")
    if any(s.iso_rssi_dbm is None for s in samples):  # protocol 1.3 packets: z_j is the mean of sample j's (NaN: none)
        z = packet_statistics(samples)[0]
    else:
        z = np.fromiter((s.iso_rssi_dbm for s in samples), dtype=float, count=len(samples))
    gate, _ = training_clutter(samples)
    if gate is None:
        k = np.fromiter((sum(1 for f in s.frames if f.box_bearings_rad) for s in samples), dtype=float, count=len(samples))
    else:
        k = np.fromiter((sum(1 for f in s.frames if any(abs(b) <= gate for b in f.box_bearings_rad)) for s in samples),
                        dtype=float, count=len(samples))
    return z, k, nu


def packet_statistics(samples: list[TrainingSample], channel_offsets: dict[int, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(zbar_j, n_j): the mean iso RSSI of the n_j advertisements of each sample (NaN when it has
    none) and their number. Under Gaussian packet noise of variance R, sample j's packets weigh
    on its latent RSSI r_j exactly as one value zbar_j of variance R / n_j would (the sufficient
    statistic: nothing is averaged away), and a sample with none carries no RF evidence. Each
    packet first loses its advertising channel's offset (``channel_offsets``; 0 for a packet
    whose channel is not reported)."""
    off = channel_offsets or {}
    n = np.fromiter((len(s.rssi_dbm("iso")) for s in samples), dtype=float, count=len(samples))
    sums = np.fromiter((sum(a.rssi_dbm - off.get(a.channel, 0.0) for a in s.advertisements_of("iso")) for s in samples),
                       dtype=float, count=len(samples))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, sums / np.maximum(n, 1.0), np.nan), n


def training_clutter(samples: list[TrainingSample]) -> tuple[float | None, float]:
    """(gate, q): the half-width [rad] around the optical axis inside which a box counts as the
    Tx's, and the probability that clutter alone puts a box inside it in a frame; (None, 0)
    for a clean detector.

    The Tx's boxes spread like a Gaussian around the axis (the detector's bearing noise) and
    clutter spreads uniformly over the field of view (whose half-width is taken as the widest
    box seen): a two-component mixture fitted by EM to the boxes' |bearing|. Where the clutter
    component holds more than 0.01 boxes per frame (and boxes beyond 6 sigmas are seen), its
    density gives q for the 4-sigma gate.
    """
    boxes = np.fromiter((b for s in samples for f in s.frames for b in f.box_bearings_rad), dtype=float)
    frames = sum(len(s.frames) for s in samples)
    if boxes.size < 20 or frames == 0:
        return None, 0.0
    a = np.abs(boxes)
    half_fov = max(float(a.max()), 1e-6)
    # |bearing| as a mixture: the Tx's half-normal of scale sigma (weight w) and clutter uniform
    # on [0, half_fov]; EM from the inner boxes' spread
    sigma = max(float(np.sqrt(np.mean(a[a <= np.quantile(a, 0.5)] ** 2))) * 2.0, 1e-5)
    w = 0.9
    for _ in range(50):
        tx = w * np.sqrt(2.0 / math.pi) / sigma * np.exp(-0.5 * (a / sigma) ** 2)
        resp = tx / (tx + (1.0 - w) / half_fov)
        w = min(max(float(resp.mean()), 1e-6), 1.0 - 1e-9)
        sigma = max(float(np.sqrt(np.sum(resp * a * a) / max(resp.sum(), 1e-12))), 1e-5)
    false_per_frame = (1.0 - w) * boxes.size / frames
    if false_per_frame <= 0.01 or (a > 6.0 * sigma).sum() / frames <= 0.01:
        return None, 0.0
    density = false_per_frame / (2.0 * half_fov)  # false boxes per frame per radian
    gate = 4.0 * sigma
    return gate, float(min(1.0 - math.exp(-density * 2.0 * gate), 0.5))


# -- 1. latent RSSI walk ----------------------------------------------------------------------

def _kalman_loglik(z: np.ndarray, a: float, b: float, R: float, rc: float) -> float:
    """Log-likelihood of the local-level model with diffusion q(x) = exp(a + b (x - rc))."""
    x = float(z[0])
    p = R * 10.0
    ll = 0.0
    for zt in z:
        S = p + R
        e = zt - x
        ll -= 0.5 * (math.log(2.0 * math.pi * S) + e * e / S)
        K = p / S
        x += K * e
        p = (1.0 - K) * p + math.exp(min(a + b * (x - rc), 50.0))
    return ll


@njit(cache=True)
def _kalman_loglik_packets(zbar, n, a, b, R, rc):
    """``_kalman_loglik`` over samples that carry 0..n packets: sample j observes r_j through
    ``zbar[j]`` with variance R / n_j, and a sample with none only diffuses the state."""
    x = 0.0
    p = -1.0  # no observation yet
    ll = 0.0
    for t in range(zbar.size):
        if p >= 0.0:
            p += math.exp(min(a + b * (x - rc), 50.0))
        if n[t] <= 0:
            continue
        r = R / n[t]
        if p < 0.0:  # the first packet starts the state, as z_0 does in the plain filter
            x = zbar[t]
            p = R * 10.0
        S = p + r
        e = zbar[t] - x
        ll -= 0.5 * (math.log(2.0 * math.pi * S) + e * e / S)
        K = p / S
        x += K * e
        p = (1.0 - K) * p
    return ll


def fit_diffusion_packets(zbar: np.ndarray, n: np.ndarray, min_noise_var: float) -> tuple[float, float, float, float]:
    """``fit_diffusion`` for samples of 0..n packets (``packet_statistics``): maximum-likelihood
    (a, b, R) of the walk, R now the variance of one packet, and r_c."""
    seen = n > 0
    rc = float(np.sum(zbar[seen] * n[seen]) / np.sum(n[seen]))
    zs = zbar[seen]
    x0 = np.array([math.log(0.5), 0.1, math.log(max(float(np.var(np.diff(zs))) / 2.0 if zs.size > 2 else 1.0, min_noise_var))])
    simplex = np.array([x0, x0 + [1.0, 0, 0], x0 + [0, 0.15, 0], x0 + [0, 0, 0.5]])
    z0 = np.where(seen, zbar, 0.0)

    def nll(th: np.ndarray) -> float:
        return -_kalman_loglik_packets(z0, n, th[0], float(np.clip(th[1], -1.0, 1.0)), max(math.exp(th[2]), min_noise_var), rc)

    res = minimize(nll, x0, method="Nelder-Mead", options={"xatol": 1e-2, "fatol": 1e-2, "maxiter": 300, "initial_simplex": simplex})
    a, b, lr = res.x
    return float(a), float(np.clip(b, -1.0, 1.0)), max(math.exp(lr), min_noise_var), rc


def fit_diffusion(z: np.ndarray, min_noise_var: float) -> tuple[float, float, float, float]:
    """Maximum-likelihood (a, b, R) of the latent RSSI walk and the centring value r_c."""
    rc = float(np.mean(z))
    x0 = np.array([math.log(0.5), 0.1, math.log(max(float(np.var(np.diff(z))) / 2.0, min_noise_var))])
    simplex = np.array([x0, x0 + [1.0, 0, 0], x0 + [0, 0.15, 0], x0 + [0, 0, 0.5]])

    def nll(th: np.ndarray) -> float:
        return -_kalman_loglik(z, th[0], float(np.clip(th[1], -1.0, 1.0)), max(math.exp(th[2]), min_noise_var), rc)

    res = minimize(nll, x0, method="Nelder-Mead", options={"xatol": 1e-2, "fatol": 1e-2, "maxiter": 300, "initial_simplex": simplex})
    a, b, lr = res.x
    return float(a), float(np.clip(b, -1.0, 1.0)), max(math.exp(lr), min_noise_var), rc


def _transition(grid: np.ndarray, a: float, b: float, rc: float) -> np.ndarray:
    q = np.exp(np.minimum(a + b * (grid - rc), 50.0))
    T = np.exp(-0.5 * (grid[None, :] - grid[:, None]) ** 2 / q[:, None])
    return T / T.sum(axis=1, keepdims=True)


def forward_backward(emission: np.ndarray, transition: np.ndarray) -> np.ndarray:
    """Posterior marginals p(r_j | all data) of a grid HMM; ``emission`` is (n, G)."""
    n, G = emission.shape
    alpha = np.empty((n, G))
    c = np.empty(n)
    a = emission[0] / G
    c[0] = a.sum()
    alpha[0] = a / c[0]
    for t in range(1, n):
        a = (alpha[t - 1] @ transition) * emission[t]
        c[t] = max(a.sum(), 1e-300)
        alpha[t] = a / c[t]
    post = np.empty((n, G))
    post[-1] = alpha[-1]
    beta = np.ones(G)
    for t in range(n - 2, -1, -1):
        beta = transition @ (emission[t + 1] * beta) / c[t + 1]
        post[t] = alpha[t] * beta
    post /= post.sum(axis=1, keepdims=True)
    return post


# -- 1b. the same with AR(1) receiver noise (fading) ---------------------------------------------

@njit(cache=True)
def _kalman_ar1_loglik(z, a, b, R, phi, rc):
    """Log-likelihood of the walk r_j (diffusion exp(a + b (r - rc))) observed through AR(1)
    noise n_j = phi n_{j-1} + v_j of stationary variance R: a Kalman filter on (r, n) with
    z_j = r_j + n_j. phi = 0 is ``_kalman_loglik`` (same start: r_0 ~ N(z_0, 10 R))."""
    x0 = z[0]
    x1 = 0.0
    p00 = 10.0 * R
    p01 = 0.0
    p11 = R
    ll = 0.0
    v = R * (1.0 - phi * phi)
    for t in range(z.size):
        if t > 0:  # predict
            q = math.exp(min(a + b * (x0 - rc), 50.0))
            x1 = phi * x1
            p00 = p00 + q
            p01 = phi * p01
            p11 = phi * phi * p11 + v
        S = p00 + 2.0 * p01 + p11 + 1e-9
        e = z[t] - x0 - x1
        ll -= 0.5 * (math.log(2.0 * math.pi * S) + e * e / S)
        k0 = (p00 + p01) / S
        k1 = (p01 + p11) / S
        x0 += k0 * e
        x1 += k1 * e
        n00 = p00 - k0 * (p00 + p01)
        n01 = p01 - k0 * (p01 + p11)
        n11 = p11 - k1 * (p01 + p11)
        p00, p01, p11 = n00, n01, n11
    return ll


def fit_fading_walk(z: np.ndarray, min_noise_var: float) -> tuple[float, float, float, float, float]:
    """Maximum-likelihood (a, b, R, phi) of the walk seen through AR(1) noise, and r_c."""
    rc = float(np.mean(z))
    a0, b0, R0, _ = fit_diffusion(z, min_noise_var)

    def unpack(th):
        # b >= 0: a walk of steady steps in range moves the RSSI more where it is stronger (near),
        # q ~ 10^((r - kappa) / (5 n)); with correlated noise a slow walk is otherwise hard to tell
        # from the noise's swings and the fit can fall into b < 0
        return th[0], float(np.clip(th[1], 0.0, 1.0)), max(math.exp(th[2]), min_noise_var), 0.97 * math.tanh(th[3])

    def nll(th: np.ndarray) -> float:
        a, b, R, phi = unpack(th)
        return -_kalman_ar1_loglik(z, a, b, R, phi, rc)

    # two starts: near the white fit, and a slow walk under strongly correlated noise (a walk
    # fast enough to swallow the noise is a local optimum the first start can fall into)
    best = None
    b0 = min(max(b0, 0.05), 1.0)
    for x0 in (np.array([a0 - 1.0, b0, math.log(R0 * 1.5), 0.0]),
               np.array([math.log(max(float(np.var(np.diff(z))), 1e-3) / 20.0), b0, math.log(max(float(np.var(z)) / 3.0, min_noise_var)),
                         math.atanh(0.8 / 0.97)])):
        simplex = np.array([x0, x0 + [1.0, 0, 0, 0], x0 + [0, 0.15, 0, 0], x0 + [0, 0, 0.5, 0], x0 + [0, 0, 0, 0.5]])
        res = minimize(nll, x0, method="Nelder-Mead", options={"xatol": 1e-2, "fatol": 1e-2, "maxiter": 600, "initial_simplex": simplex})
        if best is None or res.fun < best.fun:
            best = res
    a, b, R, phi = unpack(best.x)
    return float(a), b, R, max(float(phi), 0.0), rc


@njit(cache=True)
def chain_posterior(z, grid, transition, R, phi, node):
    """Posterior marginals p(r_j | z, node potentials) of the chain over the RSSI grid whose
    pairwise potential is transition[i, k] N((z_j - r_k) - phi (z_{j-1} - r_i); 0, R (1 - phi^2))
    and whose first sample is N(z_0 - r_0; 0, R); ``node`` (n, G) are extra per-sample
    potentials (the labels' Binomial likelihoods, or ones)."""
    n = z.size
    G = grid.size
    v = R * (1.0 - phi * phi)
    alpha = np.empty((n, G))
    c = np.empty(n)
    # band of the transition, per row (cells beyond it carry nothing)
    lo = np.empty(G, dtype=np.int64)
    hi = np.empty(G, dtype=np.int64)
    for i in range(G):
        top = transition[i].max()
        lo[i] = G
        hi[i] = -1
        for k in range(G):
            if transition[i, k] > 1e-12 * top:
                lo[i] = min(lo[i], k)
                hi[i] = max(hi[i], k)
    total = 0.0
    for k in range(G):
        d = z[0] - grid[k]
        alpha[0, k] = math.exp(-0.5 * d * d / R) * node[0, k]
        total += alpha[0, k]
    c[0] = max(total, 1e-300)
    alpha[0] /= c[0]
    for t in range(1, n):
        row = np.zeros(G)
        for i in range(G):
            ai = alpha[t - 1, i]
            if ai < 1e-300:
                continue
            prev = z[t - 1] - grid[i]
            for k in range(lo[i], hi[i] + 1):
                d = (z[t] - grid[k]) - phi * prev
                row[k] += ai * transition[i, k] * math.exp(-0.5 * d * d / v)
        total = 0.0
        for k in range(G):
            row[k] *= node[t, k]
            total += row[k]
        c[t] = max(total, 1e-300)
        alpha[t] = row / c[t]
    post = np.empty((n, G))
    beta = np.ones(G)
    post[n - 1] = alpha[n - 1]
    for t in range(n - 1, 0, -1):
        nb = np.zeros(G)
        for i in range(G):
            prev = z[t - 1] - grid[i]
            acc = 0.0
            for k in range(lo[i], hi[i] + 1):
                d = (z[t] - grid[k]) - phi * prev
                acc += transition[i, k] * math.exp(-0.5 * d * d / v) * node[t, k] * beta[k]
            nb[i] = acc / c[t]
        beta = nb
        post[t - 1] = alpha[t - 1] * beta
    for t in range(n):
        s = post[t].sum()
        post[t] /= max(s, 1e-300)
    return post


# -- 2. deconvolution with a GP prior on the warped axis ---------------------------------------

def _matern52(u: np.ndarray, length_scale: float, amplitude: float) -> np.ndarray:
    """amplitude * Matern(nu=5/2) on the warped axis ``u`` (scikit-learn's kernel)."""
    return _matern_kernel(length_scale, amplitude)(u[:, None])


def _integral_gp(stats: tuple, K: np.ndarray, want_mean: bool):
    """GP on the grid observed through y = P f + e, e ~ N(0, diag(noise)).

    ``stats`` are the sufficient statistics (P^T W P, P^T W r, r^T W r, sum log noise, n)
    with W = diag(1/noise) and r = y - m0, so each evaluation costs O(G^3) whatever the
    number of labels. Returns the log marginal likelihood and, if asked, the posterior
    mean of (f - m0) on the grid.
    """
    PtWP, PtWr, rWr, logdet_noise, n = stats
    G = K.shape[0]
    Lk = np.linalg.cholesky(K + 1e-8 * np.eye(G))
    B = np.eye(G) + Lk.T @ PtWP @ Lk
    LB = np.linalg.cholesky(B)
    w = np.linalg.solve(LB, Lk.T @ PtWr)
    quad = float(rWr - w @ w)
    logdet = float(logdet_noise + 2.0 * np.sum(np.log(np.diag(LB))))
    ll = -0.5 * (quad + logdet + n * math.log(2.0 * math.pi))
    if not want_mean:
        return ll, None
    return ll, Lk @ np.linalg.solve(LB.T, w)


def _fit_integral_gp(P: np.ndarray, y: np.ndarray, u: np.ndarray, nu: int, restarts: int):
    """GP fit of p_D on the grid from labels observed through the input posteriors ``P``; returns
    (f, (length scale, amplitude), m0, tau2). ``tau2`` is the labels' overdispersion: variance of
    the true POD around p_D(r) at one RSSI (0 when the POD is a function of the RSSI, as in the
    paper; shadowing makes one RSSI come from many ranges), a method-of-moments estimate from the
    first fit's residuals, kept in the labels' noise for the second."""
    m0 = float(np.mean(y))
    noise = np.full(y.size, max(m0 * (1.0 - m0), 0.05) / nu)
    best_theta = (0.1, 0.05)
    f = np.full(u.size, m0)
    r = y - m0
    tau2 = 0.0
    for _ in range(2):
        winv = 1.0 / noise
        stats = ((P * winv[:, None]).T @ P, P.T @ (r * winv), float(np.sum(r * r * winv)), float(np.sum(np.log(noise))), y.size)

        def nll(th: np.ndarray) -> float:
            ll, _ = _integral_gp(stats, _matern52(u, math.exp(th[0]), math.exp(th[1])), False)
            return -ll

        best = None
        for l0 in np.log(np.geomspace(0.04, 0.25, restarts)):
            res = minimize(nll, [l0, math.log(0.05)], method="L-BFGS-B",
                           bounds=[(math.log(0.01), math.log(2.0)), (math.log(1e-3), math.log(1.0))])
            if best is None or res.fun < best.fun:
                best = res
        best_theta = (math.exp(best.x[0]), math.exp(best.x[1]))
        _, df = _integral_gp(stats, _matern52(u, *best_theta), True)
        f = m0 + df
        fc = np.clip(f, 0.01, 0.99)
        ef = P @ fc
        input_var = np.maximum(P @ (fc * fc) - ef * ef, 0.0)
        noise = np.maximum(P @ (fc * (1.0 - fc)), 0.005) / nu + input_var
        if tau2 == 0.0:
            resid = y - ef
            tau2 = max(float(np.mean(resid**2 - noise)), 0.0)
            if tau2 > 0.25 * float(np.mean(noise)):  # overdispersed labels: the POD is not a function of the RSSI
                # the residuals of a Tx that lingers where the shadowing is the same are correlated in
                # time: fewer independent labels than samples, (1 + rho) / (1 - rho) fewer for AR(1)
                rho = min(max(float(np.corrcoef(resid[1:], resid[:-1])[0, 1]), 0.0), 0.99)
                tau2 *= (1.0 + rho) / (1.0 - rho)
            else:
                tau2 = 0.0
        noise = noise + tau2
    return f, best_theta, m0, tau2


# -- 3. label-informed EM ------------------------------------------------------------------------

def _binomial_loglik(k: np.ndarray, nu: int, p: np.ndarray) -> np.ndarray:
    """log Binomial(k_j; nu, p_g) as an (n, G) matrix."""
    from scipy.special import gammaln

    p = np.clip(p, 5e-3, 1.0 - 5e-3)
    logc = gammaln(nu + 1) - gammaln(k + 1) - gammaln(nu - k + 1)
    return logc[:, None] + k[:, None] * np.log(p)[None, :] + (nu - k)[:, None] * np.log1p(-p)[None, :]


def _gp_on_cells(u: np.ndarray, successes: np.ndarray, trials: np.ndarray, theta, m0: float, nu: int = 1, tau2: float = 0.0):
    """GP posterior (mean, std) on the grid from Binomial cell counts: scikit-learn's GPR with
    the kernel fixed from the deconvolution step and per-cell noise p(1-p)/N (heteroscedastic),
    plus the labels' overdispersion ``tau2`` over the cell's N / nu samples."""
    m = trials >= 1.0
    p = successes[m] / trials[m]
    shrunk = (successes[m] + 0.5) / (trials[m] + 1.0)  # keeps the variance positive at p = 0 or 1
    noise = shrunk * (1.0 - shrunk) / trials[m] + tau2 * nu / np.maximum(trials[m], nu) + 1e-6
    from sklearn.gaussian_process import GaussianProcessRegressor

    length_scale, amplitude = theta
    gpr = GaussianProcessRegressor(kernel=_matern_kernel(length_scale, amplitude), alpha=noise, optimizer=None, normalize_y=False)
    gpr.fit(u[m][:, None], p - m0)
    mean, std = gpr.predict(u[:, None], return_std=True)
    return m0 + mean, std


def _channel_sums(samples: list[TrainingSample]) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Per sample and advertising channel, the number and the sum of its iso packets: (n_jc, s_jc,
    channels); the packets without a channel in a column of their own (never offset)."""
    channels = sorted({a.channel for s in samples for a in s.advertisements_of("iso") if a.channel is not None})
    col = {c: i for i, c in enumerate(channels)}
    n = np.zeros((len(samples), len(channels) + 1))
    total = np.zeros_like(n)
    for j, s in enumerate(samples):
        for ad in s.advertisements_of("iso"):
            i = col.get(ad.channel, len(channels))
            n[j, i] += 1.0
            total[j, i] += ad.rssi_dbm
    return n, total, channels


def _packet_evidence(samples: list[TrainingSample], cfg: LearnerSettings, min_var: float):
    """The walk (a, b, R, r_c), the RSSI grid, each sample's log-evidence on it from its packets,
    and the channels' offsets. Where the packets say their advertising channel, each channel's
    offset (frequency-selective fading: a receiver reads one channel a few dB apart from another)
    is a parameter of the walk's likelihood, fitted with it (centred: the overall level belongs to
    the walk), and every packet loses its channel's offset before it weighs on its sample."""
    n_jc, s_jc, channels = _channel_sums(samples)
    counts = n_jc.sum(axis=1)
    if counts.sum() < MIN_TRAINING_ADVERTS:
        raise TrainingDataError(f"the training stream carries {int(counts.sum())} Rx(iso) advertisements in {len(samples)} samples; "
                                f"the POD learner needs at least {MIN_TRAINING_ADVERTS}")
    values = np.asarray([v for s in samples for v in s.rssi_dbm("iso")], dtype=float)
    grid = np.linspace(values.min() - cfg.grid_margin_db, values.max() + cfg.grid_margin_db, cfg.grid_points)
    seen = counts > 0

    def zbar_of(free: np.ndarray) -> np.ndarray:
        off = np.zeros(n_jc.shape[1])
        if len(channels) > 1:
            off[:len(channels)] = np.append(free, -free.sum())  # centred offsets
        return np.where(seen, (s_jc.sum(axis=1) - n_jc @ off) / np.maximum(counts, 1.0), 0.0)

    a, b, R, rc = fit_diffusion_packets(np.where(seen, s_jc.sum(axis=1) / np.maximum(counts, 1.0), np.nan), counts, min_var)
    free = np.zeros(max(len(channels) - 1, 0))
    if cfg.channel_offsets and len(channels) > 1:
        def nll(th: np.ndarray) -> float:
            return -_kalman_loglik_packets(zbar_of(th[3:]), counts, th[0], float(np.clip(th[1], -1.0, 1.0)),
                                           max(math.exp(th[2]), min_var), rc)

        x0 = np.concatenate([[a, b, math.log(R)], free])
        simplex = np.vstack([x0] + [x0 + step for step in np.diag(np.concatenate([[1.0, 0.15, 0.5], np.full(free.size, 2.0)]))])
        res = minimize(nll, x0, method="Nelder-Mead", options={"xatol": 1e-2, "fatol": 1e-2, "maxiter": 1500, "initial_simplex": simplex})
        a, b, R, free = float(res.x[0]), float(np.clip(res.x[1], -1.0, 1.0)), max(math.exp(res.x[2]), min_var), res.x[3:]
    zbar = zbar_of(free)
    log_rssi = np.where(counts[:, None] > 0, -0.5 * counts[:, None] * (zbar[:, None] - grid[None, :]) ** 2 / R, 0.0)
    fitted = cfg.channel_offsets and len(channels) > 1
    offsets = {c: float(o) for c, o in zip(channels, np.append(free, -free.sum()))} if fitted else {}
    return a, b, R, rc, grid, log_rssi, offsets


def fit_pod(samples: list[TrainingSample], settings: LearnerSettings | None = None) -> LearnedPOD:
    """Fit p_hat_D(r) from the training stream (see module docstring).

    Parameters
    ----------
    samples : list of TrainingSample, in the order they were taken
        The iso RSSI z_j and the nu frames of each sample.

    Returns
    -------
    LearnedPOD
        The compact model plus fitting time and the fitted walk parameters.

    Raises
    ------
    TrainingDataError
        Fewer than 10 samples, or on BLE fewer than 10 Rx(iso) advertisements.
    ValueError
        Inconsistent frame counts.
    """
    cfg = settings or LearnerSettings()
    started = time.perf_counter()
    z, k, nu = detection_counts(samples)
    _, q = training_clutter(samples)
    if z.size < MIN_TRAINING_SAMPLES:
        raise TrainingDataError(f"the training stream carries {z.size} samples; the POD learner needs at least {MIN_TRAINING_SAMPLES}")
    min_var = cfg.min_rf_noise_db**2
    packets = any(s.iso_rssi_dbm is None for s in samples)
    phi = 0.0
    offsets = None
    reported = None  # the noise (R, phi) the model reports when it is not the deconvolution's (shadowing)
    if packets:  # protocol 1.3: 0..n advertisements per sample (docs/radio.md)
        a, b, R, rc, grid, log_rssi, offsets = _packet_evidence(samples, cfg, min_var)
    else:
        a, b, R, rc = fit_diffusion(z, min_var)
        if z.size >= 50:
            fa, fb, fR, fphi, _ = fit_fading_walk(z, min_var)
            if fphi >= cfg.min_fading and cfg.shadowing:
                # the stream's stationary swings are fading or shadowing, and z cannot tell which: keep
                # them in the latent RSSI (the white walk: only its white noise is deconvolved); the
                # controller still gets the fading fit's noise (what the level it reads swings by)
                reported = (fR, fphi)
            elif fphi >= cfg.min_fading:
                a, b, R, phi = fa, fb, fR, fphi
        grid = np.linspace(z.min() - cfg.grid_margin_db, z.max() + cfg.grid_margin_db, cfg.grid_points)
        log_rssi = -0.5 * (z[:, None] - grid[None, :]) ** 2 / R
    transition = _transition(grid, a, b, rc)
    if phi > 0.0:
        post = chain_posterior(z, grid, transition, R, phi, np.ones((z.size, grid.size)))
    else:
        rssi_emission = np.exp(log_rssi - log_rssi.max(axis=1, keepdims=True))
        post = forward_backward(rssi_emission, transition)

    if b > 0.02:
        warped = np.exp(-0.5 * b * (grid - rc))
    else:
        warped = grid.copy()
    u = (warped - warped.min()) / max(warped.max() - warped.min(), 1e-12)
    # a frame shows a box in the gate with probability p_obs = q + (1 - q) p_D: clutter
    # corrected labels (q = 0 for a clean detector: the labels are the plain rates)
    y = (k / nu - q) / (1.0 - q)
    f, theta, m0, tau2 = _fit_integral_gp(post, y, u, nu, cfg.restarts)
    std = np.full(grid.size, math.sqrt(theta[1]))
    # the label-informed refinement moves inputs to where p_D fits their labels: right when the POD
    # is a function of the RSSI, a source of spurious wiggles when it is not (overdispersed labels)
    for _ in range(cfg.em_iterations if tau2 == 0.0 else 0):
        labels = _binomial_loglik(k, nu, q + (1.0 - q) * np.clip(f, 0.0, 1.0))
        if phi > 0.0:
            post = chain_posterior(z, grid, transition, R, phi, np.exp(labels - labels.max(axis=1, keepdims=True)))
        else:
            log_e = log_rssi + labels
            e = np.exp(log_e - log_e.max(axis=1, keepdims=True))
            post = forward_backward(e, transition)
        trials = post.sum(axis=0) * nu
        f, std = _gp_on_cells(u, np.clip(post.T @ k - q * trials, 0.0, None), trials * (1.0 - q), theta, m0, nu, tau2)

    noise_var, noise_phi = reported or (R, phi)
    model = PODModel(
        rssi_grid_dbm=tuple(float(v) for v in grid),
        mean=tuple(float(v) for v in np.clip(f, 0.0, 1.0)),
        std=tuple(float(v) for v in std),
        rf_noise_db=math.sqrt(noise_var),
        rf_noise_correlation=round(float(noise_phi), 6),
        n_train=int(z.size),
        frames_per_rf=int(nu),
    )
    return LearnedPOD(model=model, train_seconds=time.perf_counter() - started, diffusion=(a, b, R), fading=noise_phi,
                      channel_offsets=offsets or None)


# -- scoring the learner honestly (issue 20) -----------------------------------------------------

@dataclass(frozen=True)
class PODScore:
    """How well a learned POD matches the truth of its training episode.

    ``r2``: paper eq. 23 against p*(r_j), the POD the noiseless RSSI predicts (``world.TrainingTruth``).
    ``rmse``: the root mean square of p_hat_D(r_j) - p*(r_j). ``oracle_rmse``: the same for the
    oracle fit (``oracle_fit``): what a learner that saw every sample's true POD and noiseless
    RSSI reaches on this episode. Under shadowing the POD is not a function of the RSSI and R^2
    can stay low for any learner; the RMSE beside the oracle's says how far from the best
    possible a learner is.
    """

    r2: float
    rmse: float
    oracle_rmse: float


def unimodal_fit(x: np.ndarray, y: np.ndarray, candidates: int = 40) -> np.ndarray:
    """The least-squares fit of ``y`` on ``x`` that rises then falls (isotonic up to a peak, then
    antitonic; p_D is unimodal in the range, so in the RSSI), at each ``x``: the peak is the best
    of ``candidates`` quantiles of ``x``."""
    from sklearn.isotonic import IsotonicRegression

    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    best, best_sse = None, math.inf
    for peak in np.unique(np.quantile(x, np.linspace(0.0, 1.0, candidates))):
        left = x <= peak
        fit = np.empty_like(y)
        if left.any():
            fit[left] = IsotonicRegression(increasing=True).fit_transform(x[left], y[left])
        if (~left).any():
            fit[~left] = IsotonicRegression(increasing=False).fit_transform(x[~left], y[~left])
        sse = float(np.sum((fit - y) ** 2))
        if sse < best_sse:
            best, best_sse = fit, sse
    return best


def oracle_fit(rssi_dbm: np.ndarray, true_pod: np.ndarray) -> np.ndarray:
    """The oracle's fit at each training sample: ``unimodal_fit`` of every sample's true POD
    p_D(d_j) on its noiseless RSSI r_j (the episode's own data, no noise, no deconvolution)."""
    return unimodal_fit(rssi_dbm, true_pod)


def score_pod(model: PODModel, rssi_dbm: np.ndarray, pod: np.ndarray, pod_at_range: np.ndarray | None = None) -> PODScore:
    """R^2, RMSE against p*(r_j) = ``pod`` and the oracle fit's RMSE (``PODScore``), from a training
    episode's truth: noiseless RSSI ``rssi_dbm``, p*(r_j) ``pod`` and the true POD at each sample's
    range ``pod_at_range`` (None: equal to ``pod``, no shadowing)."""
    rssi = np.asarray(rssi_dbm, dtype=float)
    target = np.asarray(pod, dtype=float)
    prediction = predict(model, rssi)
    oracle = oracle_fit(rssi, target if pod_at_range is None else np.asarray(pod_at_range, dtype=float))
    return PODScore(r2=r2_score(target, prediction), rmse=float(np.sqrt(np.mean((prediction - target) ** 2))),
                    oracle_rmse=float(np.sqrt(np.mean((oracle - target) ** 2))))
