"""Input validation: ceemx.Trajectories and the checks ceemx.smooth runs before any compilation.

Every error must be a ValueError (TypeError for a wrong type) naming the offending argument and,
for bad values, the first offending index. No test here compiles the smoother.
"""

import re

import equinox as eqx
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


# --------------------------------------------------------------------------------------------------
# A user's records: lists of different lengths, NaN as missing, metadata (DataInfo)
# --------------------------------------------------------------------------------------------------


def two_records():
    """Two records (40 and 25 samples) of a one-input, two-output linear system, with noise."""
    rng = np.random.default_rng(7)
    lengths = (40, 25)
    us = [rng.standard_normal((n, 1)) for n in lengths]
    ys = [
        np.cumsum(u, axis=0) * 0.1 + rng.standard_normal((n, 2))
        for u, n in zip(us, lengths, strict=True)
    ]
    model = LinearSystem(
        0.9 * jnp.eye(2), jnp.eye(2), B=jnp.array([[0.1], [0.05]]), D=jnp.zeros((2, 1))
    )
    return ys, us, model


def test_records_of_different_lengths_pad_and_mask_and_score_like_each_alone():
    ys, us, model = two_records()
    data = ceemx.Trajectories.from_arrays(ys, us)
    assert data.y.shape == (2, 40, 2) and data.u.shape == (2, 40, 1)
    mask = np.asarray(data.mask)
    assert mask[0].all() and mask[1, :25].all() and not mask[1, 25:].any()
    np.testing.assert_array_equal(np.asarray(data.u)[1, 25:, 0], us[1][-1, 0])  # input held
    alone = [ceemx.Trajectories.from_arrays(y, u) for y, u in zip(ys, us, strict=True)]
    x1 = jnp.asarray([[0.3, -0.2], [0.1, 0.4]])

    from ceemx.evaluation.metrics import simulation_rmse

    both = simulation_rmse(model, data, x1)
    each = [simulation_rmse(model, d, x1[b : b + 1]) for b, d in enumerate(alone)]
    np.testing.assert_allclose(both.per_trajectory, [float(e.overall) for e in each], rtol=1e-12)
    counts = np.array([40 * 2, 25 * 2])  # the real samples only, not the padding
    combined = np.sqrt(
        sum(c * float(e.overall) ** 2 for c, e in zip(counts, each, strict=True)) / counts.sum()
    )
    np.testing.assert_allclose(float(both.overall), combined, rtol=1e-12)

    score = ceemx.benchmark_score(model, data, 5, x1=x1)
    for b, d in enumerate(alone):
        one = ceemx.benchmark_score(model, d, 5, x1=x1[b : b + 1])
        for field in ("rmse", "nrmse", "fit_percent", "rmse_overall"):
            np.testing.assert_allclose(getattr(score, field)[b], getattr(one, field)[0], rtol=1e-12)


def test_record_lists_refuse_mismatches():
    with raises("2 records of `y` but 1 of `u`"):
        ceemx.Trajectories.from_arrays([np.ones(5), np.ones(3)], [np.ones(5)])
    with raises("the records have different numbers of outputs: [1, 2]"):
        ceemx.Trajectories.from_arrays([np.ones(5), np.ones((3, 2))])
    with raises("record 1: `u` has 4 samples, `y` 3"):
        ceemx.Trajectories.from_arrays([np.ones(5), np.ones(3)], [np.ones(5), np.ones(4)])
    with raises("`y` must have T >= 2 time steps"):  # every record is validated as a batch
        ceemx.Trajectories.from_arrays([np.ones(1)])


