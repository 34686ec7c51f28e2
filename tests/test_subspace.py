"""Tests of multi-trajectory N4SID (ceemx.lib.subspace) and the SID baseline (baselines.sid)."""

import doctest

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.baselines.sid import fit_sid
from ceemx.lib.subspace import SubspaceResult, default_horizon, n4sid

jax.config.update("jax_enable_x64", True)


def random_system(rng, n, m, p, radius=0.9):
    """A random stable (A, B, C, D) with spectral radius ``radius`` and no pole near 0."""
    while True:
        A = rng.standard_normal((n, n))
        A *= radius / np.max(np.abs(np.linalg.eigvals(A)))
        if np.abs(np.linalg.eigvals(A)).min() > 0.3:
            break
    return A, rng.standard_normal((n, p)), rng.standard_normal((m, n)), rng.standard_normal((m, p))


def simulate(rng, system, batch, T, *, q=0.0, r=0.0, x0=None):
    """(y, u, x0) of ``batch`` trajectories: white-noise inputs, N(0, q²I), N(0, r²I) noise."""
    A, B, C, D = system
    n, p = B.shape
    u = rng.standard_normal((batch, T, p))
    x = rng.standard_normal((batch, n)) if x0 is None else x0
    start = x.copy()
    y = np.empty((batch, T, C.shape[0]))
    for t in range(T):
        y[:, t] = x @ C.T + u[:, t] @ D.T + r * rng.standard_normal((batch, C.shape[0]))
        x = x @ A.T + u[:, t] @ B.T + q * rng.standard_normal((batch, n))
    return y, u, start


def eig(A):
    return np.sort_complex(np.linalg.eigvals(np.asarray(A)))


def markov(A, B, C, D, num=10):
    """D, CB, CAB, …, CA^{num−1}B: basis-invariant, they determine the transfer function."""
    A, B, C, D = (np.asarray(a) for a in (A, B, C, D))
    out, P = [D], B
    for _ in range(num):
        out.append(C @ P)
        P = A @ P
    return np.stack(out)


def open_loop(A, B, C, D, x0, u):
    x, y = x0, []
    for t in range(u.shape[0]):
        y.append(C @ x + D @ u[t])
        x = A @ x + B @ u[t]
    return np.stack(y)


SYSTEM = random_system(np.random.default_rng(0), n=4, m=2, p=3)


# ------------------------------------------------------------- exact recovery from noiseless data
@pytest.mark.parametrize("weighting", ["n4sid", "moesp", "cva"])
@pytest.mark.parametrize("batch,T", [(1, 300), (6, 60)])
def test_noiseless_recovery(weighting, batch, T):
    rng = np.random.default_rng(1)
    y, u, _ = simulate(rng, SYSTEM, batch, T)
    res = n4sid(y, u, order=4, horizon=5, weighting=weighting)
    assert isinstance(res, SubspaceResult)
    assert np.abs(eig(res.A) - eig(SYSTEM[0])).max() < 1e-6
    truth = markov(*SYSTEM)
    assert np.abs(markov(res.A, res.B, res.C, res.D) - truth).max() < 1e-6 * np.abs(truth).max()
    # no residual; a clear gap after the 4th singular value
    assert np.abs(res.Q).max() < 1e-12 and np.abs(res.R).max() < 1e-12
    assert res.singular_values[4] < 1e-10 * res.singular_values[0]
    # the initial states reproduce every trajectory in open loop
    assert res.x0 is not None
    for b in range(batch):
        sim = open_loop(res.A, res.B, res.C, res.D, res.x0[b], u[b])
        assert np.abs(sim - y[b]).max() < 1e-6 * np.abs(y[b]).max()


