"""Training of the regression baselines: Adam on minibatches, decayed rate, best validation.

The authors' recipe (``experiments/heli/baselines.py`` and ``train_lstm.py``): Adam with learning
rate lr·d/(d + e) in epoch e (lr = 10⁻⁴, d = 1000), the "normalised RMS" loss and the network with
the best validation loss kept. Their loss (``compute_rms``) is, for a group of predictions, the root
of the mean over its entries of the squared errors (times per-output factors, the dataset's
``y_std``): for the lag models a group is one minibatch (all trajectories at one step t in their
code), for the LSTM one trajectory, averaged over the minibatch. Ours is the same with masked
entries left out of each mean.

Differences, on purpose: minibatches are random (trajectory, t) windows for the lag models (the
authors step through t = H−1, …, T−1 with all trajectories at that t) and random sets of whole
trajectories for the LSTM (the authors train it on windows of 25 steps from a zero state, with
targets shifted one step later than the inputs); we validate every epoch (they did every 100);
and epochs default to 100 (theirs: 5000 for the lag models, 1000 for the LSTM).

The paper's baselines built and trained this way: :mod:`ceemx.baselines.recipes`.

One epoch is one compiled function (``eqx.filter_jit``, a ``lax.scan`` over its minibatches), so
a fit compiles it once and never again across epochs; :attr:`TrainInfo.traces` counts the traces.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, PRNGKeyArray

from ceemx.baselines.lstm import LSTMRegressor
from ceemx.baselines.regressors import LagRegressor
from ceemx.data.arrays import back_like, on_host
from ceemx.data.trajectories import Trajectories
from ceemx.infra.compilation import jit
from ceemx.infra.options import INT32_MAX
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import no_type_check

__all__ = ["TrainInfo", "check_int", "check_training", "train_regressor", "validation_loss"]

LOSSES = ("nrms", "mse")
_ADAM = optax.scale_by_adam()  # one instance: a new one would be a new static argument (retrace)
_TRACES = {"epoch": 0}


@dataclass(frozen=True)
class TrainInfo:
    """The record of one :func:`train_regressor` run.

    Attributes:
        train_loss: per epoch, the mean minibatch loss.
        valid_loss: per epoch, the validation loss after it (see :func:`train_regressor`).
        best_epoch: index into ``valid_loss`` of the returned model (-1 if no epoch had a finite
            validation loss; the last model is returned then).
        wall_s: seconds of the whole run, compilation included.
        epoch_s: seconds per epoch (training and validation; the first includes compilation).
        traces: how often the compiled epoch function was traced during the run (≤ 1).
    """

    train_loss: list[float]
    valid_loss: list[float]
    best_epoch: int
    wall_s: float
    epoch_s: list[float]
    traces: int


# ---- losses ---------------------------------------------------------------------------------


def _safe_sqrt(x):
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _group_loss(resid, mask, scale, loss: str):
    """Loss of (G, K, m) residuals: nrms = mean over groups of the RMS within each group."""
    sq = jnp.where(mask, (resid * scale[None, None, :]) ** 2, 0.0)
    if loss == "mse":
        return sq.sum() / jnp.maximum(mask.sum(dtype=sq.dtype), 1)
    count = mask.sum(axis=(1, 2), dtype=sq.dtype)
    rms = _safe_sqrt(sq.sum(axis=(1, 2)) / jnp.maximum(count, 1))
    present = count > 0
    return jnp.where(present, rms, 0.0).sum() / jnp.maximum(present.sum(dtype=sq.dtype), 1)


def _minibatch_loss(model, arrays, rows, scale, loss: str):
    """Loss of one minibatch: ``rows`` are (trajectory, t) pairs (lag) or trajectories (LSTM)."""
    u, y, mask = arrays
    if isinstance(model, LagRegressor):
        H, p = model.lags, u.shape[-1]
        b, t = rows[:, 0], rows[:, 1]  # u is padded with H − 1 leading steps: window = u[b, t:t+H]
        windows = jax.vmap(
            lambda bi, ti: jax.lax.dynamic_slice(u, (bi, ti, jnp.zeros_like(ti)), (1, H, p))[0]
        )(b, t)
        pred = jax.vmap(model)(windows)
        return _group_loss((y[b, t] - pred)[None], mask[b, t][None], scale, loss)
    b = rows[:, 0]
    pred = jax.vmap(model)(u[b])
    return _group_loss(y[b] - pred, mask[b], scale, loss)


@jit
def _epoch(
    params, static, opt_state, key, lr, arrays, samples, scale, valid, *, batch, steps, loss, start
):
    """One epoch: ``steps`` Adam steps on random minibatches of ``samples`` (a ``lax.scan``).

    Returns the new parameters and optimiser state, the mean minibatch loss, and the validation
    loss of the new parameters (one compiled function for both).
    """
    _TRACES["epoch"] += 1
    N = samples.shape[0]
    reps = math.ceil(steps * batch / N)
    perms = [jax.random.permutation(k, N) for k in jax.random.split(key, reps)]
    order = jnp.concatenate(perms)[: steps * batch].reshape(steps, batch)

    def value(p, rows):
        return _minibatch_loss(eqx.combine(p, static), arrays, samples[rows], scale, loss)

    def step(carry, rows):
        p, state = carry
        val, grads = jax.value_and_grad(value)(p, rows)
        # optax (0.2.8) mixes its int32 step count with floats (adam's bias correction):
        # standard promotion for the transform, so that strict-promotion users can train.
        with jax.numpy_dtype_promotion("standard"):
            updates, state = _ADAM.update(grads, state, p)
        p = eqx.apply_updates(p, jax.tree_util.tree_map(lambda g: -lr * g, updates))
        return (p, state), val

    (params, opt_state), vals = jax.lax.scan(step, (params, opt_state), order)
    model = eqx.combine(params, static)
    return params, opt_state, vals.mean(), validation_loss(model, valid, scale, start, loss)


def validation_loss(model, data: Trajectories, scale, start: int, loss: str = "nrms"):
    """The validation loss: per step t ≥ ``start`` the loss over the trajectories, then the mean.

    For ``"nrms"`` (the authors' validation): the mean over the steps t ≥ ``start`` (with an
    observed entry) of sqrt(mean over the present (b, j) of (s_j (y_btj − ŷ_btj))²).
    """
    pred = model.predict(data)
    resid = jnp.swapaxes(data.y - pred, 0, 1)[start:]  # (T − start, B, m): a group per step
    mask = jnp.swapaxes(data.mask, 0, 1)[start:]
    return _group_loss(resid, mask, scale, loss)


# ---- host-side checks -----------------------------------------------------------------------


def _check_key(key) -> None:
    ok = isinstance(key, jax.Array) and (
        jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
        or (key.dtype == jnp.uint32 and key.shape == (2,))
    )
    if not ok:
        raise TypeError(f"`key` must be a JAX PRNG key (jax.random.key or PRNGKey); got {key!r}.")


def check_int(name: str, value, low: int = 1) -> int:
    """``value`` as an int in [``low``, 2**31 - 1]; a ValueError naming ``name`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"`{name}` must be an integer >= {low}; got {value!r}.")
    if value > INT32_MAX:
        raise ValueError(f"`{name}` must be an integer <= 2**31 - 1; got {value!r}.")
    return int(value)


def _check_data(name: str, data, p: int, m: int) -> None:
    if not isinstance(data, Trajectories):
        raise TypeError(f"`{name}` must be a Trajectories; got {type(data).__name__}.")
    if data.input_dim != p:
        raise ValueError(f"`{name}` has input dimension p = {data.input_dim}; the model has {p}.")
    if data.obs_dim != m:
        raise ValueError(f"`{name}` has m = {data.obs_dim} outputs; the model has {m}.")


def _samples(lags: int | None, data: Trajectories) -> np.ndarray:
    """Training samples: (trajectory, t) with t ≥ H − 1 and an observed y_t; or trajectories."""
    observed = np.array(np.any(np.asarray(data.mask), axis=-1), dtype=bool)  # (B, T)
    if lags is not None:
        observed[:, : lags - 1] = False
        rows = np.argwhere(observed).astype(np.int32)
        if rows.shape[0] == 0:
            raise ValueError(
                f"`train` has no step t >= H - 1 = {lags - 1} with an observed y "
                f"(T = {data.num_steps}); the lag-{lags} model has nothing to fit."
            )
        return rows
    rows = np.argwhere(np.any(observed, axis=1)).astype(np.int32)
    if rows.shape[0] == 0:
        raise ValueError("`train` has no observed y.")
    return rows


@dataclass(frozen=True)
class _Checked:
    epochs: int
    batch_size: int
    steps_per_epoch: int | None
    scale: np.ndarray
    valid_start: int
    samples: np.ndarray


def check_training(
    train,
    valid,
    p: int,
    m: int,
    *,
    lags: int | None,
    loss,
    lr,
    lr_decay,
    epochs,
    batch_size,
    key,
    steps_per_epoch=None,
    scale=None,
    valid_start=None,
) -> _Checked:
    """Host validation of everything :func:`train_regressor` takes (errors name the argument)."""
    _check_data("train", train, p, m)
    _check_data("valid", valid, p, m)
    if loss not in LOSSES:
        raise ValueError(f"`loss` must be one of {LOSSES}; got {loss!r}.")
    for name, val in (("lr", lr), ("lr_decay", lr_decay)):
        if not (
            isinstance(val, (int, float, np.floating))
            and not isinstance(val, bool)
            and math.isfinite(val)
            and val > 0
        ):
            raise ValueError(f"`{name}` must be a positive finite number; got {val!r}.")
    epochs = check_int("epochs", epochs)
    batch_size = check_int("batch_size", batch_size)
    if steps_per_epoch is not None:
        steps_per_epoch = check_int("steps_per_epoch", steps_per_epoch)
    _check_key(key)
    s = np.ones(m) if scale is None else np.asarray(scale, dtype=float)
    if s.shape not in ((), (m,)) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"`scale` must be {m} positive finite factors; got {scale!r}.")
    samples = _samples(lags, train)
    if valid_start is None:
        valid_start = 0 if lags is None else lags - 1
    if isinstance(valid_start, bool) or not 0 <= valid_start < valid.num_steps:
        raise ValueError(
            f"`valid_start` must be in [0, T = {valid.num_steps}) of `valid`; got {valid_start}."
        )
    return _Checked(
        epochs, batch_size, steps_per_epoch, np.broadcast_to(s, (m,)), int(valid_start), samples
    )


# ---- the training loop ----------------------------------------------------------------------


def _param_dtype(model: LagRegressor | LSTMRegressor):
    """The dtype of a regressor's parameters."""
    if isinstance(model, LSTMRegressor):
        return model.head.weight.dtype
    return model.mlp.layers[0].weight.dtype


def _cast_data(train: Trajectories, valid: Trajectories, lags: int | None, dtype):
    """(u, y, mask) of ``train`` and the ``valid`` data in ``dtype``; a lag model's u is padded.

    The padding is H − 1 leading copies of u₀, so that the window of step t is u[b, t:t+H].
    """
    u = train.u.astype(dtype)
    if lags is not None:
        host = on_host(u)  # NumPy on the host: no program per shape
        xp, a = (np, np.asarray(u)) if host else (jnp, u)
        padded = xp.concatenate([xp.repeat(a[:, :1], lags - 1, axis=1), a], axis=1)
        u = back_like(padded, u) if host else padded
    arrays = (u, train.y.astype(dtype), train.mask)
    return arrays, Trajectories(valid.y.astype(dtype), valid.u.astype(dtype), valid.mask)


def _train_epochs(run_epoch, params, opt_state, key, epochs: int):
    """``epochs`` epochs of ``run_epoch``; returns the best-validation parameters and the record.

    The parameters returned are those after the epoch with the lowest finite validation loss, or
    the last ones when no validation loss was finite.
    """
    traces0 = _TRACES["epoch"]
    train_losses, valid_losses, epoch_s = [], [], []
    best_params, best_loss, best_epoch = params, math.inf, -1
    t_start = time.perf_counter()
    for e, k in enumerate(jax.random.split(key, epochs)):
        t0 = time.perf_counter()
        params, opt_state, train_loss, v = run_epoch(params, opt_state, e, k)
        train_loss, v = float(train_loss), float(v)
        train_losses.append(train_loss)
        valid_losses.append(v)
        epoch_s.append(time.perf_counter() - t0)
        if math.isfinite(v) and v < best_loss:
            best_loss, best_params, best_epoch = v, params, e
    info = TrainInfo(
        train_losses,
        valid_losses,
        best_epoch,
        time.perf_counter() - t_start,
        epoch_s,
        _TRACES["epoch"] - traces0,
    )
    return (best_params if best_epoch >= 0 else params), info


@no_type_check
def train_regressor(
    model: LagRegressor | LSTMRegressor,
    train: Trajectories,
    valid: Trajectories,
    *,
    loss: str = "nrms",
    lr: float = 1e-4,
    lr_decay: float = 1000.0,
    epochs: int = 100,
    batch_size: int = 512,
    key: PRNGKeyArray,
    steps_per_epoch: int | None = None,
    scale: ArrayLike | None = None,
    valid_start: int | None = None,
) -> tuple[LagRegressor | LSTMRegressor, TrainInfo]:
    """Fit a regressor of y on u by Adam; returns the model with the best validation loss.

    Epoch e (0-based) takes ``steps_per_epoch`` Adam steps (moments kept across epochs) with
    learning rate lr·d/(d + e), d = ``lr_decay``, each on ``batch_size`` samples drawn without
    replacement: (trajectory, t) windows with t ≥ H − 1 and an observed y_t for a
    :class:`LagRegressor`, whole trajectories for an :class:`LSTMRegressor`. After each epoch the
    validation loss is computed; the parameters of the best epoch are returned.

    Args:
        model: the initial network (its parameter dtype is used; the data are cast to it).
        train: training trajectories (masked entries of y are left out of the loss).
        valid: validation trajectories.
        loss: ``"nrms"`` — the authors' normalised RMS: per group, the root of the masked mean of
            (s_j (y − ŷ))² (groups: the minibatch of windows; each trajectory for the LSTM; each
            step t for validation), averaged over groups — or ``"mse"``, the masked mean of
            (s_j (y − ŷ))².
        lr: Adam's initial learning rate (authors: 10⁻⁴).
        lr_decay: d in lr·d/(d + e) (authors: 1000).
        epochs: number of epochs (authors: 5000 lag models, 1000 LSTM; ours need far fewer
            steps per epoch to be useful, so callers choose).
        batch_size: samples per minibatch (clipped to the number of samples).
        key: PRNG key of the minibatch order; the fit is a deterministic function of it.
        steps_per_epoch: minibatches per epoch (default: one pass, ⌈samples / batch_size⌉).
        scale: (m,) per-output factors s_j (e.g. the dataset's ``y_std``, as the authors'
            loss); ``None``: 1.
        valid_start: first validation step (default H − 1 for a lag model, 0 for the LSTM).

    Returns:
        ``(best_model, info)`` with ``info`` a :class:`TrainInfo`.

    Raises:
        TypeError: a model of another class, data that is not :class:`Trajectories`, a bad key.
        ValueError: mismatched dimensions, a bad setting, or no training sample.
    """
    lags = _model_lags(model)
    c = check_training(
        train,
        valid,
        model.input_dim,
        model.output_dim,
        lags=lags,
        loss=loss,
        lr=lr,
        lr_decay=lr_decay,
        epochs=epochs,
        batch_size=batch_size,
        key=key,
        steps_per_epoch=steps_per_epoch,
        scale=scale,
        valid_start=valid_start,
    )
    params, static = eqx.partition(model, eqx.is_inexact_array)
    run_epoch = _EpochRunner.create(model, static, c, train, valid, lr, lr_decay, loss)
    best_params, info = _train_epochs(run_epoch, params, _ADAM.init(params), key, c.epochs)
    return eqx.combine(best_params, static), info


def _model_lags(model) -> int | None:
    """H of a :class:`LagRegressor`, ``None`` for an :class:`LSTMRegressor`; else raise."""
    if not isinstance(model, (LagRegressor, LSTMRegressor)):
        raise TypeError(
            f"`model` must be a LagRegressor or an LSTMRegressor; got {type(model).__name__}."
        )
    return model.lags if isinstance(model, LagRegressor) else None


@dataclass(frozen=True)
class _EpochRunner:
    """``(params, opt_state, e, key) -> (params, opt_state, train loss, valid loss)``: epoch e.

    Holds what every epoch of a run shares (the data in the parameters' dtype, the samples, the
    minibatch sizes); the learning rate is lr·d/(d + e).
    """

    static: Any
    arrays: tuple
    samples: Array
    scale: Array
    valid: Trajectories
    lr: float
    lr_decay: float
    dtype: Any
    batch: int
    steps: int
    loss: str
    start: int

    @classmethod
    def create(cls, model, static, c: _Checked, train, valid, lr, lr_decay, loss) -> _EpochRunner:
        """The runner of ``model``'s epochs on the checked arguments ``c``."""
        dtype = _param_dtype(model)
        scale = jnp.asarray(c.scale, dtype)
        batch = min(c.batch_size, c.samples.shape[0])
        steps = c.steps_per_epoch or math.ceil(c.samples.shape[0] / batch)
        arrays, valid = _cast_data(train, valid, _model_lags(model), dtype)
        samples = as_jax(c.samples)
        return cls(static, arrays, samples, scale, valid, lr, lr_decay, dtype, batch, steps,
                   loss, c.valid_start)  # fmt: skip

    def __call__(self, params, opt_state, e, k):
        rate = jnp.asarray(self.lr * self.lr_decay / (self.lr_decay + e), self.dtype)
        return _epoch(
            params,
            self.static,
            opt_state,
            k,
            rate,
            self.arrays,
            self.samples,
            self.scale,
            self.valid,
            batch=self.batch,
            steps=self.steps,
            loss=self.loss,
            start=self.start,
        )
