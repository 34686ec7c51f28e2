"""A generic, bounded Levenberg–Marquardt driver: the smoother's, the LM learner's, the joint one's.

The caller supplies the structure: how to evaluate the objective and its local quadratic model
(``evaluate``), how to solve the damped normal equations (``solve``) and how to evaluate the
quadratic form of the model (``quad``). The driver owns the accept/reject logic (actual vs
predicted decrease), Nielsen's damping update, convergence tests and status codes. It is a pure
``lax.while_loop``, safe under ``vmap`` (each batch element stops on its own).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jax.extend import core as jax_core
from jaxtyping import Array, ArrayLike, Float, Int

from ceemx.lib.results import RESULTS

__all__ = ["LMOutput", "levenberg_marquardt", "marquardt_scale"]


class LMOutput(NamedTuple):
    """Final iterate, objective, linearisation, iteration count, status, accepted steps, damping."""

    z: Any
    value: jax.Array
    lin: Any
    steps: jax.Array
    status: RESULTS
    accepted: jax.Array
    damping: jax.Array


def _vdot(a, b):
    return sum(jnp.sum(x * y) for x, y in zip(jtu.tree_leaves(a), jtu.tree_leaves(b), strict=True))


def _all_finite(tree):
    leaves = [jnp.all(jnp.isfinite(x)) for x in jtu.tree_leaves(tree)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)


def _traced_once(fun: Callable[[Any], Any], z0: Any) -> tuple[Callable[[Any], Any], Any]:
    """``fun`` traced once at ``z0``'s types: a function replaying its jaxpr, and its output shapes.

    The driver needs ``evaluate``'s output structure before it traces the loop body, which calls
    ``evaluate`` again; replaying the recorded equations costs a fraction of running the Python
    model code a second time. The replay is one jitted call: under ``vmap`` JAX batches a
    ``while_loop`` body two or three times (to find its batched carries), and a jitted call's
    batched form is cached after the first.
    """
    closed, shapes = jax.make_jaxpr(fun, return_shape=True)(z0)
    run_jaxpr = jax.jit(jax_core.jaxpr_as_fun(closed))
    out_tree = jtu.tree_structure(shapes)

    def replay(z):
        return jtu.tree_unflatten(out_tree, run_jaxpr(*jtu.tree_leaves(z)))

    return replay, shapes


def levenberg_marquardt(
    evaluate: Callable[[Any], tuple[jax.Array, Any]],
    grad_of: Callable[[Any], Any],
    solve: Callable[[Any, jax.Array], tuple[Any, jax.Array]],
    quad: Callable[[Any, Any], jax.Array],
    z0: Any,
    *,
    rtol: float | jax.Array,
    atol: float | jax.Array,
    max_steps: int | Int[Array, ""],
    damping: float | jax.Array,
    max_accepted: int | None = None,
    init: tuple[jax.Array, Any] | None = None,
    value: Callable[[Any], jax.Array] | None = None,
) -> LMOutput:
    """Minimise a function by Levenberg–Marquardt.

    Args:
        evaluate: ``z -> (f, lin)``: objective value and a linearisation object.
        grad_of: ``lin -> g``, the gradient (a pytree like z).
        solve: ``(lin, lam) -> (delta, ok)``: solves (H + λ·scaling) δ = −g; ``ok`` False when the
            factorisation failed.
        quad: ``(lin, delta) -> δᵀ H δ`` with the undamped model matrix H.
        z0: starting point.
        rtol: converged when the predicted or the actual decrease of an iteration is at most
            ``rtol·|f| + atol``.
        atol: the absolute part of that tolerance.
        max_steps: bound on iterations (accepted or rejected); may be traced.
        damping: initial λ.
        max_accepted: also stop after this many accepted steps (``None``: no such bound); with 1,
            one call is one LM iteration whose final λ (``LMOutput.damping``) seeds the next call.
        init: ``evaluate(z0)`` when the caller already has it (e.g. the linearisation at the point
            accepted by the previous call); saves one evaluation.
        value: ``z -> f`` alone, when it is much cheaper than ``evaluate`` (a dense Gauss–Newton
            matrix, a joint linearisation). Trial points are then judged by their value only and
            the linearisation is formed lazily, at the start of an iteration whose point has none
            yet (the first, unless ``init`` is given, and each after an accepted step): rejected
            trials and the final accepted point cost one value each instead of a linearisation.
            The first iteration's linearisation also gives the starting value, so the compiled
            program holds one copy of ``evaluate`` and one of ``value`` (compile time); that
            iteration runs even when ``max_steps`` is 0 (it then takes no step).
            ``LMOutput.lin`` is then ``None``. Under ``vmap`` the lazy linearisation (a
            ``lax.cond``) is computed at every iteration, rejected ones included: an iteration
            then costs a linearisation and a value, against a linearisation alone without
            ``value`` — which also linearises the start once more.

    Returns:
        An :class:`LMOutput`: the last accepted point with its value and linearisation.
    """
    evaluate, state = _start(evaluate, grad_of, z0, damping, init, value)
    loop = _Loop(
        evaluate,
        grad_of,
        solve,
        quad,
        value,
        rtol,
        atol,
        max_steps,
        max_accepted,
        first0=init is None and value is None,
        unknown0=init is None and value is not None,
    )
    s = jax.lax.while_loop(loop.cond, loop.body, state)
    lin = None if value is not None else s.lin
    return LMOutput(s.z, s.f, lin, s.steps, s.status, s.accepted, s.lam)


class _State(NamedTuple):
    """The loop's carry: the last accepted point and the iteration's bookkeeping."""

    z: Any  # the last accepted point
    f: jax.Array  # its value
    lin: Any  # its linearisation (lazy mode: formed only when ``stale`` is False)
    lam: jax.Array  # Marquardt's damping λ
    nu: jax.Array  # Nielsen's growth factor of λ after a rejection
    steps: jax.Array  # iterations (accepted and rejected)
    accepted: jax.Array  # accepted steps
    done: jax.Array  # converged, stalled or broken
    status: RESULTS
    stale: jax.Array  # lazy mode: the linearisation at z is not yet formed
    first: jax.Array  # the first pass (eager: evaluates z0 only; lazy: learns its value)


class _Trial(NamedTuple):
    """One iteration's trial step from the current point."""

    f: jax.Array  # the current point's value (lazy mode's first pass: just learned)
    lin: Any  # the current point's linearisation
    broken: jax.Array  # the current value or gradient is not finite
    allowed: jax.Array  # a step may be taken (lazy mode: not when max_steps is 0)
    ok: jax.Array  # the damped system was solved: a real step
    pred: jax.Array  # the predicted decrease
    z: Any  # the trial point
    f_new: jax.Array  # its value
    lin_new: Any  # its linearisation (lazy mode: the current one)
    finite_new: jax.Array  # its value (and eager mode's gradient) finite


