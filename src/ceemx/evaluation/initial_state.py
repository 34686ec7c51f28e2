"""Initial states from the first outputs: x̂₁ for a free run scored on the rest of the record.

:func:`estimate_initial_state` gives x̂₁ from the first ``n_init`` outputs (and the inputs): a MAP
smoothing (:func:`ceemx.smooth`) of that window at the system's θ, then x₁ refined so that the
free run from it (:func:`ceemx.evaluation.simulation.free_run`) fits the window.
:func:`ceemx.evaluation.metrics.benchmark_score` starts its free runs there. Trajectories are
independent (``vmap``); compiled once per shape and system structure (parameters, data and
tolerances are traced).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ceemx.data.checks import check_states, prepare, promote_array
from ceemx.data.trajectories import Trajectories
from ceemx.evaluation.simulation import (
    check_finite_data,
    check_int,
    check_system,
    free_run_one,
    strongly_typed,
)
from ceemx.identification.initialize import from_observations
from ceemx.inference.smoother import LMSmoother, smooth_batch
from ceemx.infra.options import check_bool
from ceemx.infra.policy import Runs, program, smoothing_work
from ceemx.infra.warn import warn
from ceemx.lib.dense import after, cholesky_solve
from ceemx.lib.lm import levenberg_marquardt, marquardt_scale
from ceemx.lib.results import RESULTS, select
from ceemx.lib.tree import as_jax, trace_numbers
from ceemx.lib.typing import States, no_type_check
from ceemx.models.system import AbstractSystem, with_noise
from ceemx.systems.hybrid import Hybrid, HybridContinuous

__all__ = ["estimate_initial_state", "initial_state_batch", "initial_state_prepared"]


def _window(data: Trajectories, n_init: int) -> Trajectories:
    """The first ``max(n_init, 2)`` steps, outputs from step ``n_init`` on masked."""
    L = max(n_init, 2)
    keep = (np.arange(L) < n_init)[None, :, None]
    # NumPy on the host (the constructor reads its arguments there anyway): JAX's slices
    # compiled a small program per new shape.
    y, u, mask = (np.asarray(a)[:, :L] for a in (data.y, data.u, data.mask))
    return Trajectories(y, u, mask & keep)


def _output_error_one(
    solver: LMSmoother,
    system: AbstractSystem,
    x0: Float[Array, " n"],
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
):
    """LM on x₁ of Σ_t −log p_v(y_t − g(f^t(x₁))) (+ −log p(x₁)): the simulation error."""
    n, dtype = x0.shape[0], x0.dtype
    prior = system.initial_prior
    zeros_m = jnp.zeros(y.shape[-1:], dtype)
    offset = jnp.sum(jax.vmap(lambda mk: system.obs_noise.nll(zeros_m, mk))(mask))
    if prior is not None:
        offset = offset + prior.noise.nll(jnp.zeros((n,), dtype))

    def residuals(x1):
        r = y - free_run_one(system, x1, u, jnp.zeros((), jnp.int32))[1]
        return r, r

    def evaluate(x1):
        jac, r = jax.jacfwd(residuals, has_aux=True)(x1)  # (T, m, n), (T, m)
        value = jnp.sum(jax.vmap(system.obs_noise.nll)(r, mask)) - offset
        grad = jnp.einsum("tm,tmn->n", jax.vmap(jax.grad(system.obs_noise.nll))(r, mask), jac)
        S = jax.vmap(system.obs_noise.sqrt_curvature)(r, mask)
        SJ = jnp.einsum("tkm,tmn->tkn", S, jac).reshape(-1, n)
        hess = SJ.T @ SJ
        if prior is not None:
            Sp = prior.noise.sqrt_curvature(x1 - prior.mean)
            value = value + prior.nll(x1)
            grad = grad + jax.grad(prior.nll)(x1)
            hess = hess + Sp.T @ Sp
        return value, (grad, hess)

    def solve(lin, lam):
        grad, hess = lin
        damped = hess + jnp.diag(marquardt_scale(jnp.diagonal(hess), lam))
        return cholesky_solve(damped, -grad)

    out = levenberg_marquardt(
        evaluate,
        lambda lin: lin[0],
        solve,
        lambda lin, delta: delta @ lin[1] @ delta,
        x0,
        rtol=solver.rtol,
        atol=solver.atol,
        max_steps=solver.max_steps,
        damping=solver.damping,
    )
    return out.z, out.status


def _window_error_one(system: AbstractSystem, x1, y, u, mask) -> Float[Array, ""]:
    """The refine step's objective at x₁: Σ_t −log p_v(y_t − g(f^t(x₁))) (+ −log p(x₁))."""
    r = y - free_run_one(system, x1, u, jnp.zeros((), jnp.int32))[1]
    value = jnp.sum(jax.vmap(system.obs_noise.nll)(r, mask))
    if system.initial_prior is not None:
        value = value + system.initial_prior.nll(x1)
    return value


