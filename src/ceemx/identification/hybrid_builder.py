"""Building a hybrid model from a record.

:func:`hybrid` wraps a physics model (:mod:`ceemx.systems.hybrid`) with learned terms whose input
and output normalisations come from a record: the states' mean and standard deviation (from given
states, typically the smoothed states of a physics fit, else the default start of
:func:`ceemx.fit`),
the inputs', the spread of the state increments per unit time (the vector field's scale) and the
outputs'. The output layers are zero, so the returned model equals the physics model.

Training it with early stopping on a validation record cut from the training record:
:class:`ceemx.evaluation.early_stopping.EarlyStopping`.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PRNGKeyArray

from ceemx.data.checks import prepare
from ceemx.data.trajectories import Trajectories
from ceemx.identification.initialize import warm_start_states
from ceemx.infra.options import check_bool, check_positive
from ceemx.models.system import AbstractContinuousSystem, AbstractSystem
from ceemx.systems.hybrid import Hybrid, HybridContinuous
from ceemx.systems.learned_term import check_mlp, learned_term

__all__ = ["hybrid"]


def _spread(a: np.ndarray, axis) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) along ``axis`` with a floor on the std (a constant column gets scale 1)."""
    mean = np.nanmean(a, axis=axis)
    std = np.nanstd(a, axis=axis)
    floor = 1e-6 * np.maximum(1.0, np.abs(mean))
    std = np.where(std > floor, std, np.where(np.abs(mean) > 0, np.abs(mean), 1.0))
    return mean, std


def hybrid(
    physics: AbstractSystem,
    data: Trajectories,
    *,
    states: Float[ArrayLike, "B T n"] | None = None,
    dynamics: bool | Sequence[int] = True,
    observation: bool | Sequence[int] = False,
    key: PRNGKeyArray | None = None,
    width: int = 16,
    depth: int = 2,
    activation: Callable = jnp.tanh,
    prior_std: float = 1.0,
    use_input: bool = True,
    lower: ArrayLike | None = None,
    upper: ArrayLike | None = None,
    bound_sharpness: float = 50.0,
) -> Hybrid | HybridContinuous:
    """``physics`` plus zero-initialised learned terms normalised from ``data`` (module notes).

    Args:
        physics: any :class:`~ceemx.AbstractSystem` or :class:`~ceemx.AbstractContinuousSystem`
            (typically the result of a physics fit).
        data: the training record(s) the statistics come from (as the model reads them: a
            first-order-hold model's stacked inputs).
        states: (B, T, n) states for the state statistics (e.g. ``result.states`` of the physics
            fit); ``None``: the default start of :func:`ceemx.fit` at ``physics``.
        dynamics: add a learned term to the transition (vector field for a continuous model):
            ``True`` on every state equation, or the indices of the equations it enters (e.g.
            ``(1,)``: the velocity equation of a mechanical model; keeps the hidden states'
            meaning, :class:`~ceemx.systems.learned_term.LearnedTerm`).
        observation: add a learned term to the observation (``True``, or output indices).
            With neither term, ``lower``/``upper`` must be given: the physics model with
            bounded states.
        key: PRNG key of the hidden layers (default ``PRNGKey(0)``).
        width: the MLPs' hidden width.
        depth: the MLPs' number of hidden layers.
        activation: the MLPs' hidden activation.
        prior_std: standard deviation of the weight-decay prior
            (:func:`ceemx.systems.learned_term.weight_decay`).
        use_input: whether the terms see the input u.
        lower: lower state bounds (a scalar or an n-vector; ``None``: unbounded).
        upper: upper state bounds (likewise).
        bound_sharpness: the bounds' projection sharpness in units of each state's scale.

    Returns:
        A :class:`~ceemx.systems.hybrid.HybridContinuous` for a continuous physics model, else a
        :class:`~ceemx.systems.hybrid.Hybrid`; at its initial weights it equals ``physics``.

    Raises:
        TypeError / ValueError: naming the argument — before any compute: a wrong physics or
            data type, data whose m or p differ from the model's, an activation that is not
            callable, a key that is not a PRNG key, no learned term asked for, a width or depth
            out of range or whose networks would not fit in memory, a non-positive prior σ or
            bound sharpness; then (after the default start's smoothing when ``states`` is
            None): states of the wrong shape or not finite, indices out of range, NaN or
            crossed bounds.
    """
    inputs = _checked(physics, data, activation, dynamics, observation, lower, upper)
    _check_network(inputs, width, depth, prior_std, use_input, bound_sharpness)
    k_dyn, k_obs = _split_key(key)
    x = _state_record(inputs, states)
    continuous = isinstance(physics, AbstractContinuousSystem)
    mlp = dict(width=width, depth=depth, activation=activation, prior_std=prior_std)
    common = {**_normalisation(x, inputs.data, physics), **mlp, "use_input": use_input}
    dyn = obs = None
    if dynamics is not False:
        dt = physics.dt if continuous else None  # a vector field's scale is per unit time
        dyn = _dynamics_term(k_dyn, x, dynamics, dt, common)
    if observation is not False:
        obs = _observation_term(k_obs, inputs.data, observation, physics.obs_dim, common)
    cls = HybridContinuous if continuous else Hybrid
    return cls(physics, dyn, obs, lower=lower, upper=upper, bound_sharpness=bound_sharpness)  # type: ignore[arg-type]


