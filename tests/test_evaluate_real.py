"""Models on measured data: free run, initial states from outputs, k-step prediction, scores.

Oracles: a Python loop over the model's own ``dynamics``/``observe``; the true x₁ of noise-free
simulated data; the extended Kalman filter's one-step predictions (k = 1) and a free run from its
prior mean (k ≥ T); NumPy formulas of ``nonlinear_benchmarks.error_metrics`` for the scores.
"""

import doctest

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx import GaussianPrior, Trajectories
from ceemx.evaluation import initial_state as init
from ceemx.evaluation import metrics as ev
from ceemx.evaluation import simulation as sim
from ceemx.inference.ekf import ekf
from ceemx.lib.results import RESULTS, codes, messages
from ceemx.models import DiagonalGaussian
from ceemx.systems import LinearSystem

TRACES = {"observe": 0}


class Duffing(ceemx.AbstractSystem):
    """A damped Duffing oscillator (Silverbox-like): position observed, velocity hidden."""

    k: jax.Array
    c: jax.Array
    k3: jax.Array
    process_noise: ceemx.AbstractNoise
    obs_noise: ceemx.AbstractNoise
    initial_prior: GaussianPrior | None
    dt: float = eqx.field(static=True)

    def __init__(self, k, c, k3, process_noise, obs_noise, initial_prior=None, dt=0.1):
        self.k, self.c, self.k3, self.dt = k, c, k3, dt
        self.process_noise, self.obs_noise, self.initial_prior = (
            process_noise,
            obs_noise,
            initial_prior,
        )

    @property
    def state_dim(self):
        return 2

    @property
    def obs_dim(self):
        return 1

    @property
    def input_dim(self):
        return 1

    def dynamics(self, x, u, t):
        pos, vel = x[0], x[1]
        acc = -self.k * pos - self.c * vel - self.k3 * pos**3 + u[0]
        return jnp.stack([pos + self.dt * vel, vel + self.dt * acc])

    def observe(self, x, u, t):
        TRACES["observe"] += 1  # Python side effect: runs once per trace
        return x[:1]


def duffing(k=1.0, c=0.3, k3=0.5, dtype=jnp.float64, **kw):
    a = lambda v: jnp.asarray(v, dtype)  # noqa: E731
    return Duffing(
        a(k), a(c), a(k3), DiagonalGaussian(a(0.05), 2), DiagonalGaussian(a(0.02), 1), **kw
    )


def oscillator(dt=0.1, k=1.0, c=0.2):
    """A damped linear oscillator: position observed, velocity hidden, force input."""
    A = jnp.array([[1.0, dt], [-k * dt, 1.0 - c * dt]])
    return LinearSystem(
        A, jnp.array([[1.0, 0.0]]), jnp.array([[0.0], [dt]]), process_noise=0.05, obs_noise=0.02
    )


def inputs(B, T, seed=0, dtype=np.float64):
    return np.random.default_rng(seed).standard_normal((B, T, 1)).astype(dtype)


def noise_free(system, x1, u):
    _, y = sim.free_run(system, x1, u)
    return Trajectories(y, u)


def loop(system, x1, u):
    xs, ys, x = [], [], np.asarray(x1)
    for t in range(u.shape[0]):
        xs.append(x)
        ys.append(np.asarray(system.observe(jnp.asarray(x), jnp.asarray(u[t]), t)))
        x = np.asarray(system.dynamics(jnp.asarray(x), jnp.asarray(u[t]), t))
    return np.stack(xs), np.stack(ys)


# ---------------------------------------------------------------- free run