def test_ragged_trajectories_and_single_array():
    rng = np.random.default_rng(2)
    y, u, _ = simulate(rng, SYSTEM, 3, 80)
    lengths = [80, 35, 52]
    res = n4sid(
        [y[b, :L] for b, L in enumerate(lengths)],
        [u[b, :L] for b, L in enumerate(lengths)],
        order=4,
    )
    assert res.horizon == min(default_horizon(4, 2), 35 // 2)
    assert np.abs(eig(res.A) - eig(SYSTEM[0])).max() < 1e-6
    assert res.num_columns == sum(L - 2 * res.horizon + 1 for L in lengths)
    one = n4sid(y[0], u[0], order=4, horizon=5)  # a (T, m) array is one trajectory
    assert np.abs(eig(one.A) - eig(SYSTEM[0])).max() < 1e-6


def test_autonomous_multi_trajectory():
    """p = 0: the free responses of several trajectories from random initial states."""
    rng = np.random.default_rng(3)
    A, _, C, _ = SYSTEM
    y, _, _ = simulate(rng, (A, np.zeros((4, 0)), C, np.zeros((2, 0))), 20, 30)
    res = n4sid(y, order=4, horizon=4)
    assert res.B.shape == (4, 0) and res.D.shape == (2, 0)
    assert np.abs(eig(res.A) - eig(A)).max() < 1e-6


# ------------------------------------------------------------------------- agreement with nfoursid
@pytest.mark.slow  # a second N4SID oracle; default: test_noiseless_recovery, test_fit_sid_system
def test_agrees_with_nfoursid():
    """Single noisy trajectory: our N4SID against the ``nfoursid`` package.

    Both use the same oblique projection O_k = Y_f /_{U_f} W_p, the same unweighted SVD and the
    same state-regression for (A, B, C, D). They differ only in the shifted state sequence:
    nfoursid shifts the columns of X_k = Γ_k⁺O_k by one step, we project once more with the
    past/future border moved (X_{k+1} = Γ_{k−1}⁺O_{k−1}). Both errors are finite-horizon
    Kalman-filter biases of the same order as the sampling error, so the two estimates must agree
    to a fraction of their distance from the truth (observed: ≈ 0.1–0.4 of it over seeds), and
    their innovation covariances R̂ (same residual definition) to about 1%.
    """
    nfoursid = pytest.importorskip(
        "nfoursid.nfoursid", reason="nfoursid not installed (pip install nfoursid)"
    )
    pd = pytest.importorskip("pandas", reason="nfoursid needs pandas")
    rng = np.random.default_rng(0)
    system = random_system(rng, 3, 2, 2, radius=0.85)
    k, T = 6, 2000
    y, u, _ = simulate(rng, system, 1, T, q=0.1, r=0.1)
    frame = pd.DataFrame(np.concatenate([y[0], u[0]], axis=1), columns=["y0", "y1", "u0", "u1"])
    ref = nfoursid.NFourSID(
        frame, output_columns=["y0", "y1"], input_columns=["u0", "u1"], num_block_rows=k
    )
    ref.subspace_identification()
    ss, cov = ref.system_identification(rank=3)
    res = n4sid(y, u, order=3, horizon=k, estimate_x0=False)

    truth_eig, truth_markov = eig(system[0]), markov(*system)
    scale = np.abs(truth_markov).max()
    d_eig = np.abs(eig(res.A) - eig(ss.a)).max()
    d_markov = np.abs(markov(res.A, res.B, res.C, res.D) - markov(ss.a, ss.b, ss.c, ss.d)).max()
    err_ours = np.abs(eig(res.A) - truth_eig).max()
    err_ref = np.abs(eig(ss.a) - truth_eig).max()
    assert err_ours < 0.02 and err_ref < 0.02  # both identify the system
    assert d_eig < 0.5 * max(err_ours, err_ref) and d_eig < 5e-3
    assert d_markov < 5e-3 * scale
    np.testing.assert_allclose(res.R, cov[:2, :2], rtol=0.02, atol=1e-3)


# ------------------------------------------------------------------------------------ consistency
@pytest.mark.slow  # a convergence run (5 seeds × 2 sizes); default: test_fit_sid_system
def test_error_falls_with_more_trajectories():
    """Process + measurement noise: 16× more trajectories ≈ 4× smaller eigenvalue error."""
    errors = {4: [], 64: []}
    for seed in range(5):
        rng = np.random.default_rng(100 + seed)
        system = random_system(rng, 3, 2, 2, radius=0.85)
        for batch in errors:
            y, u, _ = simulate(rng, system, batch, 100, q=0.2, r=0.2)
            res = n4sid(y, u, order=3, horizon=5, estimate_x0=False)
            errors[batch].append(np.abs(eig(res.A) - eig(system[0])).max())
    ratio = np.mean(errors[64]) / np.mean(errors[4])
    assert ratio < 0.5, (ratio, errors)
    assert np.mean(errors[64]) < 0.01


# ------------------------------------------------------------------------------------- bad inputs
def test_bad_inputs():
    rng = np.random.default_rng(4)
    y, u, _ = simulate(rng, SYSTEM, 2, 40)
    with pytest.raises(ValueError, match="shape"):
        n4sid(y[0, :, 0], order=2)
    with pytest.raises(ValueError, match="batch|trajectories"):
        n4sid(y, u[:1], order=2)
    with pytest.raises(ValueError, match="time steps"):
        n4sid(y, u[:, :30], order=2)
    with pytest.raises(ValueError, match="same m"):
        n4sid([y[0], y[1, :, :1]], order=2)
    bad = y.copy()
    bad[1, 7, 0] = np.nan
    with pytest.raises(ValueError, match=r"y\[1\].*\[7, 0\]"):
        n4sid(bad, u, order=2)
    bad_u = u.copy()
    bad_u[0, 3, 1] = np.inf
    with pytest.raises(ValueError, match=r"u\[0\]"):
        n4sid(y, bad_u, order=2)
    with pytest.raises(ValueError, match="positive integer"):
        n4sid(y, u, order=0)
    with pytest.raises(ValueError, match="too large for `horizon`"):
        n4sid(y, u, order=7, horizon=4)  # (k − 1)·m = 6 < 7
    with pytest.raises(ValueError, match="at least"):
        n4sid(y, u, order=2, horizon=21)
    with pytest.raises(ValueError, match="too few data"):
        n4sid(y[:1, :12], u[:1, :12], order=2, horizon=3)
    with pytest.raises(ValueError, match="weighting"):
        n4sid(y, u, order=2, weighting="pca")
    with pytest.raises(ValueError, match="no trajectory"):
        n4sid([], order=2)
    with pytest.raises(ValueError, match="shortest"):
        n4sid(y[:, :5], order=4)  # default horizon: needs k ≥ 3, i.e. 6 steps


# ------------------------------------------------------------------------------------------ fit_sid
def _data(batch, T, dtype=jnp.float64, seed=5):
    rng = np.random.default_rng(seed)
    A, B, C, D = random_system(rng, 3, 2, 2, radius=0.85)
    y, u, _ = simulate(rng, (A, B, C, D), batch, T, q=0.1, r=0.1)
    return A, ceemx.Trajectories(jnp.asarray(y, dtype), jnp.asarray(u, dtype))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_fit_sid_system(dtype):
    A, data = _data(16, 120, dtype)
    model = fit_sid(data, state_dim=3, horizon=5)
    assert isinstance(model, ceemx.systems.LinearSystem)
    assert model.A.dtype == dtype and model.C.dtype == dtype
    assert model.A.shape == (3, 3) and model.B.shape == (3, 2) and model.D.shape == (2, 2)
    assert np.abs(eig(model.A) - eig(A)).max() < 0.05
    for noise in (model.process_noise, model.obs_noise):
        chol = np.asarray(noise.cholesky())
        assert np.all(np.isfinite(chol)) and np.all(np.diag(chol) > 0)
    assert model.initial_prior is not None
    if dtype == jnp.float32:
        return
    # the one-step predictor runs and beats predicting zero
    pred = ceemx.evaluation.prediction.StateSpacePredictor(model).predict(data)
    assert np.mean((np.asarray(pred) - np.asarray(data.y)) ** 2) < np.mean(np.asarray(data.y) ** 2)
    unit = fit_sid(data, state_dim=3, horizon=5, noise="unit", initial_prior=False)
    np.testing.assert_allclose(np.asarray(unit.obs_noise.cholesky()), np.eye(2))
    assert unit.initial_prior is None


def test_fit_sid_subsets_and_padding():
    _, data = _data(12, 80)
    models = fit_sid(data, state_dim=3, horizon=5, subsets=3, subset_size=6)
    assert isinstance(models, list) and len(models) == 3
    assert not np.allclose(np.asarray(models[0].A), np.asarray(models[1].A))
    again = fit_sid(data, state_dim=3, horizon=5, subsets=3, subset_size=6)
    np.testing.assert_array_equal(np.asarray(models[2].A), np.asarray(again[2].A))
    # trailing padding (whole steps) = shorter trajectories
    mask = np.ones((12, 80), bool)
    mask[3, 50:] = False
    padded = ceemx.Trajectories(data.y, data.u, jnp.asarray(mask))
    direct = n4sid(
        [np.asarray(data.y[b, : (50 if b == 3 else 80)]) for b in range(12)],
        [np.asarray(data.u[b, : (50 if b == 3 else 80)]) for b in range(12)],
        order=3,
        horizon=5,
    )
    np.testing.assert_allclose(np.asarray(fit_sid(padded, state_dim=3, horizon=5).A), direct.A)


def test_fit_sid_bad_inputs():
    _, data = _data(4, 40)
    mask = np.ones((4, 40, 2), bool)
    mask[1, 10, 0] = False
    with pytest.raises(ValueError, match="complete records"):
        fit_sid(ceemx.Trajectories(data.y, data.u, jnp.asarray(mask)), state_dim=2)
    mask = np.ones((4, 40), bool)
    mask[2, 5] = False
    with pytest.raises(ValueError, match="inside trajectory 2"):
        fit_sid(ceemx.Trajectories(data.y, data.u, jnp.asarray(mask)), state_dim=2)
    with pytest.raises(TypeError, match="Trajectories"):
        fit_sid(np.asarray(data.y), state_dim=2)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="subset_size"):
        fit_sid(data, state_dim=2, subsets=2, subset_size=5)
    with pytest.raises(ValueError, match="subsets"):
        fit_sid(data, state_dim=2, subsets=0)
    with pytest.raises(ValueError, match="too large"):
        fit_sid(data, state_dim=9, horizon=4)


