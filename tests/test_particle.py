"""Tests for particle filtering, FFBSi and particle EM (ceemx.particle_filter, ceemx.ffbsi,
ceemx.ParticleEM / ceemx.particle_em) and the primitives below them (ceemx.lib.particles,
ceemx.lib.kalman).

Oracles: a textbook Kalman filter + RTS smoother in NumPy (exact likelihood, filtering and smoothing
moments of a linear-Gaussian model, with missing observations skipped), dense NumPy Gaussian
conditioning, a NumPy replay of the filter's weight recursion from its own particles and ancestors,
and a NumPy EM for the maximum-likelihood A. Statistical tests use fixed seeds and tolerances of
about 4–4.5 standard errors estimated from the spread of independent runs (plus, where the particle
approximation has an O(1/N) bias, a small stated allowance); R = 64 independent runs in the
default suite, R = 200 (the same runs and more) under ``slow``.

One problem shape is shared by almost every test — n = 2, m = 2, B = 3, T = 20, N = 300 particles,
S = 10 smoothed draws — so the filter compiles once per proposal, FFBSi once, and particle EM
reuses both (checked by the ``traces`` fixture); only the float32 test compiles its own.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
import ceemx.identification.solvers.particle_em as particle_em_mod
import ceemx.inference.particle as particle_mod
from ceemx.identification.solvers import saem_step_size
from ceemx.lib import kalman
from ceemx.lib import particles as lp
from ceemx.lib.results import codes
from ceemx.systems import LinearSystem

RESULTS = ceemx.RESULTS
PROPOSALS = ("adapted", "bootstrap")

# The shared linear-Gaussian problem: x_{t+1} = A x_t + w, y_t = C x_t + v.
A_TRUE = np.array([[0.9, 0.2], [-0.1, 0.8]])
C_OBS = np.array([[1.0, 0.0], [0.5, 1.0]])
Q_SCALE = np.array([0.4, 0.4])  # diagonal process noise
R_COV = np.array([[0.36, 0.12], [0.12, 0.36]])  # correlated observation noise
M0 = np.array([0.5, -0.5])
P0_SCALE = np.array([1.0, 0.8])
B, T, NX, NY = 3, 20, 2, 2
N = 300  # particles, every filter in this module
S = 10  # FFBSi draws per trajectory (also particle EM's n_smoothed)
R_RUNS = 200  # independent runs behind each Monte Carlo test (slow); the default suite runs
R_FAST = 64  # the first 64 of them: standard errors 1.8× as large, tolerances in SE units
RUNS = [R_FAST, pytest.param(R_RUNS, marks=pytest.mark.slow)]
PEM = dict(n_particles=N, n_smoothed=S, memory=5, burn_in=3, alpha=0.7)
A_START = A_TRUE + np.array([[0.3, -0.3], [0.3, 0.3]])
PEM_EPOCHS = 15


def make_system(A=A_TRUE, dtype=jnp.float64, obs_noise=None, initial_prior=True):
    f = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    prior = ceemx.GaussianPrior(f(M0), ceemx.DiagonalGaussian(f(P0_SCALE), NX))
    return LinearSystem(
        f(A), f(C_OBS),
        process_noise=ceemx.DiagonalGaussian(f(Q_SCALE), NX),
        obs_noise=ceemx.CholeskyGaussian(cov=f(R_COV)) if obs_noise is None else obs_noise,
        initial_prior=prior if initial_prior else None,
    )  # fmt: skip


def missing_mask():
    """(B, T, m): whole steps missing in every trajectory (5–7), the first step of trajectory 0,
    the last of trajectory 2, and single components here and there."""
    mask = np.ones((B, T, NY), bool)
    mask[:, 5:8] = False
    mask[0, 0] = False
    mask[2, T - 1] = False
    mask[0, 16, 0] = False
    mask[1, 12, 0] = False
    mask[1, 13:15, 1] = False
    mask[2, 3, 1] = False
    return mask


# --------------------------------------------------------------------------------------------------
# NumPy oracles
# --------------------------------------------------------------------------------------------------


def condition(P, C, R, mask):
    """Dense conditioning of N(·, P) on the present rows of y = C x + v, v ~ N(0, R).

    Returns (K, posterior covariance, C_o, S_o) with K of shape (n, #present); None for S_o when no
    component is present (then K is empty and the posterior is P).
    """
    o = np.asarray(mask, bool)
    if not o.any():
        return np.zeros((P.shape[0], 0)), P, C[o], None
    Co, Ro = C[o], R[np.ix_(o, o)]
    S_o = Co @ P @ Co.T + Ro
    K = np.linalg.solve(S_o, Co @ P).T
    return K, P - K @ S_o @ K.T, Co, S_o


def gauss_logpdf(r, S):
    """log N(r; 0, S) for r of shape (..., d)."""
    d = S.shape[0]
    z = np.linalg.solve(np.linalg.cholesky(S), r[..., None])[..., 0]
    return -0.5 * np.sum(z**2, -1) - 0.5 * np.linalg.slogdet(S)[1] - 0.5 * d * math.log(2 * math.pi)


def kalman_rts(A, C, Q, R, m0, P0, y, mask):
    """Exact log p(y), filtered means (T, n), smoothed means (T, n), covariances (T, n, n) and
    lag-one Cov(x_{t+1}, x_t) (T-1, n, n); missing components skip their update."""
    n = A.shape[0]
    mp, Pp = np.zeros((T, n)), np.zeros((T, n, n))
    mf, Pf = np.zeros((T, n)), np.zeros((T, n, n))
    ll = 0.0
    for t in range(T):
        mp[t], Pp[t] = (m0, P0) if t == 0 else (A @ mf[t - 1], A @ Pf[t - 1] @ A.T + Q)
        K, Pf[t], Co, S_o = condition(Pp[t], C, R, mask[t])
        if S_o is None:
            mf[t] = mp[t]
            continue
        resid = y[t, mask[t]] - Co @ mp[t]
        mf[t] = mp[t] + K @ resid
        ll += gauss_logpdf(resid, S_o)
    ms, Ps = mf.copy(), Pf.copy()
    cross = np.zeros((T - 1, n, n))
    for t in range(T - 2, -1, -1):
        J = np.linalg.solve(Pp[t + 1], A @ Pf[t]).T
        ms[t] = mf[t] + J @ (ms[t + 1] - mp[t + 1])
        Ps[t] = Pf[t] + J @ (Ps[t + 1] - Pp[t + 1]) @ J.T
        cross[t] = (J @ Ps[t + 1]).T
    return ll, mf, ms, Ps, cross


def oracle(A, y, mask):
    """Per-trajectory Kalman/RTS results stacked over the batch."""
    Q, P0 = np.diag(Q_SCALE**2), np.diag(P0_SCALE**2)
    out = [kalman_rts(A, C_OBS, Q, R_COV, M0, P0, y[b], mask[b]) for b in range(B)]
    return [np.stack(v) for v in zip(*out, strict=True)]


def em_mle_A(y, mask, A0, tol=1e-12, max_iter=5000):
    """The maximum-likelihood A (C, noises and prior known) by exact EM on the Kalman smoother."""
    A = A0.copy()
    for _ in range(max_iter):
        _, _, ms, Ps, cross = oracle(A, y, mask)
        Sxx = np.sum(Ps[:, :-1] + ms[:, :-1, :, None] * ms[:, :-1, None, :], axis=(0, 1))
        Syx = np.sum(cross + ms[:, 1:, :, None] * ms[:, :-1, None, :], axis=(0, 1))
        A_new = Syx @ np.linalg.inv(Sxx)
        done = np.max(np.abs(A_new - A)) < tol
        A = A_new
        if done:
            return A
    raise AssertionError("EM oracle did not converge")


def replay(pf, data, b, threshold):
    """Recompute trajectory b's filter bookkeeping in NumPy from its particles and ancestors.

    Returns (log-weights (T, N), ESS (T,), resampling flags (T,), log-likelihood, standardised
    proposal noise (T·N, n)). The noise must be i.i.d. N(0, I) when each particle was drawn from
    the proposal around its recorded ancestor: x_t ~ N(A x_{t−1}^{a}, Q) for the bootstrap filter,
    N(mean of p(x_t | A x_{t−1}^{a}, y_t), posterior covariance) for the fully adapted one.
    """
    x = np.asarray(pf.particles[b])
    anc = np.asarray(pf.ancestors[b])
    y, mask = np.asarray(data.y[b]), np.asarray(data.mask[b])
    Q, P0 = np.diag(Q_SCALE**2), np.diag(P0_SCALE**2)
    log_n = math.log(N)

    def obs_loglik(xt, t):
        o = mask[t]
        if not o.any():
            return np.zeros(N)
        return gauss_logpdf(y[t, o] - xt @ C_OBS[o].T, R_COV[np.ix_(o, o)])

    def lse(a):
        mx = np.max(a)
        return mx + math.log(np.sum(np.exp(a - mx)))

    def ess_of(lw):
        return 1.0 / np.sum(np.exp(2 * (lw - lse(lw))))

    lws, esss, flags, noise = [], [], [], []
    for t in range(T):
        f = M0[None] if t == 0 else x[t - 1][anc[t]] @ A_TRUE.T  # parents' predicted means
        cov = P0 if t == 0 else Q
        if pf.proposal == "adapted":
            K, post, Co, S_o = condition(cov, C_OBS, R_COV, mask[t])
            mean = f if S_o is None else f + (y[t, mask[t]] - f @ Co.T) @ K.T
            noise.append(np.linalg.solve(np.linalg.cholesky(post), (x[t] - mean).T).T)
            fx = M0[None] if t == 0 else x[t - 1] @ A_TRUE.T  # all particles, before selection
            pred = (
                np.zeros(len(fx)) if S_o is None else gauss_logpdf(y[t, mask[t]] - fx @ Co.T, S_o)
            )
            if t == 0:
                ll, lw, e, flag = pred[0], np.full(N, -log_n), float(N), False
            else:
                v = lws[-1] + pred
                ll += lse(v)
                e = ess_of(v)
                flag = e < threshold * N
                lw = np.full(N, -log_n) if flag else v - lse(v)
        else:
            noise.append((x[t] - f) / (P0_SCALE if t == 0 else Q_SCALE))
            g = obs_loglik(x[t], t)
            if t == 0:
                ll, flag, base = lse(g) - log_n, False, np.zeros(N)
            else:
                e = ess_of(lws[-1])
                flag = e < threshold * N
                base = np.full(N, -log_n) if flag else lws[-1]
            w = base + g
            if t > 0:
                ll += lse(w)
            lw = w - lse(w)
            e = ess_of(lw) if t == 0 else e
        lws.append(lw)
        esss.append(e)
        flags.append(flag)
    return np.stack(lws), np.array(esss), np.array(flags), ll, np.concatenate(noise)


# --------------------------------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------------------------------


def _signature(tree):
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    return treedef, tuple(
        (leaf.shape, str(leaf.dtype)) if hasattr(leaf, "shape") else leaf for leaf in leaves
    )


@pytest.fixture(scope="module", autouse=True)
def traces():
    """Route the filter's and FFBSi's compiled kernels (as called by ``particle_filter``, ``ffbsi``
    and ``ParticleEM``) through jit wrappers that record each trace; a second trace of an already
    compiled configuration raises, whichever test causes it. Results are unchanged."""
    seen = []
    raw_filter, raw_ffbsi = particle_mod.filter_batch, particle_mod.ffbsi_batch

    def record(kind, args):
        key = (kind, _signature(args))
        if key in seen:
            raise AssertionError(f"{kind} retraced for an already compiled configuration")
        seen.append(key)

    @eqx.filter_jit
    def filter_batch(system, data, prior, key, threshold, n_particles, proposal):
        record("filter", (system, data, prior, key, threshold, n_particles, proposal))
        return raw_filter(system, data, prior, key, threshold, n_particles, proposal)

    @eqx.filter_jit
    def ffbsi_batch(system, data, pf, key, n_samples):
        record("ffbsi", (system, data, pf, key, n_samples))
        return raw_ffbsi(system, data, pf, key, n_samples)

    with pytest.MonkeyPatch.context() as mp:
        for mod in (particle_mod, particle_em_mod):
            mp.setattr(mod, "filter_batch", filter_batch)
            mp.setattr(mod, "ffbsi_batch", ffbsi_batch)
        yield seen


@pytest.fixture(scope="module")
def problem():
    """The shared model and two data sets on the same simulated states: fully observed, and with
    the :func:`missing_mask` (masked entries NaN). Oracle results per data set."""
    rng = np.random.default_rng(20240611)
    xs = np.zeros((B, T, NX))
    xs[:, 0] = M0 + P0_SCALE * rng.standard_normal((B, NX))
    for t in range(T - 1):
        xs[:, t + 1] = xs[:, t] @ A_TRUE.T + Q_SCALE * rng.standard_normal((B, NX))
    y = xs @ C_OBS.T + rng.standard_normal((B, T, NY)) @ np.linalg.cholesky(R_COV).T
    masks = {"observed": np.ones((B, T, NY), bool), "missing": missing_mask()}
    data, oracles = {}, {}
    for name, mask in masks.items():
        data[name] = ceemx.Trajectories(
            jnp.asarray(np.where(mask, y, np.nan)), mask=jnp.asarray(mask)
        )
        ll, mf, ms, Ps, _ = oracle(A_TRUE, y, mask)
        oracles[name] = dict(ll=ll, filtered=mf, smoothed=ms, smoothed_cov=Ps)
    return dict(system=make_system(), y=y, masks=masks, data=data, oracle=oracles)


@pytest.fixture(scope="module")
def monte_carlo(problem):
    """``runs`` independent filters per (data set, proposal), computed on first use: log p̂ (R, B)
    and the particle filtering means (R, B, T, n). Fewer runs are the first of more."""
    cache = {}

    def get(name, proposal, runs=R_FAST):
        if (name, proposal, runs) not in cache:
            seed = {"observed": 0, "missing": 1}[name] + {"adapted": 10, "bootstrap": 20}[proposal]
            keys = jax.random.split(jax.random.PRNGKey(seed), R_RUNS)
            lls, means = [], []
            for i in range(runs):
                pf = ceemx.particle_filter(
                    problem["system"], problem["data"][name], n_particles=N, key=keys[i],
                    proposal=proposal,
                )  # fmt: skip
                assert np.all(codes(pf.status) == codes(RESULTS.successful))
                lls.append(np.asarray(pf.log_likelihood))
                w = np.exp(np.asarray(pf.log_weights))[..., None]
                means.append(np.sum(w * np.asarray(pf.particles), axis=-2))
            cache[name, proposal, runs] = np.array(lls), np.array(means)
        return cache[name, proposal, runs]

    return get


# --------------------------------------------------------------------------------------------------
# Particle filter against the Kalman filter
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["observed", pytest.param("missing", marks=pytest.mark.slow)])
@pytest.mark.parametrize(
    "proposal", [PROPOSALS[0], pytest.param(PROPOSALS[1], marks=pytest.mark.slow)]
)
@pytest.mark.parametrize("runs", RUNS)
def test_likelihood_estimate_is_unbiased(problem, monte_carlo, runs, proposal, name):
    """E[p̂(y)] = p(y) (exact Kalman likelihood; missing components skipped) per trajectory: the
    mean of p̂/p over R independent runs is 1 within 4 standard errors of that mean."""
    lls, _ = monte_carlo(name, proposal, runs)
    ratio = np.exp(lls - problem["oracle"][name]["ll"])  # (R, B)
    mean, se = ratio.mean(0), ratio.std(0, ddof=1) / np.sqrt(runs)
    assert np.all(se < 0.1), se  # the test has power: a 40% bias would fail it
    np.testing.assert_array_less(np.abs(mean - 1.0), 4.0 * se)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["observed", "missing"])
@pytest.mark.parametrize("runs", RUNS)
def test_adapted_likelihood_has_lower_variance(monte_carlo, runs, name):
    """Same problem and N: the fully adapted filter's log p̂ varies well below the bootstrap's."""
    var_adapted = monte_carlo(name, "adapted", runs)[0].var(0, ddof=1)
    var_bootstrap = monte_carlo(name, "bootstrap", runs)[0].var(0, ddof=1)
    np.testing.assert_array_less(var_adapted, 0.5 * var_bootstrap)


@pytest.mark.parametrize("name", ["observed", pytest.param("missing", marks=pytest.mark.slow)])
@pytest.mark.parametrize(
    "proposal", [pytest.param(PROPOSALS[0], marks=pytest.mark.slow), PROPOSALS[1]]
)
@pytest.mark.parametrize("runs", RUNS)
def test_filtering_means_match_kalman(problem, monte_carlo, runs, proposal, name):
    """The particle filtering means E_N[x_t | y_{1:t}], averaged over runs, equal the Kalman
    filter's within 4.5 standard errors plus an O(1/N) bias allowance of 0.02."""
    _, means = monte_carlo(name, proposal, runs)
    avg, se = means.mean(0), means.std(0, ddof=1) / np.sqrt(runs)
    err = np.abs(avg - problem["oracle"][name]["filtered"])
    np.testing.assert_array_less(err, 4.5 * se + 0.02)


# --------------------------------------------------------------------------------------------------
# Weight bookkeeping, ancestry and adaptive resampling (exact replay in NumPy)
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("threshold", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("proposal", PROPOSALS)
def test_filter_replays_exactly(problem, proposal, threshold):
    """On the data with missing entries, the log-weights, ESS, resampling decisions and log p̂ equal
    a NumPy recomputation from the filter's own particles and ancestors; resampling happens exactly
    when the ESS of the ancestor-selecting weights is below threshold·N; ancestors are the identity
    when not resampling and sorted (systematic) when resampling; and the proposal noise implied by
    (particle, ancestor) pairs is standard normal (a wrong ancestor index would inflate it)."""
    data = problem["data"]["missing"]
    pf = ceemx.particle_filter(
        problem["system"], data, n_particles=N, key=jax.random.PRNGKey(7), proposal=proposal,
        ess_threshold=threshold,
    )  # fmt: skip
    assert pf.proposal == proposal
    assert pf.particles.shape == (B, T, N, NX) and pf.log_weights.shape == (B, T, N)
    assert pf.ancestors.shape == (B, T, N) and pf.ess.shape == pf.resampled.shape == (B, T)
    lw_all = np.asarray(pf.log_weights)
    ess, res, anc = np.asarray(pf.ess), np.asarray(pf.resampled), np.asarray(pf.ancestors)

    np.testing.assert_allclose(np.exp(lw_all).sum(-1), 1.0, rtol=0, atol=1e-12)  # normalised
    np.testing.assert_array_equal(res[:, 1:], ess[:, 1:] < threshold * N)
    assert not res[:, 0].any()
    identity = np.broadcast_to(np.arange(N), anc.shape)
    np.testing.assert_array_equal(anc[~res], identity[~res])
    assert np.all(np.diff(anc[res], axis=-1) >= 0) and anc.min() >= 0 and anc.max() < N
    if threshold == 0.0:
        assert not res.any()
    if threshold == 1.0:  # every step whose weights are not uniform resamples (strict <)
        assert np.all(res[:, 1:] | (ess[:, 1:] > N * (1 - 1e-9)))
        assert res[:, 1:].mean() > 0.5

    noise = []
    for b in range(B):
        lw, e, flags, ll, z = replay(pf, data, b, threshold)
        np.testing.assert_array_equal(flags[1:], res[b, 1:])
        np.testing.assert_allclose(lw_all[b], lw, rtol=0, atol=1e-8)
        np.testing.assert_allclose(ess[b], e, rtol=1e-9)
        np.testing.assert_allclose(pf.log_likelihood[b], ll, rtol=0, atol=1e-8)
        noise.append(z)
    z = np.concatenate(noise)  # (B·T·N, n) i.i.d. N(0, I) draws
    k = len(z)
    np.testing.assert_array_less(np.abs(z.mean(0)), 4.5 / np.sqrt(k))
    cov = np.cov(z.T)
    np.testing.assert_array_less(np.abs(np.diag(cov) - 1.0), 4.5 * np.sqrt(2.0 / k))
    assert abs(cov[0, 1]) < 4.5 / np.sqrt(k)


def test_nonfinite_trajectory_is_isolated(problem):
    """Observations of 1e200 (finite) in one trajectory make every weight underflow: that
    trajectory alone is flagged ``particle_failure``; the others succeed with the very numbers of a
    clean run (same B, hence the same per-trajectory keys)."""
    data = problem["data"]["observed"]
    y = np.asarray(data.y).copy()
    y[1] = 1e200
    bad = ceemx.Trajectories(jnp.asarray(y))
    key = jax.random.PRNGKey(11)
    for proposal in PROPOSALS:
        kw = dict(n_particles=N, key=key, proposal=proposal)
        pf = ceemx.particle_filter(problem["system"], bad, **kw)
        clean = ceemx.particle_filter(problem["system"], data, **kw)
        ok = np.asarray(pf.status == RESULTS.successful)
        np.testing.assert_array_equal(ok, [True, False, True])
        np.testing.assert_array_equal(
            np.asarray(pf.status == RESULTS.particle_failure), [False, True, False]
        )
        assert not np.isfinite(pf.log_likelihood[1])
        np.testing.assert_array_equal(pf.log_likelihood[::2], clean.log_likelihood[::2])
        np.testing.assert_array_equal(pf.particles[::2], clean.particles[::2])


@pytest.mark.slow
@pytest.mark.parametrize(
    "proposal", ["adapted", pytest.param("bootstrap", marks=pytest.mark.slow)]
)  # each compiles its own float32 filter (~3 s)
def test_float32_in_float32_out(problem, monte_carlo, proposal):
    """A float32 system and float32 data filter and smooth in float32, with a likelihood estimate
    as close to the exact value as float64 runs are."""
    data = ceemx.Trajectories(jnp.asarray(problem["y"], jnp.float32))
    system = make_system(dtype=jnp.float32)
    pf = ceemx.particle_filter(system, data, n_particles=N, proposal=proposal)
    for leaf in (pf.particles, pf.log_weights, pf.ess, pf.log_likelihood):
        assert leaf.dtype == jnp.float32
    assert np.all(np.asarray(pf.status == RESULTS.successful))
    # log p̂ lies within the float64 runs' spread around the exact value (bias included).
    lls64 = monte_carlo("observed", proposal)[0]
    err64 = lls64 - problem["oracle"]["observed"]["ll"]
    tol = 4.5 * err64.std(0, ddof=1) + np.abs(err64.mean(0))
    err32 = np.asarray(pf.log_likelihood, np.float64) - problem["oracle"]["observed"]["ll"]
    np.testing.assert_array_less(np.abs(err32), tol)
    assert ceemx.ffbsi(system, data, pf, n_samples=2).dtype == jnp.float32


# --------------------------------------------------------------------------------------------------
# FFBSi against the RTS smoother
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["missing"])
@pytest.mark.parametrize("runs", RUNS)
def test_ffbsi_matches_rts(problem, runs, name):
    """FFBSi draws (fully adapted filter, N particles, S draws, R independent runs) have the RTS
    smoothed means and variances: per run, the mean of the S draws and the mean squared deviation
    from the RTS mean; across runs, |average − RTS| < 4.5·SE + an O(1/N) allowance (0.03 sd for
    means, 8% for variances), at every (trajectory, step, component). Every draw is a particle."""
    system, data = problem["system"], problem["data"][name]
    ms = problem["oracle"][name]["smoothed"]
    var = np.diagonal(problem["oracle"][name]["smoothed_cov"], axis1=-2, axis2=-1)
    keys = jax.random.split(jax.random.PRNGKey(3 if name == "observed" else 4), (R_RUNS, 2))
    means, sq = [], []
    for i in range(runs):
        pf = ceemx.particle_filter(system, data, n_particles=N, key=keys[i, 0], proposal="adapted")
        draws = np.asarray(ceemx.ffbsi(system, data, pf, n_samples=S, key=keys[i, 1]))
        if i == 0:
            assert draws.shape == (B, S, T, NX)
            x = np.asarray(pf.particles)  # (B, T, N, n)
            hit = np.all(draws[:, :, :, None, :] == x[:, None], axis=-1).any(-1)
            assert hit.all()
        means.append(draws.mean(1))
        sq.append(((draws - ms[:, None]) ** 2).mean(1))
    means, sq = np.array(means), np.array(sq)  # (R, B, T, n)
    se_mean = means.std(0, ddof=1) / np.sqrt(runs)
    np.testing.assert_array_less(np.abs(means.mean(0) - ms), 4.5 * se_mean + 0.03 * np.sqrt(var))
    se_sq = sq.std(0, ddof=1) / np.sqrt(runs)
    np.testing.assert_array_less(np.abs(sq.mean(0) - var), 4.5 * se_sq + 0.08 * var)


# --------------------------------------------------------------------------------------------------
# Primitives: resampling, ESS, backward indices, Gaussian conditioning
# --------------------------------------------------------------------------------------------------


@eqx.filter_jit
def _many_resamples(keys, log_w, num):
    return jax.vmap(lambda k: lp.systematic_resample(k, log_w, num))(keys)


@pytest.mark.parametrize("num", [None, 7])
def test_systematic_resampling(num):
    """Unbiased (mean offspring count num·w̄ᵢ within 4.5 SE, SE from the known two-point law),
    stratified (every draw gives ⌊num·w̄ᵢ⌋ or ⌈num·w̄ᵢ⌉ copies), sorted, num indices; weights
    need not be normalised."""
    n_part, draws = 10, 20000
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.full(n_part, 0.7))
    log_w = jnp.asarray(np.log(w) + 3.0)  # an unnormalised version
    idx = np.asarray(_many_resamples(jax.random.split(jax.random.PRNGKey(0), draws), log_w, num))
    counts = (idx[:, :, None] == np.arange(n_part)).sum(1)
    k = n_part if num is None else num
    assert idx.shape == (draws, k) and idx.dtype == np.int32
    assert np.all(np.diff(idx, axis=1) >= 0)
    np.testing.assert_array_equal(counts.sum(1), k)
    expected = k * w
    lo, hi = np.floor(expected), np.ceil(expected)
    assert np.all((counts == lo) | (counts == hi))
    frac = expected - lo
    se = np.sqrt(frac * (1 - frac) / draws)
    np.testing.assert_array_less(np.abs(counts.mean(0) - expected), 4.5 * se + 1e-12)