def test_free_run_matches_a_python_loop():
    s = duffing()
    x1 = np.array([[1.0, -0.5], [0.2, 0.3]])
    u = inputs(2, 30)
    xs, ys = sim.free_run(s, x1, u)
    assert xs.shape == (2, 30, 2) and ys.shape == (2, 30, 1)
    for b in range(2):
        lx, ly = loop(s, x1[b], u[b])
        np.testing.assert_allclose(np.asarray(xs[b]), lx, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(np.asarray(ys[b]), ly, rtol=1e-12, atol=1e-14)
    # one trajectory without a batch axis; a system without inputs with num_steps
    x_one, y_one = sim.free_run(s, x1[1], u[1])
    np.testing.assert_array_equal(np.asarray(x_one), np.asarray(xs[1]))
    lin = LinearSystem(jnp.array([[0.5]]), jnp.array([[2.0]]))
    _, y = sim.free_run(lin, jnp.ones((3, 1)), num_steps=4)
    np.testing.assert_allclose(np.asarray(y[:, :, 0]), np.tile([2.0, 1.0, 0.5, 0.25], (3, 1)))


def test_free_run_dtype_and_errors():
    s32 = duffing(dtype=jnp.float32)
    xs, ys = sim.free_run(s32, np.ones((1, 2), np.float32), inputs(1, 5, dtype=np.float32))
    assert xs.dtype == ys.dtype == jnp.float32
    s = duffing()
    with pytest.raises(ValueError, match="`x1`"):
        sim.free_run(s, np.ones((2, 3)), inputs(2, 5))
    with pytest.raises(ValueError, match="`u`"):
        sim.free_run(s, np.ones((2, 2)), inputs(3, 5))
    with pytest.raises(ValueError, match="`u`"):
        sim.free_run(s, np.ones((2, 2)), np.ones((2, 5, 2)))
    with pytest.raises(ValueError, match="pass `u`"):
        sim.free_run(s, np.ones((2, 2)))
    with pytest.raises(ValueError, match="non-finite"):
        sim.free_run(s, np.array([[np.nan, 0.0]]), inputs(1, 5))
    with pytest.raises(ValueError, match="num_steps"):
        sim.free_run(s, np.ones((1, 2)), inputs(1, 5), num_steps=4)
    with pytest.raises(TypeError, match="AbstractSystem"):
        sim.free_run(object(), np.ones((1, 2)), inputs(1, 5))  # pyright: ignore[reportArgumentType]


# ---------------------------------------------------------------- initial states


@pytest.mark.slow
def test_initial_state_recovered_on_noise_free_data():
    x1 = np.array([[1.0, -0.5], [-0.3, 0.8]])
    lin = oscillator()
    data = noise_free(lin, x1, inputs(2, 40, seed=1))
    for refine in (True, False):  # refined, and the MAP smoothing's own x₁
        est, status = init.estimate_initial_state(lin, data, 15, refine=refine, return_status=True)
        assert est.shape == (2, 2) and len(ceemx.lib.results.messages(status)) == 2
        np.testing.assert_allclose(np.asarray(est), x1, atol=1e-7)
    s = duffing()
    data = noise_free(s, x1, inputs(2, 30, seed=1))
    np.testing.assert_allclose(np.asarray(init.estimate_initial_state(s, data, 10)), x1, atol=1e-8)
    # two outputs determine (position, velocity) of this second-order system; one output only
    # the position (the window has two steps either way: one compilation)
    np.testing.assert_allclose(np.asarray(init.estimate_initial_state(s, data, 2)), x1, atol=1e-8)
    one = np.asarray(init.estimate_initial_state(s, data, 1))
    np.testing.assert_allclose(one[:, 0], x1[:, 0], atol=1e-8)
    assert np.all(np.isfinite(one))


@pytest.mark.slow
def test_refinement_fits_the_window_when_process_noise_is_large():
    """With a large process noise the smoothed x₁ follows y by w_t; the refined one simulates it."""
    true = oscillator()
    x1 = np.array([[1.0, -0.5], [0.0, 1.0]])
    u = inputs(2, 40, seed=2)
    y = np.asarray(noise_free(true, x1, u).y)
    y = y + 0.05 * np.random.default_rng(3).standard_normal(y.shape)
    data = Trajectories(y, u)
    model = ceemx.with_noise(true, process_noise=1.0, obs_noise=0.05)
    errs, off = {}, {}
    for refine in (True, False):
        est = init.estimate_initial_state(model, data, 15, refine=refine)
        _, ys = sim.free_run(model, est, u)
        errs[refine] = np.sqrt(np.mean((np.asarray(ys) - y)[:, :15] ** 2, axis=(1, 2)))
        off[refine] = np.max(np.abs(np.asarray(est) - x1))
    assert np.all(errs[True] <= errs[False] + 1e-12) and np.all(errs[True] < 0.08)
    assert off[True] < 0.03 and off[False] > 0.1  # measured: 0.01 and 0.18


@pytest.mark.slow
def test_initial_state_compiles_once_per_structure_and_window():
    system = duffing()
    d1 = noise_free(system, np.ones((2, 2)), inputs(2, 30, seed=4))
    d2 = noise_free(system, -np.ones((2, 2)), inputs(2, 30, seed=5))
    other = duffing(k=1.3, c=0.1)  # new parameter values, same structure
    init.estimate_initial_state(system, d1, 10)
    before = TRACES["observe"]
    init.estimate_initial_state(other, d2, 10)
    init.estimate_initial_state(system, d1, 10, smoother=ceemx.LMSmoother(rtol=1e-8))
    assert TRACES["observe"] == before
    ev.benchmark_score(other, d2, 10)
    after = TRACES["observe"]
    ev.benchmark_score(system, d1, 10)
    ev.benchmark_score(other, d1, 10, x1=np.zeros((2, 2)))
    assert TRACES["observe"] == after


def test_initial_state_errors():
    s = duffing()
    data = noise_free(s, np.ones((2, 2)), inputs(2, 20))
    with pytest.raises(ValueError, match="n_init"):
        init.estimate_initial_state(s, data, 0)
    with pytest.raises(ValueError, match="n_init"):
        init.estimate_initial_state(s, data, 21)
    with pytest.raises(TypeError, match="n_init"):
        init.estimate_initial_state(s, data, 2.5)  # pyright: ignore[reportArgumentType]
    mask = np.ones((2, 20), bool)
    mask[1, :5] = False
    with pytest.raises(ValueError, match="trajectory 1 has no observed output"):
        init.estimate_initial_state(s, Trajectories(data.y, data.u, mask), 5)
    # (a float32 system with float64 data is no longer refused: the data are cast to float32,
    # as by fit — tests/test_reliability.py::test_every_entry_point_promotes_as_fit_and_smooth)
    bad = eqx.tree_at(lambda d: d.y, data, data.y.at[0, 3, 0].set(jnp.nan))
    with pytest.raises(ValueError, match="non-finite"):
        init.estimate_initial_state(s, bad, 5)
    with pytest.raises(ValueError, match="m = "):
        init.estimate_initial_state(s, Trajectories(np.zeros((2, 20, 2)), data.u), 5)


# ---------------------------------------------------------------- k-step prediction


@pytest.fixture(scope="module")
def noisy():
    true = oscillator(dt=0.2, k=2.0, c=2.0)  # |eigenvalues| ≈ 0.82: predictions forget x̂_t
    prior = GaussianPrior(jnp.array([0.5, 0.0]), DiagonalGaussian(jnp.asarray(1.0), 2))
    model = eqx.tree_at(lambda s: s.initial_prior, true, prior, is_leaf=lambda x: x is None)
    key = jax.random.PRNGKey(0)
    u = inputs(2, 50, seed=6)
    _, data = ceemx.simulate(true, key, np.array([[1.0, 0.0], [-1.0, 0.5]]), 50, u)
    return model, data


def test_k_step_one_is_the_filter_and_large_k_is_a_free_run(noisy):
    model, data = noisy
    p1 = sim.predict_k_step(model, data, 1)
    np.testing.assert_allclose(
        np.asarray(p1), np.asarray(ekf(model, data).predicted_obs), rtol=1e-12, atol=1e-12
    )
    T = data.num_steps
    x0 = np.broadcast_to(np.asarray(model.initial_prior.mean), (2, 2))
    _, free = sim.free_run(model, x0, data.u)
    for k in (T, T + 7):
        np.testing.assert_allclose(np.asarray(sim.predict_k_step(model, data, k)), free, atol=1e-12)
    gaps = [float(jnp.max(jnp.abs(sim.predict_k_step(model, data, k) - free))) for k in (1, 10, 35)]
    assert gaps[0] > gaps[1] > gaps[2] and gaps[2] < 0.05 * gaps[0]


def test_k_step_reads_only_outputs_up_to_s_minus_k(noisy):
    model, data = noisy
    k, s = 3, 20
    base = np.asarray(sim.predict_k_step(model, data, k))

    def bumped(t):
        y = data.y.at[:, t].add(1.0)
        return np.asarray(sim.predict_k_step(model, Trajectories(y, data.u), k))

    np.testing.assert_array_equal(bumped(s - k + 1)[:, s], base[:, s])
    assert np.all(np.abs(bumped(s - k)[:, s] - base[:, s]) > 1e-6)


def test_k_step_errors(noisy):
    model, data = noisy
    with pytest.raises(ValueError, match="`k`"):
        sim.predict_k_step(model, data, 0)
    with pytest.raises(TypeError, match="`k`"):
        sim.predict_k_step(model, data, 1.0)  # pyright: ignore[reportArgumentType]


# ---------------------------------------------------------------- the benchmark protocol


def hand_scores(y, y_sim, mask, n, scale):
    """nonlinear_benchmarks.error_metrics on the present entries of y[n:], per output."""
    B, _, m = y.shape
    rmse, nrmse, fit = (np.zeros((B, m)) for _ in range(3))
    overall = np.zeros(B)
    for b in range(B):
        errs = []
        for j in range(m):
            keep = mask[b, n:, j]
            yt, yp = scale[j] * y[b, n:, j][keep], scale[j] * y_sim[b, n:, j][keep]
            rmse[b, j] = np.sqrt(np.mean((yp - yt) ** 2))
            nrmse[b, j] = rmse[b, j] / np.std(yt)
            fit[b, j] = 100 * (1 - np.linalg.norm(yt - yp) / np.linalg.norm(yt - yt.mean()))
            errs.append(yp - yt)
        overall[b] = np.sqrt(np.mean(np.concatenate(errs) ** 2))
    return rmse, nrmse, fit, overall


def two_output_system(obs_noise=0.1):
    A = jnp.array([[0.9, 0.2, 0.0], [-0.2, 0.9, 0.1], [0.0, 0.0, 0.7]])
    C = jnp.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    B = jnp.array([[0.0], [1.0], [0.5]])
    return LinearSystem(A, C, B, process_noise=0.1, obs_noise=obs_noise)


def test_benchmark_score_matches_a_hand_computation():
    true = two_output_system()
    model = eqx.tree_at(lambda s: s.A, true, true.A * 0.97)
    u = inputs(2, 80, seed=7)
    _, data = ceemx.simulate(true, jax.random.PRNGKey(1), np.ones((2, 3)), 80, u)
    mask = np.ones((2, 80, 2), bool)
    mask[0, 40:45, 1] = False  # missing outputs are left out of the scores
    test = Trajectories(data.y, data.u, mask)
    n, scale = 10, np.array([2.0, 0.5])
    s = ev.benchmark_score(model, test, n, scale=scale)
    x1 = init.estimate_initial_state(model, test, n)
    np.testing.assert_allclose(np.asarray(s.x1), np.asarray(x1), rtol=1e-12, atol=1e-12)
    x_sim, y_sim = sim.free_run(model, x1, u)
    np.testing.assert_allclose(np.asarray(s.y_sim), np.asarray(y_sim), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(s.x_sim), np.asarray(x_sim), rtol=1e-12, atol=1e-12)
    rmse, nrmse, fit, overall = hand_scores(np.asarray(test.y), np.asarray(y_sim), mask, n, scale)
    np.testing.assert_allclose(np.asarray(s.rmse), rmse, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(s.nrmse), nrmse, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(s.fit_percent), fit, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(s.rmse_overall), overall, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(s.nrmse_overall), nrmse.mean(1), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(s.fit_percent_overall), fit.mean(1), rtol=1e-10)
    assert s.n_init == n and all(m == "converged" for m in ceemx.lib.results.messages(s.status))
    # given initial states: the free run from them; NRMSE does not depend on the scale
    t = ev.benchmark_score(model, test, n, x1=np.asarray(x1))
    np.testing.assert_allclose(np.asarray(t.rmse) * scale, np.asarray(s.rmse), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(t.nrmse), np.asarray(s.nrmse), rtol=1e-10)
    # the true model from the true x1 on noise-free data scores 0 and 100 %
    clean = noise_free(true, np.ones((2, 3)), u)
    p = ev.benchmark_score(true, clean, n, x1=np.ones((2, 3)))
    assert float(jnp.max(p.rmse)) < 1e-12 and float(jnp.min(p.fit_percent)) > 100 - 1e-9


@pytest.mark.slow  # ≈ 2 s; the float64 score's hand computation stays
def test_benchmark_score_float32():
    s32 = duffing(dtype=jnp.float32)
    data = noise_free(s32, np.ones((1, 2), np.float32), inputs(1, 30, dtype=np.float32))
    out = ev.benchmark_score(s32, data, 5)
    assert out.rmse.dtype == out.y_sim.dtype == out.x1.dtype == jnp.float32
    assert float(out.rmse[0, 0]) < 1e-3


def test_benchmark_score_rejects_bad_input_before_compute():
    s = duffing()
    data = noise_free(s, np.ones((2, 2)), inputs(2, 20))
    for n in (0, 20, -1):
        with pytest.raises(ValueError, match=r"\[1, T − 1\]"):
            ev.benchmark_score(s, data, n)
    with pytest.raises(TypeError, match="n_init"):
        ev.benchmark_score(s, data, True)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="p = "):
        ev.benchmark_score(s, Trajectories(data.y, np.ones((2, 20, 2))), 5)
    with pytest.raises(ValueError, match="`x1`"):
        ev.benchmark_score(s, data, 5, x1=np.ones((3, 2)))
    with pytest.raises(ValueError, match="`x1`"):
        ev.benchmark_score(s, data, 5, x1=np.full((2, 2), np.nan))
    with pytest.raises(ValueError, match="scale"):
        ev.benchmark_score(s, data, 5, scale=[1.0, 2.0])
    with pytest.raises(ValueError, match="scale"):
        ev.benchmark_score(s, data, 5, scale=-1.0)
    bad = eqx.tree_at(lambda d: d.u, data, data.u.at[1, 7, 0].set(jnp.inf))
    with pytest.raises(ValueError, match="non-finite"):
        ev.benchmark_score(s, bad, 5)
    mask = np.ones((2, 20), bool)
    mask[0, 5:] = False
    with pytest.raises(ValueError, match="nothing to score"):
        ev.benchmark_score(s, Trajectories(data.y, data.u, mask), 5)
    with pytest.raises(TypeError, match="AbstractSystem"):
        ev.benchmark_score(None, data, 5)  # pyright: ignore[reportArgumentType]


