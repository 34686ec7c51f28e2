"""One-step-ahead prediction: one interface for state-space models and regressors (paper §4.2.4).

Every model that predicts y_t from the inputs u_1, …, u_t and the earlier observations
y_1, …, y_{t−1} is an :class:`AbstractPredictor` with one method, ``predict(data)`` → (B, T, m).
A state-space model (any :class:`~ceemx.AbstractSystem`) predicts through the extended Kalman
filter (:class:`StateSpacePredictor`): at each step ŷ_t = g(x̂_{t|t−1}, u_t) is recorded before the
filter corrects x̂ with the measured y_t. Regressors of the inputs (:mod:`ceemx.baselines`)
implement ``predict`` directly. :class:`ResidualPredictor` adds a model of the residual
ỹ = y − base(u) to a base model, as the paper's SID, LSTM and NL models do.

:func:`prediction_rmse` is paper Eq. 15 as the authors' evaluation file computes it.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from ceemx.data.trajectories import Trajectories
from ceemx.inference.ekf import ekf
from ceemx.lib.typing import Observations
from ceemx.models.system import AbstractSystem, GaussianPrior

__all__ = [
    "AbstractPredictor",
    "BestValidation",
    "ResidualPredictor",
    "StateSpacePredictor",
    "as_predictor",
    "one_step_predictions",
    "prediction_rmse",
    "residual_data",
]


class AbstractPredictor(eqx.Module):
    """A one-step-ahead predictor: ŷ_t from u_{1:t} and y_{1:t−1}, for every t of every trajectory.

    Subclasses implement :meth:`predict`. ``predict`` must never read y_t (or later) to predict
    y_t; the tests of every predictor check this by perturbing y_t.
    """

    @abc.abstractmethod
    def predict(self, data: Trajectories) -> Observations:
        """(B, T, m) one-step predictions of ``data.y``."""


class StateSpacePredictor(AbstractPredictor):
    """A state-space model's one-step predictions by the extended Kalman filter.

    Attributes:
        system: the model; its noise models must be Gaussian (they are the filter's Q and R).
        initial: the filter's prior on x₁ (``None``: the system's ``initial_prior`` if it has one,
            else N(0, I) — the authors' evaluation).
    """

    system: AbstractSystem
    initial: GaussianPrior | None = None

    def predict(self, data: Trajectories) -> Observations:
        """ŷ_t = g(x̂_{t|t−1}, u_t), recorded before the correction with y_t."""
        return ekf(self.system, data, initial=self.initial).predicted_obs


class ResidualPredictor(AbstractPredictor):
    """ŷ = base(data) + residual(data with y replaced by y − base(data)).

    The residual model sees the base model's prediction errors ỹ = y − ŷ_base as its
    observations, exactly as it was trained (paper §4.2.2: SID, LSTM and NL model the naive
    model's residuals).

    Attributes:
        base: the model of y (e.g. the naive regressor).
        residual: the model of the base model's residual.
    """

    base: AbstractPredictor
    residual: AbstractPredictor

    def predict(self, data: Trajectories) -> Observations:
        """Base plus residual prediction."""
        base = self.base.predict(data)
        return base + self.residual.predict(residual_data(data, base))


def residual_data(data: Trajectories, predictions: Observations) -> Trajectories:
    """``data`` with observations y − ``predictions`` (same inputs and mask)."""
    return Trajectories(jnp.where(data.mask, data.y - predictions, 0.0), data.u, data.mask)


def as_predictor(model: AbstractPredictor | AbstractSystem) -> AbstractPredictor:
    """A predictor as is; a system wrapped in :class:`StateSpacePredictor`."""
    if isinstance(model, AbstractPredictor):
        return model
    if isinstance(model, AbstractSystem):
        return StateSpacePredictor(model)
    raise TypeError(
        f"`model` must be an AbstractPredictor or an AbstractSystem; got {type(model).__name__}."
    )


def one_step_predictions(model: AbstractPredictor | AbstractSystem, data: Trajectories):
    """(B, T, m) one-step predictions of ``data.y`` by ``model`` (a predictor or a system)."""
    if not isinstance(data, Trajectories):
        raise TypeError(f"`data` must be a Trajectories; got {type(data).__name__}.")
    return as_predictor(model).predict(data)


def prediction_rmse(
    predictions: ArrayLike,
    data: Trajectories,
    *,
    start: int = 25,
    scale: ArrayLike | None = None,
) -> Float[np.ndarray, " B"]:
    """Per-trajectory RMSE of one-step predictions (paper Eq. 15, the authors' evaluation).

    RMSE_b = sqrt( Σ_{t ≥ start, j} (s_j (y_btj − ŷ_btj))² / N_b ) with N_b the number of present
    (unmasked) entries from step ``start`` on: the mean over time steps *and* output components,
    as the authors' ``compute_rms`` (which the paper's Figure 4 numbers come from).

    Args:
        predictions: (B, T, m) predicted observations.
        data: the measured trajectories (mask respected).
        start: first scored time step, 0-based (authors: 25 — the H25 model needs 25 inputs).
        scale: (m,) factors s_j turning normalised units into physical ones (the dataset's
            ``y_std``); ``None``: 1.

    Returns:
        (B,) NumPy array; NaN for a trajectory with no present entry from ``start`` on.
    """
    pred = np.asarray(predictions)
    y = np.asarray(data.y)
    mask = np.asarray(data.mask)
    if pred.shape != y.shape:
        raise ValueError(f"`predictions` has shape {pred.shape}; the data's y has {y.shape}.")
    if not 0 <= start < y.shape[1]:
        raise ValueError(f"`start` must be in [0, T = {y.shape[1]}); got {start}.")
    s = np.ones(y.shape[-1]) if scale is None else np.broadcast_to(np.asarray(scale), y.shape[-1:])
    err = ((y - pred) * s)[:, start:] ** 2
    m = mask[:, start:]
    count = m.sum(axis=(1, 2))
    total = np.where(m, err, 0.0).sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.where(count > 0, total / np.maximum(count, 1), np.nan))


class BestValidation:
    """Fit callback: one-step prediction RMSE on validation data after every epoch; keeps the best.

    The authors' NL-model training kept the epoch with the best validation RMSE (an EM fit of a
    large model keeps improving J on the training data long after its predictions stop
    improving). Pass an instance in ``fit(..., callbacks=[...])``; the history gets
    ``val_rmse`` (mean over validation trajectories of :func:`prediction_rmse`) and, after the fit,
    :attr:`best_system`, :attr:`best_epoch` and :attr:`best_rmse` hold the winner.

    Args:
        valid: validation trajectories (in the units the model is fitted in).
        start: first scored step (:func:`prediction_rmse`).
        scale: per-output factors to physical units (:func:`prediction_rmse`).
        predictor: maps a system to the predictor to score (default :class:`StateSpacePredictor`;
            e.g. ``lambda s: ResidualPredictor(base, StateSpacePredictor(s))`` to score the full
            model of y when the system models a residual — then ``valid`` holds y itself).
        initial_system: scored as epoch 0, so a fit that never beats its start returns the start.
    """

    def __init__(
        self,
        valid: Trajectories,
        *,
        start: int = 25,
        scale: ArrayLike | None = None,
        predictor=None,
        initial_system: AbstractSystem | None = None,
    ):
        self.valid = valid
        self.start = start
        self.scale = scale
        self.predictor = StateSpacePredictor if predictor is None else predictor
        self.best_system: AbstractSystem | None = None
        self.best_epoch = -1
        self.best_rmse = float("inf")
        self.rmse: list[float] = []
        if initial_system is not None:
            self._score(0, initial_system)

    def _score(self, epoch: int, system: AbstractSystem) -> float:
        pred = self.predictor(system).predict(self.valid)
        per = prediction_rmse(pred, self.valid, start=self.start, scale=self.scale)
        value = float(np.nanmean(per)) if np.isfinite(per).any() else float("inf")
        if value < self.best_rmse:
            self.best_rmse, self.best_epoch, self.best_system = value, epoch, system
        return value

    def __call__(self, info) -> dict:
        """Score ``info.system``; returns ``{"val_rmse": …}`` for the history."""
        value = self._score(info.epoch, info.system)
        self.rmse.append(value)
        return {"val_rmse": value}