def _window_work(solver, system: AbstractSystem, weak, window: Trajectories, x_init, refine):
    """:func:`initial_state_batch`'s work: smoothing the window (its LM on x₁ is smaller)."""
    del solver, weak, x_init, refine
    B, T, _ = window.y.shape
    return smoothing_work(B, T, system.state_dim)


# once per score or prediction: a short window's smoothing and LM
@program(runs=Runs.ONCE, work=_window_work)
def initial_state_batch(
    solver: LMSmoother,
    system: AbstractSystem,
    weak: AbstractSystem | None | tuple[AbstractSystem | None, ...],
    window: Trajectories,
    x_init: States | None,
    refine: bool,
) -> tuple[Float[Array, "B n"], RESULTS]:
    """The compiled kernel of :func:`estimate_initial_state` (no validation; numbers traced).

    Start: ``x_init``, else :func:`ceemx.identification.initialize.from_observations` followed by
    one smoothing
    pass of ``weak`` (the system with weak dynamics weights, as :func:`ceemx.warm_start`); then
    the MAP smoothing of ``system`` and, with ``refine``, LM on x₁ of the window's simulation
    error. Returns x̂₁ and the last solve's status. A tuple ``weak`` gives one start per entry
    (``None``: no weak pass), run one after the other (:func:`ceemx.lib.dense.after`: no two
    batched solves run concurrently); each trajectory keeps the x̂₁ of the lowest window
    simulation error.
    """
    starts = weak if isinstance(weak, tuple) else (weak,)
    best = None
    for w in starts:
        x0 = from_observations(system, window) if x_init is None else x_init
        if best is not None:
            x0 = after(x0, best[0])
        if x_init is None and w is not None:
            x0 = smooth_batch(solver, w, x0, window, False).states
        sol = smooth_batch(solver, system, x0, window, False)
        x1, status = sol.states[:, 0], sol.status
        if refine:
            one = lambda x, y, u, m: _output_error_one(solver, system, x, y, u, m)  # noqa: E731
            x1, status = jax.vmap(one)(x1, window.y, window.u, window.mask)
        if len(starts) == 1:
            return x1, status
        err = jax.vmap(lambda x, y, u, m: _window_error_one(system, x, y, u, m))(
            x1, window.y, window.u, window.mask
        )
        err = jnp.where(jnp.isfinite(err), err, jnp.inf)
        if best is None:
            best = (x1, status, err)
        else:
            take = err < best[2]
            best = (
                jnp.where(take[:, None], x1, best[0]),
                select(take, status, best[1]),
                jnp.where(take, err, best[2]),
            )
    assert best is not None
    return best[0], best[1]