class _Outcome(NamedTuple):
    """The verdict on a trial: acceptance, counts, the damping and the status after it."""

    accept: jax.Array
    counted: jax.Array  # counts as an accepted step
    idle: jax.Array  # a pass that takes no step and counts none
    lam: jax.Array
    nu: jax.Array
    status: RESULTS
    done: jax.Array


def _start(evaluate, grad_of, z0, damping, init, value) -> tuple[Callable[[Any], Any], _State]:
    """``evaluate`` as the loop calls it, and the loop's first state.

    With ``init``, the caller's evaluation of z0. Otherwise z0 is evaluated inside the loop —
    eager mode: by a first pass that takes a zero step; lazy mode (``value`` given): by the
    first linearisation, which also gives the starting value — so the compiled program holds
    one copy of ``evaluate`` (its compile time is most of a small fit's); zero placeholders of
    its output structure start the carry, and ``evaluate`` is traced here once and replayed in
    the loop. The eager first pass still runs ``solve`` on the placeholder (its result is
    discarded): under ``vmap`` a ``lax.cond`` would compute it anyway.
    """
    if init is not None:
        f0, lin0 = init
    else:
        evaluate, shapes = _traced_once(evaluate, z0)
        f0, lin0 = jtu.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    unknown0 = init is None and value is not None  # lazy: the start's value not yet known
    finite0 = jnp.isfinite(f0) & _all_finite(grad_of(lin0))
    dtype = jnp.result_type(f0)
    state = _State(
        z=z0,
        f=f0,
        lin=lin0,
        lam=jnp.asarray(damping, dtype),
        nu=jnp.asarray(2.0, dtype),
        steps=jnp.zeros((), jnp.int32),  # not weakly typed: a weak carry traces the body twice
        accepted=jnp.zeros((), jnp.int32),
        done=~finite0,
        status=RESULTS.where(finite0, RESULTS.max_steps_reached, RESULTS.nonfinite),
        stale=jnp.asarray(unknown0),
        first=jnp.asarray(init is None),
    )
    return evaluate, state