# The small helpers below run under jit, as the filter and smoother run them: one program per
# shape instead of one per operation (eager evaluation compiles each of a few dozen operations).
offspring_counts = jax.jit(lp.offspring_counts, static_argnums=1)
ess = jax.jit(lp.ess)
log_normalize = jax.jit(lp.log_normalize)


def test_offspring_counts():
    """How often each particle index appears among the ancestors."""
    anc = jnp.asarray([0, 0, 2, 3, 3, 3], jnp.int32)
    np.testing.assert_array_equal(offspring_counts(anc, 6), [2, 0, 1, 3, 0, 0])


def test_offspring_counts_of_fewer_draws():
    """``systematic_resample(key, log_w, num)`` allows num != N ancestors; counting them over N
    particles must be possible too."""
    anc = jnp.asarray([0, 0, 2], jnp.int32)
    np.testing.assert_array_equal(offspring_counts(anc, 5), [2, 0, 1, 0, 0])


def test_ess_and_log_normalize():
    """ESS = 1/Σw̄²: N for uniform weights, 1 for a point mass; log_normalize returns log Σ exp and
    falls back to uniform weights with a −∞ total when every weight is impossible."""
    rng = np.random.default_rng(1)
    log_w = rng.standard_normal(12) * 2
    w = np.exp(log_w) / np.exp(log_w).sum()
    np.testing.assert_allclose(ess(jnp.asarray(log_w)), 1.0 / np.sum(w**2), rtol=1e-12)
    np.testing.assert_allclose(ess(jnp.full((12,), -3.0)), 12.0, rtol=1e-12)
    point = jnp.asarray(np.where(np.arange(12) == 4, 0.0, -np.inf))
    np.testing.assert_allclose(ess(point), 1.0, rtol=1e-12)
    normed, total = log_normalize(jnp.asarray(log_w))
    np.testing.assert_allclose(np.exp(normed), w, rtol=1e-12)
    np.testing.assert_allclose(total, np.log(np.exp(log_w).sum()), rtol=1e-12)
    normed, total = log_normalize(jnp.full((5,), -jnp.inf))
    assert total == -np.inf
    np.testing.assert_allclose(normed, np.full(5, -np.log(5.0)))