@no_type_check  # validates its arguments
def estimate_initial_state(
    system: AbstractSystem,
    data: Trajectories,
    n_init: int | None = None,
    *,
    refine: bool = True,
    smoother: LMSmoother | None = None,
    x_init: ArrayLike | None = None,
    warm_process_noise: float | None | Sequence[float | None] = 1.0,
    return_status: bool = False,
) -> Any:
    """x̂₁ of every trajectory from its first ``n_init`` outputs and inputs.

    1. MAP smoothing of the window y_{0:n_init}, u_{0:n_init} at the system's θ (paper Eq. 10 on
       the window's states, weighted by the system's noise models and initial prior), started
       from least squares through the observation map and a weak-dynamics pass (as
       :func:`ceemx.warm_start`); its first state is x̂₁ when ``refine`` is False.
    2. With ``refine`` (default): Levenberg–Marquardt on x₁ alone, from that state, of the
       window's simulation error Σ_{t<n_init} −log p_v(y_t − g(f^t(x₁), u_t, t)) (+ −log p(x₁)):
       the x̂₁ whose noise-free :func:`free_run` best explains the window — what a free run
       scored on ``y[n_init:]`` needs (:func:`ceemx.evaluation.metrics.benchmark_score`). The
       smoothed x₁
       is the best state estimate under the model's process noise, but a free run from it can
       be far off when that noise is large (the smoothed path may follow y through w_t).

    On noise-free data of an observable system without an initial prior both give the true x₁.

    Args:
        system: the model; its noise models weight the window's residuals.
        data: B trajectories (observations, inputs, mask); only steps ``< n_init`` are read.
        n_init: outputs to use, in [1, T]; ``None``: all T. With ``n_init = 1`` the window has
            two steps, the second unobserved.
        refine: step 2 above.
        smoother: the solver of both steps (its ``rtol``, ``atol``, ``max_steps``, ``damping``;
            default :class:`ceemx.LMSmoother`).
        x_init: (B, max(n_init, 2), n) starting states of step 1 instead of the warm start.
        warm_process_noise: scale of the weak dynamics weights of the warm start (``None``: no
            weak pass); a sequence of them: one start per entry (steps 1–2 from each), each
            trajectory keeping the x̂₁ of the lowest window simulation error (the refine step's
            objective) — for a model whose window
            objective has several minima, e.g. a sign-insensitive sensor y = |v| (the coupled
            drives: ``(1.0, None)``).
        return_status: also return the last solve's (B,) :class:`ceemx.RESULTS`.

    Data and ``x_init`` are cast to the dtype of the system's parameters, as by :func:`ceemx.fit`
    and :func:`ceemx.smooth` (:func:`ceemx.data.checks.prepare`).

    Returns:
        (B, n) initial states in the system's dtype; ``(x1, status)`` with ``return_status``.

    Warns:
        UserWarning: x̂₁ of a hybrid model lies outside its state bounds (``lower``, ``upper``;
            the model reads it through its projection into them).

    Raises:
        TypeError: ``system`` or ``data`` of the wrong type, or a non-integer ``n_init``.
        ValueError: ``n_init`` outside [1, T], mismatched dimensions, a float16 system,
            non-finite data, or a trajectory with no observed output in the window.

    Trajectories are independent (``vmap``). Compiled once per system structure, B and window
    length ``n_init`` (and the smoother's type): the parameters, data and the smoother's
    numbers are traced, so scoring many models or records of one shape never recompiles.
    """
    check_system(system)
    inputs = prepare(system, data)
    check_finite_data(inputs.data)
    out = initial_state_prepared(
        inputs.system,
        inputs.data,
        n_init,
        refine=refine,
        smoother=smoother,
        x_init=x_init,
        warm_process_noise=warm_process_noise,
        return_status=return_status,
    )
    _warn_outside_bounds(inputs.system, out[0] if return_status else out)
    return out


def _warn_outside_bounds(system: AbstractSystem, x1) -> None:
    """A warning when x̂₁ lies outside a hybrid model's state bounds (``lower``, ``upper``).

    The model reads every state through its smooth projection into the bounds
    (:meth:`ceemx.systems.hybrid.Hybrid.project`), where it is flat far outside: the window's
    simulation error does not pull x̂₁ back in, and a state such as a tank level of −1 V is
    returned although the free run starts from its projection.
    """
    if not isinstance(system, Hybrid | HybridContinuous):
        return
    x = np.asarray(x1, np.float64)
    lower, upper = np.asarray(system.lower), np.asarray(system.upper)
    outside = np.isfinite(x) & ((x < lower) | (x > upper))
    if not outside.any():
        return
    b, i = (int(v) for v in np.argwhere(outside)[0])
    projected = np.asarray(system.project(jnp.asarray(x[b], jnp.asarray(x1).dtype)))[i]
    warn(
        f"estimate_initial_state: x̂₁ lies outside the model's state bounds in "
        f"{int(outside.sum())} entr{'ies' if outside.sum() > 1 else 'y'}, e.g. state {i + 1} "
        f"of trajectory {b}: {x[b, i]:.4g} outside [{lower[i]:.4g}, {upper[i]:.4g}]. The model "
        f"reads it through its projection into the bounds ({projected:.4g}); the estimate "
        "itself is not a state of the bounded model (its window fit is flat out there)."
    )