def test_docstring_examples():
    failed, attempted = doctest.testmod(sim, extraglobs={"ceemx": ceemx, "jnp": jnp}, verbose=False)
    assert attempted > 0 and failed == 0


def _have_tanks():
    from ceemx import datasets

    try:
        return (datasets.data_root() / datasets.REGISTRY["cascaded_tanks"].file).is_file()
    except FileNotFoundError:
        return False


@pytest.mark.slow
@pytest.mark.skipif(not _have_tanks(), reason="cascaded_tanks data not available")
def test_official_protocol_on_the_cascaded_tanks():
    """A first-order ARX model on real data, scored by hand: closed-form x̂₁ and free run."""
    from ceemx import datasets

    ds = datasets.cascaded_tanks()
    y, u = np.asarray(ds.train.y)[0, :, 0], np.asarray(ds.train.u)[0, :, 0]
    a, b = np.linalg.lstsq(np.stack([y[:-1], u[:-1]], 1), y[1:], rcond=None)[0]
    model = LinearSystem(jnp.array([[a]]), jnp.array([[1.0]]), jnp.array([[b]]), obs_noise=0.1)
    test, n = ds.tests["test"], ds.n_init
    s = ev.benchmark_score(model, test, n, scale=ds.score_scale)
    yt, ut = np.asarray(test.y)[0, :, 0], np.asarray(test.u)[0, :, 0]
    forced = np.zeros_like(yt)  # the free run from x₁ = 0
    for t in range(1, len(yt)):
        forced[t] = a * forced[t - 1] + b * ut[t - 1]
    powers = a ** np.arange(len(yt))
    # the window's least-squares start (the process noise does not enter the refined x̂₁)
    x1 = np.sum(powers[:n] * (yt[:n] - forced[:n])) / np.sum(powers[:n] ** 2)
    np.testing.assert_allclose(float(s.x1[0, 0]), x1, rtol=1e-8)
    y_sim = forced + powers * x1
    np.testing.assert_allclose(np.asarray(s.y_sim)[0, :, 0], y_sim, rtol=1e-8)
    rmse = np.sqrt(np.mean((y_sim[n:] - yt[n:]) ** 2))
    np.testing.assert_allclose(float(s.rmse[0, 0]), rmse, rtol=1e-8)
    fit = 100 * (1 - np.linalg.norm(y_sim[n:] - yt[n:]) / np.linalg.norm(yt[n:] - yt[n:].mean()))
    np.testing.assert_allclose(float(s.fit_percent[0, 0]), fit, rtol=1e-8)
    assert 0.75 < rmse < 3.0  # worse than the published best linear approximation (0.75 V)