def test_docstring_examples():
    import ceemx.baselines.sid
    import ceemx.lib.subspace

    for module in (ceemx.lib.subspace, ceemx.baselines.sid):
        failed, attempted = doctest.testmod(module, verbose=False)
        assert attempted > 0 and failed == 0


def _simulate_affine(A, B, C, D, u, x0, c_x=0.0, c_y=0.0):
    x, ys = x0.copy(), []
    for t in range(u.shape[0]):
        ys.append(C @ x + D @ u[t] + c_y)
        x = A @ x + B @ u[t] + c_x
    return np.array(ys)


def test_stabilize_refits_b_d_x0_exactly_and_projects_unstable_a():
    """At the true stable (A, C), the simulation-error refit recovers B, D and x₀ exactly (the
    regression is exact on noise-free data); an unstable A comes back with spectral radius
    0.999, real."""
    from ceemx.lib.output_error import spectral_radius, stabilize

    rng = np.random.default_rng(0)
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    B, C, D = np.array([[1.0], [0.5]]), np.array([[1.0, 0.3]]), np.array([[0.2]])
    us = [rng.standard_normal((200, 1)) for _ in range(3)]
    x0s = rng.standard_normal((3, 2))
    ys = [_simulate_affine(A, B, C, D, u, x0) for u, x0 in zip(us, x0s, strict=True)]
    A2, B2, D2, x02 = stabilize(A, 0 * B, C, 0 * D, us, ys)
    np.testing.assert_allclose(A2, A, atol=1e-14)
    np.testing.assert_allclose(B2, B, atol=1e-12)
    np.testing.assert_allclose(D2, D, atol=1e-12)
    np.testing.assert_allclose(x02, x0s, atol=1e-10)
    unstable = np.array([[1.2, 0.3], [0.0, 0.5]])
    A3, *_ = stabilize(unstable, B, C, D, us, ys)
    assert spectral_radius(A3) == pytest.approx(0.999, abs=1e-12)
    assert np.isrealobj(A3)
    np.testing.assert_allclose(np.sort(np.abs(np.linalg.eigvals(A3))), [0.5, 0.999], atol=1e-12)