def test_backward_indices_distribution():
    """Index s is drawn with probability ∝ w_i · p(x̃^s | x_i): frequencies within 4.5 SE."""
    n_part, n_traj, draws = 6, 3, 20000
    rng = np.random.default_rng(2)
    log_w = jnp.asarray(rng.standard_normal(n_part))
    log_trans = jnp.asarray(rng.standard_normal((n_traj, n_part)) * 1.5)
    keys = jax.random.split(jax.random.PRNGKey(5), draws)
    idx = np.asarray(jax.jit(jax.vmap(lambda k: lp.backward_indices(k, log_w, log_trans)))(keys))
    assert idx.shape == (draws, n_traj)
    logits = np.asarray(log_w)[None] + np.asarray(log_trans)
    p = np.exp(logits - logits.max(1, keepdims=True))
    p /= p.sum(1, keepdims=True)
    freq = np.stack([(idx == i).mean(0) for i in range(n_part)], axis=1)  # (S, N)
    np.testing.assert_array_less(np.abs(freq - p), 4.5 * np.sqrt(p * (1 - p) / draws) + 1e-12)


@pytest.mark.parametrize(
    "mask", [[True, True, True], [True, False, True], [False, False, False]],
    ids=["all", "partial", "none"],
)  # fmt: skip
def test_gaussian_update_matches_dense_conditioning(mask):
    """Posterior mean and covariance and log N(y_o; C_o μ, C_o P C_oᵀ + R_oo) equal dense NumPy
    conditioning on the present components (correlated R); missing components may hold NaN."""
    rng = np.random.default_rng(3)
    n, m = 3, 3
    M = rng.standard_normal((n, n))
    P = M @ M.T + 0.5 * np.eye(n)
    C = rng.standard_normal((m, n))
    L = np.tril(rng.standard_normal((m, m)) * 0.3) + np.diag([0.5, 0.7, 0.6])
    R = L @ L.T
    mu, y = rng.standard_normal(n), rng.standard_normal(m)
    mask = np.array(mask)
    y_in = np.where(mask, y, np.nan)
    up, got_mean, logp = _update(*map(jnp.asarray, (P, C, L, mask, mu, y_in)))
    K, post, Co, S_o = condition(P, C, R, mask)
    mean = mu + K @ (y[mask] - Co @ mu)
    np.testing.assert_allclose(got_mean, mean, atol=1e-12)
    chol_post = np.asarray(up.chol_post)
    np.testing.assert_allclose(chol_post @ chol_post.T, post, atol=1e-12)
    np.testing.assert_allclose(np.tril(chol_post), chol_post)
    expected = 0.0 if S_o is None else gauss_logpdf(y[mask] - Co @ mu, S_o)
    np.testing.assert_allclose(logp, expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(up.gain)[:, ~mask], 0.0)


