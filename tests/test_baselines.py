"""The regression baselines: causality, learning known maps, training bookkeeping, errors."""

import doctest

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ceemx import Trajectories
from ceemx.baselines import (
    LagRegressor,
    LSTMRegressor,
    TrainInfo,
    fit_lag,
    fit_lstm,
    fit_naive,
    train_regressor,
)

SMALL: dict = dict(width=16, depth=2)  # the authors' 8 × 32 network is the default; tiny here
FAST: dict = dict(lr=1e-2, lr_decay=1000.0, batch_size=64)


def _lagged_data(key, B, T=24):
    """y_t = sin(2 u_{t−2,0}) + 0.5 u_{t,1}: needs the input two steps back."""
    u = jax.random.normal(key, (B, T, 2))
    past = jnp.concatenate([jnp.zeros((B, 2, 1)), u[:, :-2, :1]], axis=1)
    return Trajectories(jnp.sin(2.0 * past) + 0.5 * u[..., 1:], u)


def _filter_data(key, B, T=24):
    """y_t = 0.9 y_{t−1} + u_t (a first-order filter: a hidden state in y's past)."""
    u = 0.3 * jax.random.normal(key, (B, T, 1))

    def step(y, ut):
        y = 0.9 * y + ut
        return y, y

    _, y = jax.lax.scan(step, jnp.zeros((B, 1)), jnp.swapaxes(u, 0, 1))
    return Trajectories(jnp.swapaxes(y, 0, 1), u)


def _rmse(model, data, start):
    err = np.asarray(model.predict(data) - data.y)[:, start:]
    return float(np.sqrt(np.mean(err**2)))


@pytest.fixture(scope="module")
def lagged():
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    return _lagged_data(k1, 32), _lagged_data(k2, 8)


@pytest.fixture(scope="module")
def lag_fits(lagged):
    train, valid = lagged
    key = jax.random.PRNGKey(1)
    h1 = fit_naive(train, valid, epochs=12, key=key, **SMALL, **FAST)
    h3 = fit_lag(train, valid, lags=3, epochs=12, key=key, **SMALL, **FAST)
    return h1, h3


# ---- causality ------------------------------------------------------------------------------


def _perturbed(data, *, y=None, u=None):
    return Trajectories(data.y if y is None else y, data.u if u is None else u, data.mask)


@pytest.mark.parametrize("kind", ["lag", "lstm"])
def test_predictions_are_causal(kind, request):
    key = jax.random.PRNGKey(3)
    H = 3
    if kind == "lag":
        # The fitted lag-3 model of the module fixture on the validation record's shape: its
        # prediction program is the one the learning tests compile.
        _, (model, _) = request.getfixturevalue("lag_fits")
        assert isinstance(model, LagRegressor) and model.lags == H
        data = _lagged_data(key, 8)
    else:
        data = _lagged_data(key, 2, T=12)
        model = LSTMRegressor(2, 1, hidden=8, key=key)
    T = data.num_steps
    base = np.asarray(model.predict(data))
    assert base.shape == (data.batch_size, T, 1)
    # The observations are never read.
    noisy_y = _perturbed(data, y=data.y + 100.0 * jax.random.normal(key, data.y.shape))
    np.testing.assert_array_equal(np.asarray(model.predict(noisy_y)), base)
    # An input at step t changes steps t..t+H−1 (lag) or t..T−1 (LSTM), and nothing before t.
    t = 5
    changed = _perturbed(data, u=data.u.at[:, t].add(1.0))
    diff = np.abs(np.asarray(model.predict(changed)) - base).max(axis=(0, 2))
    affected = diff > 0
    expected = np.zeros(T, bool)
    expected[t : t + H] = True
    if kind == "lstm":
        expected[t:] = True
    np.testing.assert_array_equal(affected, expected)


# ---- learning -------------------------------------------------------------------------------


def test_lag_model_learns_a_lagged_map(lagged, lag_fits):
    _, valid = lagged
    (h1, info1), (h3, info3) = lag_fits
    r1, r3 = _rmse(h1, valid, 2), _rmse(h3, valid, 2)
    assert r3 < 0.5 * r1, (r1, r3)
    for info in (info1, info3):
        assert isinstance(info, TrainInfo)
        assert len(info.train_loss) == len(info.valid_loss) == len(info.epoch_s) == 12
        assert info.train_loss[-1] < info.train_loss[0]
        assert info.wall_s >= sum(info.epoch_s) * 0.99
    assert info3.train_loss[-1] < 0.8 * info3.train_loss[0]


def test_returned_model_is_the_best_validation_one(lagged, lag_fits):
    _, valid = lagged
    (_, _), (h3, info) = lag_fits
    assert info.best_epoch == int(np.argmin(info.valid_loss))
    # The authors' validation loss, recomputed: per step t ≥ H − 1, the RMS over trajectories.
    err = np.asarray(h3.predict(valid) - valid.y)[:, 2:, 0]
    again = np.mean(np.sqrt(np.mean(err**2, axis=0)))
    np.testing.assert_allclose(again, min(info.valid_loss), rtol=1e-10)