def initial_state_prepared(
    system: AbstractSystem,
    data: Trajectories,
    n_init: int | None = None,
    *,
    refine: bool = True,
    smoother: LMSmoother | None = None,
    x_init: ArrayLike | None = None,
    warm_process_noise: float | None | Sequence[float | None] = 1.0,
    return_status: bool = False,
) -> Any:
    """:func:`estimate_initial_state` of prepared inputs (:func:`ceemx.data.checks.prepare`).

    ``n_init``, ``x_init`` and the options are checked here; the system and data are not again.
    """
    x_init = promote_array("x_init", x_init, system)
    T = data.num_steps
    n_init = T if n_init is None else check_int("n_init", n_init, 1, T)
    check_bool("refine", refine)
    check_bool("return_status", return_status)
    if smoother is not None and not isinstance(smoother, LMSmoother):
        raise TypeError(f"`smoother` must be a ceemx.LMSmoother or None; got {smoother!r:.80}.")
    window = _window(data, n_init)
    seen = np.asarray(window.mask).any(axis=(1, 2))
    if not seen.all():
        raise ValueError(
            f"trajectory {int(np.argmin(seen))} has no observed output among its first "
            f"n_init = {n_init} steps: its initial state cannot be estimated."
        )
    if x_init is not None:
        check_states(system, window, x_init)
        x_init = as_jax(x_init)
    dtype = window.y.dtype
    solver = trace_numbers(LMSmoother() if smoother is None else smoother, dtype)
    many = isinstance(warm_process_noise, (tuple, list))
    scales = tuple(warm_process_noise) if many else (warm_process_noise,)
    for q in scales:
        number = isinstance(q, (int, float, np.number)) and not isinstance(q, bool)
        if q is not None and not (number and 0 < float(q) < math.inf):  # type: ignore[arg-type]
            raise ValueError(
                "`warm_process_noise` must be a positive finite number, None, or a non-empty "
                f"sequence of them; got {warm_process_noise!r}."
            )
    if not scales:
        raise ValueError("`warm_process_noise` must not be an empty sequence.")
    weaks = tuple(
        None if q is None else with_noise(system, process_noise=jnp.asarray(q, dtype))
        for q in scales
    )
    weak = weaks if many else weaks[0]
    system, weak = strongly_typed((system, weak))
    x1, status = initial_state_batch(solver, system, weak, window, x_init, bool(refine))
    status = _flag_nonfinite(x1, status)
    return (x1, status) if return_status else x1


def _flag_nonfinite(x1: Float[Array, "B n"], status: RESULTS) -> RESULTS:
    """Status ``nonfinite`` and a warning for every trajectory whose x̂₁ is not finite."""
    bad = ~np.all(np.isfinite(np.asarray(x1)), axis=-1)
    if not bad.any():
        return status
    which = ", ".join(str(b) for b in np.flatnonzero(bad))
    warn(
        f"estimate_initial_state: x̂₁ is not finite (NaN or inf) for "
        f"trajector{'ies' if bad.sum() > 1 else 'y'} {which}: the window's objective is not "
        "finite at the model's parameters (a noise scale so small that whitening overflows, "
        "such as 1e-300, or a model that overflows in the window). Their status is "
        "RESULTS.nonfinite (return_status=True; BenchmarkScore.status)."
    )
    return select(as_jax(~bad), status, RESULTS.nonfinite)