@jax.jit
def _update(P, C, L, mask, mu, y):
    """The update, its posterior mean and predictive log-density: one program for every mask."""
    up = kalman.gaussian_update(P, C, L, mask)
    return up, up.mean(mu, y), kalman.predictive_log_density(up, mu, y)


# --------------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------------


def test_invalid_arguments_raise_before_compute(problem):
    system, data = problem["system"], problem["data"]["observed"]
    pf_kw = dict(n_particles=N, key=jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="n_particles"):
        ceemx.particle_filter(system, data, n_particles=0)
    with pytest.raises(TypeError, match="n_particles"):
        ceemx.particle_filter(system, data, n_particles=10.0)
    with pytest.raises(ValueError, match="ess_threshold"):
        ceemx.particle_filter(system, data, **pf_kw, ess_threshold=1.5)
    with pytest.raises(ValueError, match="ess_threshold"):
        ceemx.particle_filter(system, data, **pf_kw, ess_threshold=-0.1)
    with pytest.raises(TypeError, match="ess_threshold"):
        ceemx.particle_filter(system, data, **pf_kw, ess_threshold="half")
    with pytest.raises(ValueError, match="proposal"):
        ceemx.particle_filter(system, data, **pf_kw, proposal="foo")
    student = make_system(obs_noise=ceemx.StudentT(1.0, 4.0, NY))
    with pytest.raises(ValueError, match="observation noise is not Gaussian"):
        ceemx.particle_filter(student, data, **pf_kw, proposal="adapted")
    prior = student.initial_prior
    assert particle_mod.resolve_proposal(student, "auto", prior) == "bootstrap"
    assert particle_mod.resolve_proposal(system, "auto", prior) == "adapted"
    flat = make_system(initial_prior=False)
    with pytest.raises(ValueError, match="initial"):
        ceemx.particle_filter(flat, data, **pf_kw)
    with pytest.raises(TypeError, match="initial"):
        ceemx.particle_filter(flat, data, **pf_kw, initial=(M0, P0_SCALE))
    with pytest.raises(ValueError, match="initial"):
        bad_mean = ceemx.GaussianPrior(jnp.zeros(3), ceemx.DiagonalGaussian(1.0, 3))
        ceemx.particle_filter(flat, data, **pf_kw, initial=bad_mean)
    with pytest.raises(ValueError, match="m = 1"):
        ceemx.particle_filter(system, ceemx.Trajectories(jnp.zeros((B, T, 1))), **pf_kw)

    pf = ceemx.particle_filter(system, data, **pf_kw)
    with pytest.raises(ValueError, match="`pf`"):
        ceemx.ffbsi(system, ceemx.Trajectories(data.y[:2]), pf, n_samples=S)
    with pytest.raises(TypeError, match="`pf`"):
        ceemx.ffbsi(system, data, pf.particles, n_samples=S)
    with pytest.raises(ValueError, match="n_samples"):
        ceemx.ffbsi(system, data, pf, n_samples=0)

    with pytest.raises(ValueError, match="n_particles"):
        ceemx.ParticleEM(n_particles=0)
    with pytest.raises(TypeError, match="memory"):
        ceemx.ParticleEM(memory=2.0)
    with pytest.raises(ValueError, match="alpha"):
        ceemx.ParticleEM(alpha=0.5)
    with pytest.raises(ValueError, match="burn_in"):
        ceemx.ParticleEM(burn_in=-1)
    with pytest.raises(ValueError, match="proposal"):
        ceemx.ParticleEM(proposal="foo")
    with pytest.raises(ValueError, match="ess_threshold"):
        ceemx.ParticleEM(ess_threshold=2.0)
    x0 = jnp.zeros((B, T, NX))
    with pytest.raises(ValueError, match="initial"):
        ceemx.particle_em(flat, data, x0, trainable=lambda s: s.A, max_epochs=1, **PEM)
    with pytest.raises(ValueError, match="observation noise is not Gaussian"):
        ceemx.particle_em(
            student, data, x0, trainable=lambda s: s.A, max_epochs=1, proposal="adapted", **PEM
        )


