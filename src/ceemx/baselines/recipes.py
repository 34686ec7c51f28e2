"""The paper's neural baselines (§4.2.2), built and trained by the authors' recipe.

- :func:`fit_lag` — the lag-H model y_t = NN(u_{t−H+1:t}) (H = 25: *H25*);
- :func:`fit_naive` — the naive model y_t = NN(u_t) (H = 1);
- :func:`fit_lstm` — the LSTM on the inputs (in the paper, on the naive model's residual).

Each checks its arguments before building its network, then trains it by
:func:`ceemx.baselines.training.train_regressor` (Adam, decayed rate, best validation kept).
"""

from __future__ import annotations

import jax
from jaxtyping import PRNGKeyArray

from ceemx.baselines.lstm import LSTMRegressor
from ceemx.baselines.regressors import LagRegressor
from ceemx.baselines.training import TrainInfo, check_int, check_training, train_regressor
from ceemx.data.trajectories import Trajectories
from ceemx.lib.typing import no_type_check

__all__ = ["fit_lag", "fit_lstm", "fit_naive"]

_TRAIN_KWARGS = ("loss", "lr", "lr_decay", "steps_per_epoch", "scale", "valid_start")


def _precheck(train, valid, key, *, lags, epochs, batch_size, **kwargs) -> None:
    """Validate a fit's arguments before its network is built (errors name the argument)."""
    unknown = sorted(set(kwargs) - set(_TRAIN_KWARGS))
    if unknown:
        raise TypeError(f"unexpected arguments {unknown}; allowed: {_TRAIN_KWARGS}.")
    if not isinstance(train, Trajectories):
        raise TypeError(f"`train` must be a Trajectories; got {type(train).__name__}.")
    kwargs = {"loss": "nrms", "lr": 1e-4, "lr_decay": 1000.0, **kwargs}
    check_training(
        train,
        valid,
        train.input_dim,
        train.obs_dim,
        lags=lags,
        epochs=epochs,
        batch_size=batch_size,
        key=key,
        **kwargs,
    )


@no_type_check
def fit_lag(
    train: Trajectories,
    valid: Trajectories,
    *,
    lags: int = 25,
    width: int = 32,
    depth: int = 8,
    epochs: int = 100,
    batch_size: int = 512,
    key: PRNGKeyArray,
    **kwargs,
) -> tuple[LagRegressor, TrainInfo]:
    """The paper's lag-H model y_t = NN(u_{t−H+1:t}) (H = 25: *H25*) by the authors' recipe.

    Args:
        train: training trajectories; the model's dtype is ``train.y``'s.
        valid: validation trajectories (the best epoch on them is returned).
        lags: H (authors: 25).
        width: units per hidden layer (authors: 32).
        depth: hidden layers, tanh (authors: 8).
        epochs: epochs of one pass over the (trajectory, t) windows each (authors: 5000 epochs of
            T − H + 1 steps; the default is ours).
        batch_size: windows per minibatch (the authors' were the B trajectories at one t).
        key: PRNG key (initialisation and minibatches).
        **kwargs: further :func:`train_regressor` arguments (``loss``, ``lr``, ``lr_decay``,
            ``steps_per_epoch``, ``scale``, ``valid_start``).

    Returns:
        ``(model, info)``: the best-validation :class:`LagRegressor` and its :class:`TrainInfo`.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from ceemx import Trajectories
        >>> from ceemx.baselines import fit_lag
        >>> u = jax.random.normal(jax.random.PRNGKey(0), (4, 20, 2))
        >>> data = Trajectories(jnp.sin(u[..., :1]), u)
        >>> model, info = fit_lag(
        ...     data, data, lags=3, width=8, depth=2, epochs=2, key=jax.random.PRNGKey(1)
        ... )
        >>> model.predict(data).shape, len(info.valid_loss)
        ((4, 20, 1), 2)
    """
    _precheck(
        train,
        valid,
        key,
        lags=check_int("lags", lags),
        epochs=epochs,
        batch_size=batch_size,
        **kwargs,
    )
    k_init, k_train = jax.random.split(key)
    model = LagRegressor(
        train.input_dim,
        train.obs_dim,
        lags,
        width=width,
        depth=depth,
        dtype=train.y.dtype,
        key=k_init,
    )
    return train_regressor(  # pyright: ignore[reportReturnType]
        model, train, valid, epochs=epochs, batch_size=batch_size, key=k_train, **kwargs
    )


@no_type_check
def fit_naive(train: Trajectories, valid: Trajectories, **kwargs) -> tuple[LagRegressor, TrainInfo]:
    """The paper's naive model y_t = NN(u_t): :func:`fit_lag` with H = 1 (same arguments)."""
    if "lags" in kwargs:
        raise TypeError("`fit_naive` has H = 1; use `fit_lag` for other lags.")
    return fit_lag(train, valid, lags=1, **kwargs)


@no_type_check
def fit_lstm(
    train: Trajectories,
    valid: Trajectories,
    *,
    hidden: int = 32,
    layers: int = 2,
    epochs: int = 100,
    batch_size: int = 16,
    key: PRNGKeyArray,
    **kwargs,
) -> tuple[LSTMRegressor, TrainInfo]:
    """The paper's LSTM baseline (2 layers of 32, linear head, from u), by the authors' recipe.

    In the paper it models the naive model's residual: pass ``residual_data(train, naive(train))``
    and compose with :class:`ceemx.evaluation.prediction.ResidualPredictor`.

    Args:
        train: training trajectories; the model's dtype is ``train.y``'s.
        valid: validation trajectories (the best epoch on them is returned).
        hidden: units per layer (authors: 32).
        layers: LSTM layers (authors: 2).
        epochs: passes over the training trajectories (authors: 1000 epochs of 25-step windows;
            the default is ours).
        batch_size: whole trajectories per minibatch (ours; the authors' were all trajectories).
        key: PRNG key (initialisation and minibatches).
        **kwargs: further :func:`train_regressor` arguments.

    Returns:
        ``(model, info)``: the best-validation :class:`LSTMRegressor` and its :class:`TrainInfo`.
    """
    _precheck(train, valid, key, lags=None, epochs=epochs, batch_size=batch_size, **kwargs)
    k_init, k_train = jax.random.split(key)
    model = LSTMRegressor(
        train.input_dim,
        train.obs_dim,
        hidden=hidden,
        layers=layers,
        dtype=train.y.dtype,
        key=k_init,
    )
    return train_regressor(  # pyright: ignore[reportReturnType]
        model, train, valid, epochs=epochs, batch_size=batch_size, key=k_train, **kwargs
    )