def test_several_warm_starts_checked_before_compute():
    s = duffing()
    data = noise_free(s, np.ones((2, 2)), inputs(2, 20))
    for bad in ((), (1.0, -2.0), "1", (None, float("nan"))):
        with pytest.raises(ValueError, match="warm_process_noise"):
            init.estimate_initial_state(s, data, 5, warm_process_noise=bad)  # pyright: ignore


def _have_drives():
    from ceemx import datasets

    try:
        spec = datasets.REGISTRY["coupled_electric_drives"]
        return (datasets.data_root() / spec.file).is_file()
    except FileNotFoundError:
        return False


@pytest.mark.slow  # three initial-state compilations on real data (≈ 5 s)
@pytest.mark.skipif(not _have_drives(), reason="coupled_electric_drives data not available")
def test_several_warm_starts_keep_the_better_window_fit():
    """The drives' sign-insensitive sensor: the default start ends in the wrong sign of v.

    A fitted CoupledDrives (CE-EM, offsets, p = 1) on set 2's test window: the weak-pass start
    gives v₁ < 0 and a poor window fit, the start without it v₁ > 0; the pair keeps the latter.
    """
    from ceemx import datasets
    from ceemx.systems import CoupledDrives

    ds = datasets.coupled_electric_drives()
    test, n = ds.tests["set2_high"], ds.n_init
    model = CoupledDrives.default(
        a=4.2396, f0=3.6693, zeta=0.1347, gain=1.2168, u0=0.1576, y0=-0.2124,
        process_noise=0.002,
    )  # fmt: skip

    def window_rmse(x1):
        _, ys = sim.free_run(model, x1, test.u[:, :n])
        return float(np.sqrt(np.mean((np.asarray(ys) - np.asarray(test.y[:, :n])) ** 2)))

    one = init.estimate_initial_state(model, test, n, warm_process_noise=1.0)
    plain = init.estimate_initial_state(model, test, n, warm_process_noise=None)
    both = init.estimate_initial_state(model, test, n, warm_process_noise=(1.0, None))
    assert float(one[0, 1]) < 0 < float(plain[0, 1])
    assert window_rmse(plain) < 0.5 * window_rmse(one)
    np.testing.assert_allclose(np.asarray(both), np.asarray(plain), rtol=1e-12, atol=1e-12)
    assert window_rmse(plain) < 0.05


