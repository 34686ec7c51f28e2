"""Models on measured data: free-run simulation and k-step prediction.

- :func:`free_run` — noise-free simulation x_{t+1} = f(x_t, u_t, t), y_t = g(x_t, u_t, t) from
  initial states and an input sequence (no measured output is used).
- :func:`predict_k_step` — ŷ_{t+k|t}: the extended Kalman filter's mean at t, then k noise-free
  steps.

The initial states a free run starts from are estimated from the first outputs by
:func:`ceemx.evaluation.initial_state.estimate_initial_state`;
:func:`ceemx.evaluation.metrics.benchmark_score` combines them into the official protocol of the
``nonlinear-benchmarks`` package. All work on a batch of B trajectories (``vmap``), ``lax.scan``
over time, and are compiled once per shape and system structure (numbers — parameters, data,
tolerances — are traced).
"""

from __future__ import annotations

import operator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ceemx.data.arrays import back_like, indexed, on_host
from ceemx.data.checks import prepare, promote_array, promote_tree
from ceemx.data.trajectories import Trajectories
from ceemx.inference.ekf import ekf_prepared
from ceemx.infra.compilation import jit
from ceemx.infra.options import INT32_MAX
from ceemx.infra.warn import warn
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import Inputs, Observations, States, no_type_check
from ceemx.models.method_check import check_methods, nonfinite_run
from ceemx.models.system import AbstractSystem, GaussianPrior

__all__ = [
    "check_finite_data",
    "check_int",
    "check_system",
    "free_run",
    "free_run_batch",
    "free_run_one",
    "k_step_batch",
    "predict_k_step",
    "strongly_typed",
]


# --------------------------------------------------------------------------------------------
# Host-side checks (before any compute)
# --------------------------------------------------------------------------------------------


def check_system(system) -> None:
    """``system`` is a :class:`ceemx.AbstractSystem`, or a TypeError."""
    if not isinstance(system, AbstractSystem):
        raise TypeError(f"`system` must be a ceemx.AbstractSystem; got {type(system).__name__}.")


