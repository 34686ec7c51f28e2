"""Input validation: ceemx.Trajectories and the checks ceemx.smooth runs before any compilation.

Every error must be a ValueError (TypeError for a wrong type) naming the offending argument and,
for bad values, the first offending index. No test here compiles the smoother.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.systems import LinearSystem

B, T, M, P, N = 2, 5, 3, 1, 2


def y_ok():
    return np.random.default_rng(0).standard_normal((B, T, M))


def u_ok():
    return np.random.default_rng(1).standard_normal((B, T, P))


def raises(match):
    return pytest.raises(ValueError, match=re.escape(match))


# --------------------------------------------------------------------------------------------------
# Trajectories
# --------------------------------------------------------------------------------------------------


def test_valid_trajectories_are_normalised():
    y = y_ok()
    data = ceemx.Trajectories(y, u_ok())
    assert data.y.shape == (B, T, M) and data.u.shape == (B, T, P)
    assert data.mask.shape == (B, T, M) and data.mask.dtype == jnp.bool_ and bool(data.mask.all())
    assert (data.batch_size, data.num_steps, data.obs_dim, data.input_dim) == (B, T, M, P)
    assert ceemx.Trajectories(y).u.shape == (B, T, 0)
    np.testing.assert_array_equal(data.y, y)


@pytest.mark.parametrize("shape", [(T, M), (B, T, M, 1), (M,)])
def test_y_wrong_rank(shape):
    with raises(f"`y` must have shape (B, T, m); got rank {len(shape)}"):
        ceemx.Trajectories(np.zeros(shape))


@pytest.mark.parametrize("shape", [(B, T), (B, T, P, 1)])
def test_u_wrong_rank(shape):
    with raises(f"`u` must have shape (B, T, p); got rank {len(shape)}"):
        ceemx.Trajectories(y_ok(), np.zeros(shape))


def test_u_mismatched_batch():
    with raises(f"`u` has batch size {B + 1} but `y` has B = {B}"):
        ceemx.Trajectories(y_ok(), np.zeros((B + 1, T, P)))


def test_u_mismatched_steps():
    with raises(f"`u` has {T - 1} time steps but `y` has T = {T}"):
        ceemx.Trajectories(y_ok(), np.zeros((B, T - 1, P)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf], ids=["nan", "inf", "-inf"])
def test_nonfinite_unmasked_y(bad):
    y = y_ok()
    y[1, 3, 2] = bad
    y[1, 4, 0] = bad  # a later one: the first offending index is reported
    with raises("`y` has a non-finite value") as info:
        ceemx.Trajectories(y)
    assert "[1, 3, 2]" in str(info.value)
    # Masking only the later entry is not enough.
    mask = np.ones((B, T, M), bool)
    mask[1, 4, 0] = False
    with raises("at unmasked index [1, 3, 2]"):
        ceemx.Trajectories(y, mask=mask)


def test_nonfinite_masked_y_is_accepted():
    y = y_ok()
    y[0, 1, 2] = np.nan
    y[1, 2] = np.inf  # a whole step
    mask = np.ones((B, T, M), bool)
    mask[0, 1, 2] = False
    mask[1, 2] = False
    data = ceemx.Trajectories(y, mask=mask)
    assert np.all(np.isfinite(np.asarray(data.y)))
    assert float(data.y[0, 1, 2]) == 0.0 and np.all(np.asarray(data.y[1, 2]) == 0.0)
    np.testing.assert_array_equal(data.mask, mask)
    # The same with a per-step (B, T) mask, which is broadcast over the dimensions.
    step_mask = np.ones((B, T), bool)
    step_mask[0, 1] = step_mask[1, 2] = False
    data = ceemx.Trajectories(y, mask=step_mask)
    assert data.mask.shape == (B, T, M)
    np.testing.assert_array_equal(data.mask, np.broadcast_to(step_mask[..., None], (B, T, M)))


@pytest.mark.parametrize("bad", [np.nan, np.inf], ids=["nan", "inf"])
def test_nonfinite_u(bad):
    u = u_ok()
    u[1, 2, 0] = bad
    u[1, 3, 0] = bad
    with raises("`u` has a non-finite value") as info:
        ceemx.Trajectories(y_ok(), u)
    assert "[1, 2, 0]" in str(info.value)


def test_empty_batch():
    with raises("`y` is an empty batch (B = 0)"):
        ceemx.Trajectories(np.zeros((0, T, M)))


@pytest.mark.parametrize("steps", [0, 1])
def test_too_few_steps(steps):
    with raises(f"`y` must have T >= 2 time steps; got T = {steps}"):
        ceemx.Trajectories(np.zeros((B, steps, M)))


def test_y_not_floating():
    with raises("`y` must be a floating-point array"):
        ceemx.Trajectories(np.zeros((B, T, M), np.int32))


@pytest.mark.parametrize(
    "shape", [(B, T, M + 1), (B + 1, T), (B, T - 1, M), (B,), (B, T, M, 1)], ids=str
)
def test_mask_wrong_shape(shape):
    expected = f"`mask` must have shape (B, T) = {(B, T)} or (B, T, m) = {(B, T, M)}; got {shape}"
    with raises(expected):
        ceemx.Trajectories(y_ok(), mask=np.ones(shape, bool))


@pytest.mark.parametrize("dtype", [np.float64, np.int32, np.uint8])
def test_mask_wrong_dtype(dtype):
    with raises("`mask` must be boolean"):
        ceemx.Trajectories(y_ok(), mask=np.ones((B, T, M), dtype))


def test_construction_inside_jit_skips_validation():
    mask = np.ones((B, T), bool)
    mask[0, 0] = False
    f = jax.jit(lambda y, mask: ceemx.Trajectories(y, mask=mask))
    data = f(jnp.asarray(y_ok()), jnp.asarray(mask))
    assert data.mask.shape == (B, T, M) and data.u.shape == (B, T, 0)
    assert np.all(np.asarray(data.y[0, 0]) == 0.0)


def test_getitem_keeps_batch_axis():
    data = ceemx.Trajectories(y_ok(), u_ok())
    assert data[0:1].y.shape == (1, T, M) and data[0:1].u.shape == (1, T, P)
    sub = data[np.array([1, 0])]
    assert sub.mask.shape == (B, T, M)
    np.testing.assert_array_equal(sub.y[0], data.y[1])


def test_getitem_integer_keeps_batch_axis():
    assert ceemx.Trajectories(y_ok())[0].y.shape == (1, T, M)


def test_head_keeps_the_first_steps_of_every_record():
    mask = np.ones((B, T, M), bool)
    mask[1, 2, 0] = False
    data = ceemx.Trajectories(y_ok(), u_ok(), jnp.asarray(mask))
    head = data.head(3)
    assert head.y.shape == (B, 3, M) and head.u.shape == (B, 3, P) and head.mask.shape == (B, 3, M)
    for got, full in ((head.y, data.y), (head.u, data.u), (head.mask, data.mask)):
        np.testing.assert_array_equal(got, np.asarray(full)[:, :3])
    assert not bool(head.mask[1, 2, 0])
    for bad in (1, T + 1, 2.0):
        with pytest.raises(ValueError, match="`steps` must be an integer in"):
            data.head(bad)


# --------------------------------------------------------------------------------------------------
# smooth: checks before any compilation
# --------------------------------------------------------------------------------------------------


def linear_system(**kw):
    args = dict(process_noise=0.1, obs_noise=0.2)
    args.update(kw)
    A = 0.5 * jnp.eye(N)
    C = jnp.asarray(np.random.default_rng(2).standard_normal((M, N)))
    return LinearSystem(A, C, **args)


def good_inputs():
    return linear_system(), ceemx.Trajectories(y_ok()), jnp.zeros((B, T, N))


@pytest.mark.parametrize("shape", [(B, T, N + 1), (B, T + 1, N), (B + 1, T, N), (T, N)], ids=str)
def test_smooth_x_init_wrong_shape(shape):
    system, data, _ = good_inputs()
    with raises(f"`x_init` must have shape (B, T, n) = {(B, T, N)}; got {shape}"):
        ceemx.smooth(system, data, jnp.zeros(shape))


@pytest.mark.parametrize("bad", [np.nan, np.inf], ids=["nan", "inf"])
def test_smooth_x_init_nonfinite(bad):
    system, data, x = good_inputs()
    x = x.at[1, 2, 1].set(bad).at[1, 4, 0].set(bad)
    with raises("`x_init` has a non-finite value at index [1, 2, 1]"):
        ceemx.smooth(system, data, x)


def test_smooth_x_init_dtype_mismatch_is_promoted():
    # ceemx.smooth promotes x_init (and data) to the system's dtype; check_inputs alone refuses.
    system, data, x = good_inputs()
    assert ceemx.smooth(system, data, x.astype(jnp.float32)).states.dtype == jnp.float64
    with raises("`x_init` has dtype float32"):
        ceemx.data.checks.check_inputs(system, data, x.astype(jnp.float32))


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(obs_noise=0.0), "`system.obs_noise.scale` must be positive; entry 0 is 0.0"),
        (dict(obs_noise=-0.2), "`system.obs_noise.scale` must be positive"),
        (dict(process_noise=-1.0), "`system.process_noise.scale` must be positive"),
        (
            dict(process_noise=jnp.asarray([0.1, 0.0])),
            "`system.process_noise.scale` must be positive; entry 1",
        ),
        (dict(obs_noise=np.nan), "`system.obs_noise.scale` must be finite"),
        (dict(process_noise=np.inf), "`system.process_noise.scale` must be finite"),
        (
            dict(process_noise=ceemx.CholeskyGaussian(jnp.asarray([[0.1, 0.0], [0.3, -0.1]]))),
            "`system.process_noise.chol diagonal` must be positive; entry 1",
        ),
        (dict(obs_noise=ceemx.StudentT(0.2, 0.0, M)), "`system.obs_noise.df` must be positive"),
        (dict(obs_noise=ceemx.StudentT(-0.2, 4.0, M)), "`system.obs_noise.scale` must be positive"),
        (
            dict(initial_prior=ceemx.GaussianPrior(jnp.zeros(N), ceemx.DiagonalGaussian(0.0, N))),
            "`system.initial_prior.noise.scale` must be positive",
        ),
    ],
    ids=[
        "obs-zero", "obs-negative", "process-negative", "process-vector", "obs-nan", "process-inf",
        "cholesky-diagonal", "student-df", "student-scale", "prior",
    ],
)  # fmt: skip
def test_smooth_invalid_noise(kw, match):
    _, data, x = good_inputs()
    with raises(match):
        ceemx.smooth(linear_system(**kw), data, x)


def test_smooth_obs_dim_mismatch():
    system, _, x = good_inputs()
    data = ceemx.Trajectories(np.zeros((B, T, M + 1)))
    with raises(f"`data.y` has m = {M + 1} but the system observes m = {M}"):
        ceemx.smooth(system, data, x)


def test_smooth_input_dim_mismatch():
    system, _, x = good_inputs()
    data = ceemx.Trajectories(y_ok(), u_ok())
    with raises(f"`data.u` has p = {P} but the system takes p = 0 inputs"):
        ceemx.smooth(system, data, x)


def test_smooth_data_not_trajectories():
    system, data, x = good_inputs()
    with pytest.raises(TypeError, match=re.escape("`data` must be a ceemx.Trajectories")):
        ceemx.smooth(system, data.y, x)


def test_observation_free_data_is_refused():
    """y of shape (B, T, 0) was accepted: no observation to fit."""
    with raises("`y` has shape (2, 5, 0): no observed components (m = 0)"):
        ceemx.Trajectories(np.zeros((2, 5, 0)))