# ---------------------------------------------------------------- no quiet NaN


def linear(a, b=1.0):
    one = np.ones((1, 1))
    return LinearSystem(a * one, one, b * one, 0 * one, process_noise=0.1, obs_noise=0.1)


RECORD = ceemx.Trajectories(
    np.random.default_rng(1).standard_normal((2, 40, 1)),
    np.random.default_rng(2).standard_normal((2, 40, 1)),
)


def test_initial_state_nan_warns_and_carries_a_status():
    """obs_noise = 1e-300: whitening overflows; x̂₁ was NaN with no warning. (The hand-computed
    score's model and record shapes: the estimate's program is compiled already.)"""
    record = Trajectories(np.random.default_rng(1).standard_normal((2, 80, 2)), inputs(2, 80))
    system = two_output_system(obs_noise=1e-300)
    with pytest.warns(UserWarning, match=r"x̂₁ is not finite \(NaN or inf\) for trajectories 0, 1"):
        x1, status = init.estimate_initial_state(system, record, 10, return_status=True)
    assert np.all(np.isnan(np.asarray(x1)))
    assert codes(status).tolist() == [codes(RESULTS.nonfinite)] * 2


def test_diverging_benchmark_score_warns_and_carries_a_status():
    """x_{t+1} = 1e10·x: the free run overflows; RMSE and fit % were inf/NaN with no warning."""
    start = np.array([[1.0], [0.0]])  # no input: trajectory 1 stays at 0
    with pytest.warns(UserWarning, match="free-run simulation of trajectory 0 is not finite"):
        score = ev.benchmark_score(linear(1e10, b=0.0), RECORD, 5, x1=start)
    assert not np.isfinite(float(score.rmse_overall[0]))
    assert np.isfinite(float(score.rmse_overall[1]))
    assert messages(score.status) == [RESULTS[RESULTS.diverged], RESULTS[RESULTS.successful]]