@pytest.mark.slow
def test_lstm_fits_a_filter_better_than_any_function_of_the_current_input():
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(4), 3)
    train, valid = _filter_data(k1, 32), _filter_data(k2, 8)
    lstm, info = fit_lstm(
        train, valid, hidden=8, layers=1, epochs=20, batch_size=8, lr=2e-2, key=k3
    )
    # The H = 1 model's best: y and u are jointly Gaussian, so E[y_t | u_t] is linear in u_t;
    # least squares on the validation data itself bounds every H = 1 model from below.
    u, y = np.asarray(valid.u).reshape(-1, 1), np.asarray(valid.y).reshape(-1)
    coef, *_ = np.linalg.lstsq(np.c_[u, np.ones_like(u)], y, rcond=None)
    r_h1 = float(np.sqrt(np.mean((np.c_[u, np.ones_like(u)] @ coef - y) ** 2)))
    r_lstm = _rmse(lstm, valid, 0)
    assert r_lstm < 0.6 * r_h1, (r_lstm, r_h1)
    assert info.train_loss[-1] < info.train_loss[0]


# ---- bookkeeping ----------------------------------------------------------------------------


def test_one_trace_and_deterministic(lagged, lag_fits):
    train, valid = lagged
    (h1, info1), _ = lag_fits
    assert info1.traces <= 1  # 12 epochs, at most one compilation
    again, info = fit_naive(train, valid, epochs=12, key=jax.random.PRNGKey(1), **SMALL, **FAST)
    assert info.traces == 0  # same shapes and settings: the compiled epoch is reused
    assert info.valid_loss == info1.valid_loss
    for a, b in zip(jax.tree_util.tree_leaves(h1), jax.tree_util.tree_leaves(again), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    _, other = fit_naive(train, valid, epochs=2, key=jax.random.PRNGKey(2), **SMALL, **FAST)
    assert other.valid_loss != info1.valid_loss[:2]


def test_float32_and_masked_entries(lagged):
    train, valid = lagged
    mask = np.ones(train.y.shape, bool)
    mask[:, ::3] = False
    y32 = np.where(mask, np.asarray(train.y), 1e6).astype(np.float32)  # masked: huge values
    train = Trajectories(y32, np.asarray(train.u, np.float32), mask)
    valid = Trajectories(np.asarray(valid.y, np.float32), np.asarray(valid.u, np.float32))
    model, info = fit_naive(train, valid, epochs=2, key=jax.random.PRNGKey(0), **SMALL, **FAST)
    assert model.predict(valid).dtype == jnp.float32
    assert all(np.isfinite(info.train_loss)) and max(info.train_loss) < 10


def test_bad_inputs(lagged):
    train, valid = lagged
    key = jax.random.PRNGKey(0)
    kw: dict = dict(epochs=1, key=key, **SMALL)
    with pytest.raises(TypeError, match="`train` must be a Trajectories"):
        fit_naive(np.asarray(train.y), valid, **kw)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="`valid` has input dimension"):
        fit_naive(train, Trajectories(valid.y, valid.u[..., :1]), **kw)
    with pytest.raises(ValueError, match="`loss`"):
        fit_naive(train, valid, loss="l1", **kw)
    with pytest.raises(ValueError, match="`epochs`"):
        fit_naive(train, valid, epochs=0, key=key)
    with pytest.raises(ValueError, match="`batch_size`"):
        fit_naive(train, valid, batch_size=0, **kw)
    with pytest.raises(ValueError, match="`lr`"):
        fit_naive(train, valid, lr=-1.0, **kw)
    with pytest.raises(ValueError, match="`scale`"):
        fit_naive(train, valid, scale=[1.0, 2.0], **kw)
    with pytest.raises(ValueError, match="nothing to fit"):
        fit_lag(train, valid, lags=train.num_steps + 1, **kw)
    with pytest.raises(TypeError, match="`key`"):
        fit_naive(train, valid, epochs=1, key=0)  # pyright: ignore[reportArgumentType]
    with pytest.raises(TypeError, match="`model`"):
        train_regressor(object(), train, valid, key=key)  # pyright: ignore[reportArgumentType]
    with pytest.raises(TypeError, match="fit_lag"):
        fit_naive(train, valid, lags=3, **kw)


def test_docstring_examples():
    import ceemx.baselines.recipes
    import ceemx.baselines.regressors

    for module in (ceemx.baselines.regressors, ceemx.baselines.recipes):
        failed, attempted = doctest.testmod(module, verbose=False)
        assert attempted > 0 and failed == 0, module.__name__