# --------------------------------------------------------------------------------------------------
# Particle EM
# --------------------------------------------------------------------------------------------------

DRIVER_KEYS = {
    "epoch", "time", "J", "J_before", "J_per_trajectory", "dtheta_norm", "dx_norm",
    "failed_trajectories", "converged", "stop",
}  # fmt: skip


def run_pem(problem, max_epochs, **kw):
    thetas, states = [], []

    def record(info):
        thetas.append(np.asarray(info.system.A))
        states.append(np.asarray(info.states))

    result = ceemx.particle_em(
        make_system(A_START), problem["data"]["missing"], jnp.zeros((B, T, NX)),
        trainable=lambda s: s.A, max_epochs=max_epochs, key=jax.random.PRNGKey(42),
        callbacks=[record], progress=False, **PEM, **kw,
    )  # fmt: skip
    return result, thetas, states


@pytest.fixture(scope="module")
def pem_run(problem):
    return run_pem(problem, PEM_EPOCHS)


@pytest.mark.slow
def test_particle_em_approaches_mle(problem, pem_run):
    """From A₀ = A + 0.3·(±1), PEM_EPOCHS epochs of particle EM (with missing data) bring A within a
    tenth of the initial distance to the exact maximum-likelihood A (NumPy EM on the Kalman
    smoother); every trajectory succeeds."""
    result, thetas, _ = pem_run
    A_mle = em_mle_A(problem["y"], problem["masks"]["missing"], A_START)
    start = np.linalg.norm(A_START - A_mle)
    final = np.linalg.norm(np.asarray(result.system.A) - A_mle)
    assert final < 0.1 * start, (final, start, np.asarray(result.system.A), A_mle)
    # ... and so toward the truth, as far as these 60 noisy transitions identify it.
    assert np.linalg.norm(np.asarray(result.system.A) - A_TRUE) < 0.5 * np.linalg.norm(
        A_START - A_TRUE
    )
    np.testing.assert_array_equal(thetas[-1], result.system.A)
    assert np.all(np.asarray(result.status == RESULTS.successful))
    assert result.epochs == PEM_EPOCHS and not result.converged