@dataclasses.dataclass(frozen=True)
class _Loop:
    """The driver's ``while_loop``: the caller's functions, the bounds and the start's mode.

    ``first0``: eager mode without ``init`` (the first pass only evaluates z0); ``unknown0``:
    lazy mode without ``init`` (the first pass learns z0's value and may take a step).
    """

    evaluate: Callable[[Any], tuple[jax.Array, Any]]
    grad_of: Callable[[Any], Any]
    solve: Callable[[Any, jax.Array], tuple[Any, jax.Array]]
    quad: Callable[[Any, Any], jax.Array]
    value: Callable[[Any], jax.Array] | None
    rtol: Any
    atol: Any
    max_steps: Any
    max_accepted: int | None
    first0: bool
    unknown0: bool

    def tol(self, f: jax.Array) -> jax.Array:
        """The decrease below which an iteration counts as converged."""
        return self.rtol * jnp.abs(f) + self.atol

    def cond(self, s: _State) -> jax.Array:
        """Go on while not done and within the bounds (the first pass always runs)."""
        going = (~s.done) & (s.steps < self.max_steps)
        if self.max_accepted is not None:
            going = going & (s.accepted < self.max_accepted)
        return going | s.first

    def body(self, s: _State) -> _State:
        """One iteration: a trial step, its verdict, the next state."""
        trial = self.trial(s)
        outcome = self.first_pass(s, trial, self.judge(s, trial))
        pick = lambda a, b: jnp.where(outcome.accept, a, b)  # noqa: E731
        return _State(
            z=jtu.tree_map(pick, trial.z, s.z),
            f=jnp.where(outcome.accept, trial.f_new, trial.f),
            lin=jtu.tree_map(pick, trial.lin_new, trial.lin),
            lam=outcome.lam,
            nu=outcome.nu,
            steps=s.steps + jnp.where(outcome.idle, 0, 1),
            accepted=s.accepted + outcome.counted.astype(jnp.int32),
            done=outcome.done,
            status=outcome.status,
            stale=outcome.accept if self.value is not None else s.stale,
            first=jnp.zeros_like(s.first),
        )

    def trial(self, s: _State) -> _Trial:
        """The damped Gauss–Newton step from ``s.z`` and the trial point's value."""
        f, lin, allowed = s.f, s.lin, jnp.asarray(True)
        if self.value is not None:
            f_z, lin = jax.lax.cond(s.stale, lambda: self.evaluate(s.z), lambda: (s.f, s.lin))
            if self.unknown0:  # the first pass learns the start's value; it may take a step
                f = jnp.where(s.first, f_z, f)
                allowed = s.steps < self.max_steps
        g = self.grad_of(lin)
        # Lazy mode: an accepted point whose gradient turns out non-finite ends the run there
        # (and a start whose value or gradient is not finite, before any step).
        broken = ~_all_finite(g) | ~jnp.isfinite(f)
        delta, ok = self.solve(lin, s.lam)
        ok = ok & _all_finite(delta) & ~broken & allowed & ~(s.first & self.first0)
        delta = jtu.tree_map(lambda d: jnp.where(ok, d, 0.0), delta)
        pred = -(_vdot(g, delta) + 0.5 * self.quad(lin, delta))
        z_new = jtu.tree_map(jnp.add, s.z, delta)
        if self.value is None:
            f_new, lin_new = self.evaluate(z_new)
            finite_new = jnp.isfinite(f_new) & _all_finite(self.grad_of(lin_new))
        else:
            f_new, lin_new = self.value(z_new), lin
            finite_new = jnp.isfinite(f_new)
        return _Trial(f, lin, broken, allowed, ok, pred, z_new, f_new, lin_new, finite_new)

    def judge(self, s: _State, t: _Trial) -> _Outcome:
        """Accept on the ratio of actual to predicted decrease; Nielsen's damping update."""
        actual = t.f - t.f_new
        ratio = actual / jnp.where(t.pred > 0, t.pred, 1.0)
        small_pred = t.ok & (t.pred >= 0) & (t.pred <= self.tol(t.f))
        # A step whose predicted decrease is below tolerance is at round-off level: keep it unless
        # it makes things worse by more than the tolerance (the ratio test is noise there).
        accept = (
            t.finite_new
            & t.ok
            & (((t.pred > 0) & (ratio > 1e-4)) | (small_pred & (t.f_new <= t.f + self.tol(t.f))))
        )
        lam_acc = s.lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
        lam = jnp.where(accept, lam_acc, s.lam * s.nu)
        nu = jnp.where(accept, 2.0, 2.0 * s.nu)
        converged = small_pred | (accept & (actual <= self.tol(t.f)))
        stalled = lam > 1e20
        status = RESULTS.where(stalled, RESULTS.stalled, s.status)
        status = RESULTS.where(converged, RESULTS.successful, status)
        status = RESULTS.where(t.broken, RESULTS.nonfinite, status)
        idle = s.first & self.first0  # a pass that takes no step and counts none
        return _Outcome(accept, accept, idle, lam, nu, status, converged | stalled | t.broken)

    def first_pass(self, s: _State, t: _Trial, o: _Outcome) -> _Outcome:
        """The verdict of a first pass that evaluates the start (no ``init``)."""
        first = s.first
        if self.unknown0:  # a step not allowed (max_steps 0) or a broken start changes nothing
            idle = first & (t.broken | ~t.allowed)
            o = o._replace(
                idle=idle, lam=jnp.where(idle, s.lam, o.lam), nu=jnp.where(idle, s.nu, o.nu)
            )
        if self.first0:  # the first pass only evaluates z0 (δ = 0): it takes the start, or fails
            accept = jnp.where(first, t.finite_new, o.accept)
            started = RESULTS.where(t.finite_new, RESULTS.max_steps_reached, RESULTS.nonfinite)
            o = o._replace(
                accept=accept,
                counted=accept & ~first,
                lam=jnp.where(first, s.lam, o.lam),
                nu=jnp.where(first, s.nu, o.nu),
                status=RESULTS.where(first, started, o.status),
                done=jnp.where(first, ~t.finite_new, o.done),
            )
        return o


def marquardt_scale(
    diag: Float[Array, "*shape"], lam: Float[ArrayLike, ""]
) -> Float[Array, "*shape"]:
    """λ·diag(H): Marquardt's per-variable damping, invariant to the scale of each variable.

    Variables with (numerically) zero curvature — parameters with no effect on the objective, such
    as masked entries — get λ·max(diag) instead, so the damped matrix stays well conditioned; their
    gradient is zero too, so they do not move.
    """
    top = jnp.max(diag)
    return jnp.asarray(lam) * jnp.where(diag > 1e-10 * top, diag, jnp.maximum(top, 1.0))