def _checked(physics, data, activation, dynamics, observation, lower, upper):
    """The prepared inputs, after the checks that need no compute (named errors)."""
    if not isinstance(physics, AbstractSystem):
        raise TypeError(f"`physics` must be a ceemx.AbstractSystem; got {type(physics).__name__}.")
    if not isinstance(data, Trajectories):
        raise TypeError(f"`data` must be ceemx.Trajectories; got {type(data).__name__}.")
    inputs = prepare(physics, data)  # m, p, dtype: named errors before any statistics
    if not callable(activation):
        raise TypeError(f"`activation` must be a callable (e.g. jnp.tanh); got {activation!r}.")
    if dynamics is False and observation is False and lower is None and upper is None:
        raise ValueError(
            "ask for at least one learned term (`dynamics` and/or `observation`) or for state "
            "bounds (`lower`/`upper`: the physics model with bounded states)."
        )
    return inputs


def _check_network(inputs, width, depth, prior_std, use_input, bound_sharpness) -> None:
    """The networks' options, and their size against the memory, before any compute."""
    check_positive("prior_std", prior_std)
    check_bool("use_input", use_input)
    check_positive("bound_sharpness", bound_sharpness)
    system = inputs.system
    n_in = system.state_dim + (system.input_dim if use_input else 0)
    out = max(system.state_dim, system.obs_dim)  # the larger of the two terms
    check_mlp(width, depth, n_in, out, np.dtype(inputs.data.y.dtype).itemsize)


def _split_key(key: PRNGKeyArray | None) -> tuple[PRNGKeyArray, PRNGKeyArray]:
    """The keys of the dynamics and the observation terms (default ``PRNGKey(0)``)."""
    key = jax.random.PRNGKey(0) if key is None else key
    try:
        k_dyn, k_obs = jax.random.split(key)
    except (TypeError, ValueError):
        raise TypeError(f"`key` must be a JAX PRNG key (jax.random.key(0)); got {key!r}.") from None
    return k_dyn, k_obs


def _state_record(inputs, states) -> np.ndarray:
    """(B, T, n) float states: given and checked, or the default start of :func:`ceemx.fit`."""
    data, n = inputs.data, inputs.system.state_dim
    if states is None:
        states = warm_start_states(inputs.system, inputs.data)
    x = np.asarray(states, dtype=float)
    if x.ndim != 3 or x.shape[:2] != (data.batch_size, data.num_steps) or x.shape[2] != n:
        raise ValueError(
            f"`states` must have shape (B, T, n) = ({data.batch_size}, {data.num_steps}, {n}); "
            f"got {x.shape}."
        )
    if not np.all(np.isfinite(x)):
        raise ValueError("`states` must be finite.")
    return x


def _normalisation(x: np.ndarray, data: Trajectories, physics: AbstractSystem) -> dict[str, Any]:
    """The learned terms' input normalisation (the states' and inputs' mean and spread), dtype.

    A continuous model reads its first ``control_dim`` input channels (a first-order-hold
    model's stacked inputs carry the next step's too).
    """
    n = x.shape[-1]
    x_mean, x_scale = _spread(x.reshape(-1, n), 0)
    u = np.asarray(data.u, dtype=float)
    if isinstance(physics, AbstractContinuousSystem):
        u = u[..., : physics.control_dim]
    p = u.shape[-1]
    u_mean, u_scale = _spread(u.reshape(-1, p), 0) if p else (np.zeros(0), np.zeros(0))
    dtype = jnp.asarray(data.y).dtype
    return dict(x_mean=x_mean, x_scale=x_scale, u_mean=u_mean, u_scale=u_scale, dtype=dtype)


def _dynamics_term(key, x: np.ndarray, spec, dt: float | None, common: dict[str, Any]):
    """The transition's (vector field's) term, its output scaled by the state increments'."""
    n = x.shape[-1]
    step = np.diff(x, axis=1).reshape(-1, n)
    if dt is not None:
        step = step / dt
    _, out = _spread(step, 0)
    targets = _targets(spec, n, "dynamics")
    out = out if targets is None else out[list(targets)]
    return learned_term(key, out_scale=out, targets=targets, size=n, **common)


def _observation_term(key, data: Trajectories, spec, m: int, common: dict[str, Any]):
    """The observation's term, its output scaled by the observed outputs' spread."""
    y = np.where(np.asarray(data.mask), np.asarray(data.y, dtype=float), np.nan)
    _, out = _spread(y.reshape(-1, m), 0)
    targets = _targets(spec, m, "observation")
    out = out if targets is None else out[list(targets)]
    return learned_term(key, out_scale=out, targets=targets, size=m, **common)


def _targets(spec, size: int, name: str) -> tuple[int, ...] | None:
    if spec is True:
        return None
    try:
        if isinstance(spec, str | bytes):
            raise TypeError
        targets = tuple(operator.index(i) for i in spec)
    except TypeError:
        raise TypeError(
            f"`{name}` must be a bool or a sequence of indices; got {spec!r}."
        ) from None
    if not targets or len(set(targets)) != len(targets) or not all(0 <= i < size for i in targets):
        raise ValueError(f"`{name}` must be distinct indices in [0, {size}); got {spec!r}.")
    return targets