def test_nan_outputs_are_missing_and_nan_inputs_are_refused():
    y = np.arange(12.0).reshape(6, 2)
    y[2, 1] = y[4, :] = np.nan
    data = ceemx.Trajectories.from_arrays(y, np.ones(6))
    mask = np.asarray(data.mask)[0]
    assert mask.sum() == 12 - 3 and not mask[2, 1] and not mask[4].any() and mask[2, 0]
    assert np.all(np.isfinite(data.y)) and float(data.y[0, 4, 0]) == 0.0
    given = np.ones((6, 2), bool)
    given[0, 0] = False  # a given mask is kept, the NaN added to it
    assert np.asarray(ceemx.Trajectories.from_arrays(y, mask=given).mask)[0].sum() == 12 - 4
    u = np.ones(6)
    u[3] = np.nan
    with raises("`u` is NaN at record 0, step 3, input 0"):
        ceemx.Trajectories.from_arrays(np.ones(6), u)
    y[1, 0] = np.inf  # an infinite output is an error, not a gap
    with raises("`y` has a non-finite value inf at unmasked index [0, 1, 0]"):
        ceemx.Trajectories.from_arrays(y)
    with raises("`y` has a non-finite value nan"):  # the constructor itself stays strict
        ceemx.Trajectories(np.full((1, 3, 1), np.nan))


def test_data_info_travels_with_the_data_and_does_not_retrace_jit():
    from ceemx import DataInfo
    from ceemx.baselines.sid import with_constant_input

    ys, us, _ = two_records()
    data = ceemx.Trajectories.from_arrays(
        ys, us, dt=0.5, output_names=["h1", "h2"], output_units=["V", "V"], input_names="pump"
    )
    info = data.info
    assert info == DataInfo(0.5, "s", ("h1", "h2"), ("V", "V"), ("pump",), None)
    assert info.output_labels(2) == ("h1 [V]", "h2 [V]") and info.input_labels(1) == ("pump",)
    for derived in (data[1], data[:1], data.windows(10, 5), data.head(8)):
        assert derived.info is info
    assert data.with_info(dt=0.25).info.output_names == ("h1", "h2")
    foh = ceemx.foh_inputs(data).info
    assert foh.input_names == ("pump", "pump (next)") and foh.dt == 0.5
    assert with_constant_input(data).info.input_names == ("pump", "constant")
    assert jax.jit(lambda d: d)(data).info == info  # a static field: through jit unchanged

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def total(d):
        return jnp.sum(d.y)

    total(data)
    total(ceemx.Trajectories.from_arrays([y + 1.0 for y in ys], us, **_kwargs(info)))
    with raises("`output_names` has 1 entries but the data have 2 outputs"):
        data.with_info(output_names="h")
    with raises("`dt` must be a positive finite sample time"):
        DataInfo(dt=0.0)
    assert DataInfo.from_dict(info.to_dict()) == info


def _kwargs(info):
    return dict(
        dt=info.dt,
        output_names=info.output_names,
        output_units=info.output_units,
        input_names=info.input_names,
    )


def test_benchmark_score_prints_the_output_names_and_units():
    ys, us, model = two_records()
    data = ceemx.Trajectories.from_arrays(
        ys, us, output_names=["h1", "h2"], output_units=["V", "V"]
    )
    x1 = jnp.zeros((2, 2))
    text = str(ceemx.benchmark_score(model, data, 5, x1=x1))
    assert "h1 [V]" in text and "h2 [V]" in text and "y1" not in text
    scaled = str(ceemx.benchmark_score(model, data, 5, x1=x1, scale=1000.0))
    assert "h1 " in scaled and "[V]" not in scaled  # scaled errors: not in the data's unit


def test_data_docstring_examples_run():
    import doctest

    from ceemx.data import info, trajectories

    for module in (info, trajectories):
        failed, attempted = doctest.testmod(module, verbose=False)
        assert attempted >= 1 and failed == 0, module.__name__


def test_observation_free_data_is_refused():
    """y of shape (B, T, 0) was accepted: no observation to fit."""
    with raises("`y` has shape (2, 5, 0): no observed components (m = 0)"):
        ceemx.Trajectories(np.zeros((2, 5, 0)))
