"""Tests for ceemx.evaluation.metrics: ε(θ) (paper Eq. 14), open-loop simulation RMSE, mean (SE),
callbacks.

Oracles: a NumPy implementation of the coupled-Lorenz vector field (Eq. 12) evaluated at the same
sampled states; exact zeros for identical systems and for noise-free data replayed from the true
initial states.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.evaluation import metrics as ev
from ceemx.models import AbstractContinuousSystem, DiagonalGaussian
from ceemx.systems import CoupledLorenz, initial_states, random_coupling, random_observation_matrix


def lorenz(K=2, sigma=10.0, rho=28.0, beta=8.0 / 3.0, key=0):
    kc, kh = jax.random.split(jax.random.PRNGKey(key))
    ones = jnp.ones((K,))
    return CoupledLorenz(
        sigma * ones,
        rho * ones,
        beta * ones,
        random_observation_matrix(kc, K),
        H=random_coupling(kh, K),
    )


def numpy_field(x, sigma, rho, beta, H, K):
    """Eq. 12 in NumPy for a batch of states x (N, 3K), own-attractor blocks of H ignored."""
    z = x.reshape(-1, K, 3)
    x1, x2, x3 = z[..., 0], z[..., 1], z[..., 2]
    dx = np.stack([sigma * (x2 - x1), x1 * (rho - x3) - x2, x1 * x2 - beta * x3], axis=-1).reshape(
        x.shape
    )
    mask = 1.0 - np.kron(np.eye(K), np.ones((3, 3)))
    return dx + x @ (H * mask).T


def test_dynamics_error_zero_for_identical_systems():
    s = lorenz()
    assert float(ev.dynamics_error(s, s)) == 0.0


def test_dynamics_error_matches_numpy():
    K = 2
    true = lorenz(K)
    est = eqx.tree_at(
        lambda s: (s.sigma, s.rho, s.beta, s.H),
        true,
        (
            jnp.array([10.5, 9.7]),
            jnp.array([27.0, 28.3]),
            jnp.array([2.5, 2.9]),
            true.H * 1.1 + 0.01,
        ),
    )
    key = jax.random.PRNGKey(7)
    eps = float(ev.dynamics_error(est, true, key=key, num=256, std=3.0))
    mean = np.tile([-6.0, -6.0, 24.0], K)
    x = mean[None, :] + 3.0 * np.asarray(jax.random.normal(key, (256, 3 * K), jnp.float64))
    f_est = numpy_field(
        x, np.array([10.5, 9.7]), np.array([27.0, 28.3]), np.array([2.5, 2.9]), np.asarray(est.H), K
    )
    f_true = numpy_field(x, 10.0, 28.0, 8.0 / 3.0, np.asarray(true.H), K)
    expected = np.mean((f_est - f_true) ** 2)
    assert eps > 1.0
    np.testing.assert_allclose(eps, expected, rtol=1e-12)


def test_dynamics_error_defaults_are_the_authors():
    """Default: 1024 samples from PRNGKey(4), std 5, mean (−6, −6, 24) per attractor."""
    true = lorenz(1)
    est = eqx.tree_at(lambda s: s.sigma, true, jnp.array([11.0]))
    x = np.array([-6.0, -6.0, 24.0])[None, :] + 5.0 * np.asarray(
        jax.random.normal(jax.random.PRNGKey(4), (1024, 3))
    )
    # Only the first component changes: Δẋ₁ = (11 − 10)(x₂ − x₁); mean over all 3·1024 entries.
    expected = np.sum((x[:, 1] - x[:, 0]) ** 2) / (3 * 1024)
    np.testing.assert_allclose(float(ev.dynamics_error(est, true)), expected, rtol=1e-12)


class _Decay(AbstractContinuousSystem):
    a: jax.Array
    process_noise: DiagonalGaussian
    obs_noise: DiagonalGaussian
    initial_prior: None
    dt: float = eqx.field(static=True)

    def __init__(self, a):
        self.a = jnp.asarray(a)
        self.process_noise = DiagonalGaussian(1.0, 2)
        self.obs_noise = DiagonalGaussian(1.0, 2)
        self.initial_prior = None
        self.dt = 0.1

    @property
    def state_dim(self):
        return 2

    @property
    def obs_dim(self):
        return 2

    def vector_field(self, x, u, t):
        return -self.a * x

    def observe(self, x, u, t):
        return x


def test_default_state_mean_is_a_system_hook():
    np.testing.assert_array_equal(
        np.asarray(lorenz(2).default_state_mean()), np.tile([-6.0, -6.0, 24.0], 2)
    )
    p32 = [jnp.full((1,), v, jnp.float32) for v in (10.0, 28.0, 2.5)]
    s32 = CoupledLorenz(*p32, jnp.ones((1, 3), jnp.float32))
    assert s32.default_state_mean().dtype == jnp.float32
    assert _Decay(1.0).default_state_mean() is None


def test_dynamics_error_generic_system_needs_mean():
    s1, s2 = _Decay(1.0), _Decay(2.0)
    with pytest.raises(ValueError, match="mean"):
        ev.dynamics_error(s1, s2)
    eps = float(ev.dynamics_error(s1, s2, mean=jnp.zeros(2), std=1.0, num=4096))
    # (−x + 2x)² = x², x ~ N(0, 1): mean ≈ 1.
    assert abs(eps - 1.0) < 0.1
    with pytest.raises(ValueError, match="shape"):
        ev.dynamics_error(s1, s2, mean=jnp.zeros(3))


def test_simulation_rmse_zero_on_noise_free_data():
    s = lorenz(2)
    x1 = initial_states(jax.random.PRNGKey(1), 3, 2)
    _, data = ceemx.simulate(s, jax.random.PRNGKey(2), x1, 40, process_noise=False, obs_noise=False)
    out = ev.simulation_rmse(s, data, x1)
    assert out.per_trajectory.shape == (3,)
    np.testing.assert_allclose(np.asarray(out.per_trajectory), 0.0, atol=1e-12)
    assert float(out.overall) <= 1e-12
    assert out.predictions.shape == data.y.shape


def test_simulation_rmse_respects_mask():
    s = lorenz(2)
    x1 = initial_states(jax.random.PRNGKey(1), 2, 2)
    _, data = ceemx.simulate(s, jax.random.PRNGKey(2), x1, 20, process_noise=False, obs_noise=False)
    y = np.asarray(data.y).copy()
    mask = np.ones(y.shape, bool)
    y[0, 5, 1] += 3.0
    mask[0, 5, 1] = False
    y[1, 7, 0] += 2.0  # observed: contributes
    masked = ceemx.Trajectories(jnp.asarray(y), mask=jnp.asarray(mask))
    out = ev.simulation_rmse(s, masked, x1)
    assert float(out.per_trajectory[0]) <= 1e-12
    np.testing.assert_allclose(
        float(out.per_trajectory[1]), 2.0 / np.sqrt(y.shape[1] * y.shape[2]), rtol=1e-9
    )
    n_obs = mask.sum()
    np.testing.assert_allclose(float(out.overall), 2.0 / np.sqrt(n_obs), rtol=1e-9)


def test_mean_se():
    est = ev.mean_se([1.0, 2.0, 3.0, 4.0])
    assert est.mean == 2.5 and est.n == 4
    np.testing.assert_allclose(est.se, np.std([1, 2, 3, 4], ddof=1) / 2.0)
    assert est.within(2.5) and not est.within(10.0)
    assert ev.mean_se([3.0]).se == 0.0
    with pytest.raises(ValueError):
        ev.mean_se([])


def test_dynamics_error_callback():
    true = lorenz(1)
    est = eqx.tree_at(lambda s: s.sigma, true, jnp.array([11.0]))
    printed = []
    cb = ev.DynamicsErrorCallback(true, name="e", printer=lambda info, e: printed.append(e))
    info = ceemx.EpochInfo(epoch=3, system=est, states=jnp.zeros((1, 2, 3)), record={"J": 0.0})
    out = cb(info)
    assert set(out) == {"e"} and isinstance(out["e"], float)
    assert out["e"] == float(ev.dynamics_error(est, true)) == cb.error(est)
    assert printed == [out["e"]]
    # Options of dynamics_error pass through.
    small = ev.DynamicsErrorCallback(true, num=8, std=1.0)
    assert small.error(est) == float(ev.dynamics_error(est, true, num=8, std=1.0))


def test_fit_timer_and_monotone():
    timer = ev.FitTimer().start()
    walls = [timer(None)["wall"] for _ in range(3)]
    assert walls == sorted(walls) and len(timer.per_epoch()) == 3
    np.testing.assert_allclose(sum(timer.per_epoch()), walls[-1])
    assert ev.is_monotone(1.0, [{"J": 2.0}, {"J": 2.0}, {"J": 3.0}])
    assert not ev.is_monotone(1.0, [{"J": 2.0}, {"J": 1.5}])
    assert ev.is_monotone(1.0, [])