def test_affine_sid_recovers_an_offset_system():
    """Data with a constant drive and an output offset (levels around 5): the affine N4SID model
    (centred N4SID, then B, D with the constant channel refitted) simulates held-out data to
    rounding, where plain N4SID on the raw data cannot represent the offset."""
    import jax.numpy as jnp

    import ceemx
    from ceemx.baselines import fit_affine_sid, with_constant_input

    rng = np.random.default_rng(1)
    A = np.array([[0.9, 0.1], [0.0, 0.7]])
    B, C, D = np.array([[0.5], [1.0]]), np.array([[1.0, 0.5]]), np.array([[0.0]])
    u = 2.0 + rng.standard_normal((2, 400, 1))
    y = np.stack(
        [_simulate_affine(A, B, C, D, u[b], np.zeros(2), c_x=0.3, c_y=5.0) for b in range(2)]
    )
    train = ceemx.Trajectories(jnp.asarray(y[:1]), jnp.asarray(u[:1]))
    model = fit_affine_sid(train, state_dim=2)
    assert model.input_dim == 2
    ones = np.asarray(
        with_constant_input(ceemx.Trajectories(jnp.asarray(y[1:]), jnp.asarray(u[1:]))).u[0]
    )
    # the held-out record: zero-state response plus the least-squares initial response (the
    # constant channel lets the model's state carry an offset the truth's does not)
    mA, mB, mC, mD = (np.asarray(m) for m in (model.A, model.B, model.C, model.D))
    sim = _simulate_affine(mA, mB, mC, mD, ones, np.zeros(2))
    obs = np.stack([mC @ np.linalg.matrix_power(mA, t) for t in range(len(ones))])
    x0 = np.linalg.lstsq(obs.reshape(-1, 2), (y[1] - sim).reshape(-1), rcond=None)[0]
    sim = sim + obs @ x0
    assert float(np.max(np.abs(sim - y[1]))) < 1e-6 * float(np.std(y))