@pytest.mark.slow
def test_particle_em_history(pem_run):
    """History: the driver's keys plus ParticleEM.history_keys; SAEM step sizes γ_k = 1 for
    k ≤ burn_in, then (k − burn_in)^(−α); the kept SAEM mass follows the ring-buffer recursion
    (exactly 1 while the memory is not full or only zero-weight epochs were dropped)."""
    result, _, _ = pem_run
    keys = DRIVER_KEYS | set(ceemx.ParticleEM.history_keys)
    for h in result.history:
        assert keys <= set(h), keys - set(h)
    k = np.arange(1, PEM_EPOCHS + 1)
    burn, alpha = PEM["burn_in"], PEM["alpha"]
    gamma = np.where(k <= burn, 1.0, np.maximum(k - burn, 1.0) ** -alpha)
    np.testing.assert_allclose(result.history_array("step_size"), gamma, rtol=1e-12)
    np.testing.assert_allclose(saem_step_size(k, burn, alpha), gamma, rtol=1e-12)
    weights, mass = np.zeros(PEM["memory"]), []
    for epoch, g in zip(k, gamma, strict=True):
        weights *= 1.0 - g
        weights[(epoch - 1) % PEM["memory"]] = g
        mass.append(weights.sum())
    np.testing.assert_allclose(result.history_array("saem_mass"), mass, rtol=1e-12)
    np.testing.assert_allclose(result.history_array("saem_mass")[: PEM["memory"]], 1.0, rtol=1e-12)
    assert mass[-1] < 0.9  # the test covers dropped mass too
    per = np.array(result.history_array("pf_log_likelihood_per_trajectory"))
    assert per.shape == (PEM_EPOCHS, B) and np.all(np.isfinite(per))
    np.testing.assert_allclose(result.history_array("pf_log_likelihood"), per.sum(1), rtol=1e-12)
    assert np.all(result.history_array("min_ess") >= 1.0)
    assert np.all(result.history_array("min_ess") <= N * (1 + 1e-12))
    rate = result.history_array("resampling_rate")
    assert np.all((rate >= 0) & (rate <= 1))
    assert all(h["failed_trajectories"] == [] for h in result.history)