def _finite(name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        idx = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(f"`{name}` has a non-finite value at index {list(idx)}.")


def check_int(name: str, value, low: int, high: int | None = None) -> int:
    """``value`` as an int in [low, high] (``None``: up to 2**31 - 1, JAX's int32 counts)."""
    try:
        if isinstance(value, bool):
            raise TypeError
        v = operator.index(value)
    except TypeError:
        raise TypeError(f"`{name}` must be an integer; got {value!r}.") from None
    if v < low or v > (INT32_MAX if high is None else high):
        bound = f"[{low}, {high}]" if high is not None else f"[{low}, 2**31 - 1]"
        raise ValueError(f"`{name}` must be in {bound}; got {v}.")
    return v


def strongly_typed(tree):
    """``tree`` with its weakly typed floating-point arrays made strongly typed (same dtype).

    ``jnp.asarray(0.1)`` is weakly typed and ``filter_jit`` keys its cache on weak types too: a
    system built from Python scalars and the same system with converted leaves would compile
    twice. Entry points pass systems through this first.
    """
    fix = lambda a: jnp.asarray(a, a.dtype) if eqx.is_inexact_array(a) else a  # noqa: E731
    return jax.tree_util.tree_map(fix, tree)


def check_finite_data(data: Trajectories) -> None:
    """``data`` has finite observed outputs and inputs (after :func:`ceemx.data.checks.prepare`)."""
    y, u, mask = np.asarray(data.y), np.asarray(data.u), np.asarray(data.mask)
    _finite("data.y", np.where(mask, y, 0.0))  # a Trajectories built under a transformation
    _finite("data.u", u)


# --------------------------------------------------------------------------------------------
# Free run
# --------------------------------------------------------------------------------------------


def free_run_one(system: AbstractSystem, x1, u, t0):
    """The free run of one trajectory: (T, n) states and (T, m) outputs from x1, steps from t0."""
    dtype = x1.dtype

    def step(x, inp):
        ut, t = inp
        y = system.observe(x, ut, t).astype(dtype)
        return system.dynamics(x, ut, t).astype(dtype), (x, y)

    ts = jnp.arange(u.shape[0])  # the default integer, as every other time index
    _, (xs, ys) = jax.lax.scan(step, x1, (u, jnp.asarray(t0, ts.dtype) + ts))
    return xs, ys


@jit
def free_run_batch(
    system: AbstractSystem, x1: Float[Array, "B n"], u: Inputs, t0: Int[Array, ""]
) -> tuple[States, Observations]:
    """The compiled kernel of :func:`free_run` (no validation; time steps from ``t0``)."""
    return jax.vmap(lambda x, ub: free_run_one(system, x, ub, t0))(x1, u)


@no_type_check  # validates its arguments
def free_run(
    system: AbstractSystem,
    x1: ArrayLike,
    u: ArrayLike | None = None,
    *,
    num_steps: int | None = None,
) -> tuple[Array, Array]:
    """Noise-free simulation of ``system`` from initial states under given inputs.

    x_{t+1} = f_θ(x_t, u_t, t), y_t = g_θ(x_t, u_t, t) for t = 0, …, T−1 (the system's integer
    time index), from x_0 = ``x1`` (the paper's x₁). No measured output is used: this is the
    "simulation" of the system-identification benchmarks, as opposed to prediction.

    Args:
        system: the model (any :class:`ceemx.AbstractSystem`; its noise models are not used).
        x1: (B, n) initial states, or (n,) for one trajectory.
        u: (B, T, p) inputs (with (B, n) states) or (T, p) (with (n,)); ``None`` for a system
            without inputs, then ``num_steps`` gives T.
        num_steps: T when ``u`` is ``None``; otherwise it must be ``None`` or equal to T.

    Returns:
        ``(states, outputs)``: (B, T, n) and (B, T, m) — or (T, n) and (T, m) for one trajectory —
        in the dtype of the system's parameters (``x1`` and ``u`` are cast to it, as by
        :func:`ceemx.fit`). ``states[:, 0]`` is ``x1``.

    Raises:
        TypeError: ``system`` is not a :class:`ceemx.AbstractSystem`; a complex or non-numeric
            ``x1`` or ``u``.
        ValueError: mismatched shapes, non-finite ``x1`` or ``u`` (or a value that overflows
            the cast), a float16 system, or a missing ``num_steps``; a ``dynamics``,
            ``vector_field`` or ``observe`` that returns another shape or dtype than the
            system's, or not one array (:func:`ceemx.models.method_check.check_methods`, as
            :func:`ceemx.fit` and :func:`ceemx.smooth` check).

    Warns:
        UserWarning: the run is not finite — naming the trajectory, the step and the method
            that returned NaN or inf (the arrays are returned as computed).

    ``lax.scan`` over time and ``vmap`` over the batch; compiled once per system structure and
    (B, T, p).

    Example:
        >>> sys = ceemx.systems.LinearSystem(jnp.array([[0.5]]), jnp.array([[2.0]]))
        >>> xs, ys = free_run(sys, jnp.array([1.0]), num_steps=3)
        >>> ys[:, 0].tolist()
        [2.0, 1.0, 0.5]
    """
    check_system(system)
    check_methods(system)  # the shapes and dtypes its methods return, as fit and smooth check
    x = promote_array("x1", x1, system)  # the system's dtype (x1's used to win)
    single = x.ndim == 1
    xb = _batch_of_one(x) if single else x
    n, p = system.state_dim, system.input_dim
    if xb.ndim != 2 or xb.shape[1] != n:
        raise ValueError(f"`x1` must have shape (B, n) or (n,) with n = {n}; got {x.shape}.")
    if u is None:
        if p != 0:
            raise ValueError(f"the system takes p = {p} inputs: pass `u`.")
        if num_steps is None:
            raise ValueError("pass `u` or `num_steps` (T).")
        T = check_int("num_steps", num_steps, 1)
        ub = as_jax(np.zeros((xb.shape[0], T, 0), x.dtype))
    else:
        ub = promote_array("u", u, system)
        ub = _batch_of_one(ub) if single else ub
        if ub.ndim != 3 or ub.shape[0] != xb.shape[0] or ub.shape[2] != p or ub.shape[1] < 1:
            want = f"(T, {p})" if single else f"(B, T, {p}) with B = {xb.shape[0]}"
            raise ValueError(f"`u` must have shape {want}; got {jnp.shape(u)}.")
        if num_steps is not None and check_int("num_steps", num_steps, 1) != ub.shape[1]:
            raise ValueError(f"`num_steps` = {num_steps} but `u` has T = {ub.shape[1]} steps.")
        _finite("u", np.asarray(ub))
    _finite("x1", np.asarray(xb))
    xs, ys = free_run_batch(strongly_typed(system), xb, ub, as_jax(np.zeros((), np.int32)))
    where = nonfinite_run(xs, ys)
    if where is not None:
        warn(f"free_run: the run is not finite: {where}")
    return (indexed(xs, 0), indexed(ys, 0)) if single else (xs, ys)


def _batch_of_one(a: jax.Array) -> jax.Array:
    """``a[None]``; in NumPy and a transfer for a concrete CPU array (no program per shape)."""
    return back_like(np.asarray(a)[None], a) if on_host(a) else a[None]


# --------------------------------------------------------------------------------------------
# k-step-ahead prediction
# --------------------------------------------------------------------------------------------


def _k_step_one(system: AbstractSystem, xf, x0, u, k: int):
    T = xf.shape[0]
    s = jnp.arange(T)
    start = s - k
    z = jnp.where((start >= 0)[:, None], xf[jnp.clip(start, 0, T - 1)], x0[None])

    def step(z, i):
        tau = start + i
        t = jnp.clip(tau, 0, T - 1)
        nxt = jax.vmap(system.dynamics)(z, u[t], t).astype(z.dtype)
        return jnp.where((tau >= 0)[:, None], nxt, z), None

    z, _ = jax.lax.scan(step, z, jnp.arange(k))
    return jax.vmap(system.observe)(z, u, s).astype(z.dtype)


@jit
def k_step_batch(
    system: AbstractSystem,
    filtered: States,
    prior_mean: Float[Array, "B n"],
    u: Inputs,
    k: int,
) -> Observations:
    """The compiled kernel of :func:`predict_k_step` (``k`` ≤ T static; means from the EKF)."""
    return jax.vmap(lambda xf, x0, ub: _k_step_one(system, xf, x0, ub, k))(filtered, prior_mean, u)


@no_type_check  # validates its arguments
def predict_k_step(
    system: AbstractSystem,
    data: Trajectories,
    k: int,
    *,
    initial: GaussianPrior | None = None,
) -> Array:
    """k-step-ahead predictions ŷ_{t+k|t} of every output by the extended Kalman filter.

    With x̂_{t|t} the EKF's filtered mean (:func:`ceemx.inference.ekf.ekf`, which has read y_0, …,
    y_t) and x̂_{0|−1} its prior mean, the prediction of y_s is

        x̂_{s|s−k} = f^k(x̂_{s−k|s−k})  (k noise-free steps under the inputs u_{s−k}, …, u_{s−1}),
        ŷ_{s|s−k} = g(x̂_{s|s−k}, u_s, s)                                        for s ≥ k,

    and for s < k (no output before s − k ≥ 0 exists) a free run from the prior mean,
    ŷ_s = g(f^s(x̂_{0|−1}), u_s, s). So ŷ_s reads only y_{0:s−k+1}; k = 1 is the EKF's
    ``predicted_obs`` (one-step prediction) and k ≥ T is :func:`free_run` from the prior mean.

    Args:
        system: the model; its noise models must be Gaussian (the filter's Q and R).
        data: B trajectories of T steps.
        k: the horizon, an integer ≥ 1 (values above T act as T).
        initial: the filter's prior on x₁ (see :func:`ceemx.inference.ekf.ekf`).

    Returns:
        (B, T, m) predictions in the system's dtype (``data`` is cast to it); NaN from the step
        on where the filter of a trajectory failed (its ``status``).

    Raises:
        TypeError: as :func:`ceemx.inference.ekf.ekf`.
        ValueError: as :func:`ceemx.inference.ekf.ekf`, and for ``k`` not an integer ≥ 1.

    Cost O(B·T·k) model evaluations; compiled once per shape and ``k`` (k is a loop length).
    """
    check_system(system)
    k = check_int("k", k, 1)
    inputs = prepare(system, data)
    system, data = inputs.system, inputs.data
    if initial is not None:
        initial = promote_tree(initial, system)
    sol = ekf_prepared(system, data, initial)
    k = min(k, data.num_steps)
    means, prior_mean = sol.filtered_means, indexed(sol.predicted_means, (slice(None), 0))
    return k_step_batch(strongly_typed(system), means, prior_mean, data.u, k)