def test_refine_linear_refuses_bad_input():
    """refine_linear names the argument and the problem before any compute."""
    import jax.numpy as jnp

    import ceemx
    from ceemx.baselines import refine_linear, with_constant_input
    from ceemx.systems import LinearSystem

    model = LinearSystem(np.eye(2) * 0.5, np.ones((1, 2)), np.ones((2, 2)), np.zeros((1, 2)))
    data = ceemx.Trajectories(jnp.ones((1, 20, 1)).at[0, ::2].set(2.0), jnp.ones((1, 20, 1)))
    with pytest.raises(TypeError, match="`model`"):
        refine_linear("A", with_constant_input(data))  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="`data`"):
        refine_linear(model, np.ones((1, 20, 1)))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="with_constant_input"):
        refine_linear(model, data)
    with pytest.raises(ValueError, match="`process_noise`"):
        refine_linear(model, with_constant_input(data), process_noise=0.0)
    with pytest.raises(ValueError, match="`obs_noise`"):
        refine_linear(model, with_constant_input(data), obs_noise=float("nan"))
    flat = ceemx.Trajectories(jnp.ones((1, 20, 1)), jnp.ones((1, 20, 1)))
    with pytest.raises(ValueError, match="vary"):
        refine_linear(model, with_constant_input(flat))


def test_output_spread_counts_observed_entries_per_output():
    """The noise scales of refine_linear: masked entries (stored as zeros) excluded, one spread
    per output (outputs in different units), the pooled one for an output never observed."""
    from ceemx.baselines.sid import output_spread

    rng = np.random.default_rng(3)
    y = np.stack([5.0 + rng.standard_normal((2, 50)), 100.0 * rng.standard_normal((2, 50)),
                  rng.standard_normal((2, 50))], axis=-1)  # fmt: skip
    mask = np.ones((2, 50, 3), bool)
    mask[1, 30:, :] = False  # padding of a shorter record
    mask[:, :, 2] = False  # an output never observed
    data = _masked_trajectories(y, mask)
    pooled, per = output_spread(data)
    observed = y[:, :, :2][mask[:, :, :2]]
    assert pooled == pytest.approx(np.std(observed), rel=1e-12)
    for j in range(2):
        assert per[j] == pytest.approx(np.std(y[:, :, j][mask[:, :, j]]), rel=1e-12)
    assert per[2] == pooled
    with pytest.raises(ValueError, match="vary"):
        output_spread(_masked_trajectories(np.ones((1, 10, 1)), np.ones((1, 10, 1), bool)))


def _masked_trajectories(y, mask):
    import ceemx
    from ceemx.lib.tree import as_jax

    return ceemx.Trajectories(as_jax(y), as_jax(np.ones(y.shape[:2] + (1,))), as_jax(mask))
