"""Tests for the start of a fit: ceemx.identification.initialize (warm_start, perturb) and
models.with_noise."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import ceemx
from ceemx.identification.initialize import from_observations, perturb, warm_start
from ceemx.models import CholeskyGaussian, DiagonalGaussian, with_noise
from ceemx.systems import CoupledLorenz, random_observation_matrix


def lorenz(dtype=jnp.float64):
    C = random_observation_matrix(jax.random.PRNGKey(0), 1).astype(dtype)
    p = [jnp.full((1,), v, dtype) for v in (10.0, 28.0, 8.0 / 3.0)]
    return CoupledLorenz(*p, C, process_noise=0.01, obs_noise=0.01)


def test_with_noise_generic_and_dtype():
    for dtype in (jnp.float32, jnp.float64):
        s = with_noise(lorenz(dtype), 0.5, 2.0)
        assert isinstance(s.process_noise, DiagonalGaussian) and s.process_noise.dim == 3
        assert s.process_noise.scale.dtype == dtype and s.obs_noise.scale.dtype == dtype
        assert float(s.process_noise.scale) == 0.5 and float(s.obs_noise.scale) == 2.0
    s = lorenz()
    full = CholeskyGaussian(jnp.eye(1))
    t = with_noise(s, obs_noise=full)  # a noise model as given; None keeps the current one
    assert eqx.tree_equal(t.obs_noise, full) and eqx.tree_equal(t.process_noise, s.process_noise)
    lin = ceemx.systems.LinearSystem(jnp.eye(2), jnp.ones((1, 2)))
    assert with_noise(lin, jnp.array([1.0, 2.0])).process_noise.std().shape == (2,)


def test_perturb():
    tree = {"a": jnp.array([1.0, -2.0, 0.0]), "i": jnp.array([3, 4]), "b": jnp.ones((2, 2))}
    out = perturb(jax.random.PRNGKey(0), tree, 0.1)
    a, b = np.asarray(tree["a"]), np.asarray(out["a"])
    assert np.all(np.abs(b - a) <= 0.1 * np.abs(a)) and b[2] == 0.0 and b[0] != a[0]
    np.testing.assert_array_equal(np.asarray(out["i"]), [3, 4])  # integers untouched
    only_b = perturb(jax.random.PRNGKey(0), tree, 0.1, where=lambda t: t["b"])
    assert only_b["a"] is tree["a"] and not np.allclose(np.asarray(only_b["b"]), 1.0)


def test_warm_start_fills_unobserved_direction():
    # x₂ is seen only through the dynamics: least squares leaves it at 0, the smoothing fills it.
    A = jnp.array([[0.9, 0.3], [-0.3, 0.9]])
    s = ceemx.systems.LinearSystem(A, jnp.array([[1.0, 0.0]]), process_noise=0.01, obs_noise=0.01)
    x1 = jnp.array([[1.0, 2.0], [-1.0, 0.5]])
    xs, data = ceemx.simulate(s, jax.random.PRNGKey(2), x1, 12, process_noise=False)
    x0 = from_observations(s, data)
    x = warm_start(s, data)
    assert x.shape == xs.shape and x.dtype == xs.dtype
    err0 = float(jnp.sqrt(jnp.mean((x0 - xs) ** 2)))
    err = float(jnp.sqrt(jnp.mean((x - xs) ** 2)))
    assert err < 0.5 * err0
    # The same as smoothing by hand with unit process noise.
    soft = eqx.tree_at(lambda m: m.process_noise, s, DiagonalGaussian(jnp.asarray(1.0), 2))
    np.testing.assert_allclose(
        np.asarray(x), np.asarray(ceemx.smooth(soft, data, x0).states), rtol=1e-12, atol=1e-12
    )
