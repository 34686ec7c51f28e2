"""Learners for the θ-step (paper Eq. 11): Levenberg–Marquardt, L-BFGS, Optax, Nelder–Mead.

Every learner maps an
:class:`~ceemx.identification.learning.learning_problem.AbstractLearningProblem` (Eq. 11, or
Laplace EM's −Q), the current flat θ and its
own state to a new θ, a new state and a :class:`LearnInfo`. States persist across EM epochs (so an
Adam learner keeps its moments) and are saved in checkpoints.
"""

from __future__ import annotations

import abc
from typing import Any, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, PRNGKeyArray

from ceemx.identification.learning.learning_problem import AbstractLearningProblem
from ceemx.infra.memory import check_fits
from ceemx.infra.options import check_damping, check_int, check_nonnegative, check_rtol
from ceemx.lib.dense import cholesky_solve
from ceemx.lib.lm import levenberg_marquardt, marquardt_scale
from ceemx.lib.results import RESULTS
from ceemx.lib.typing import IntScalar, Scalar, Theta

__all__ = [
    "AbstractLearner",
    "LBFGSLearner",
    "LMLearner",
    "LearnInfo",
    "NelderMeadLearner",
    "OptaxLearner",
]


class LearnInfo(eqx.Module):
    """What one learning step did: objective before/after, iterations, status."""

    value_before: Scalar
    value_after: Scalar
    steps: IntScalar
    status: RESULTS


class AbstractLearner(eqx.Module):
    """A θ-step optimiser (an ``init`` / ``run`` pair; ``run`` is jit-compiled by the caller)."""

    def init(self, theta: Theta, key: PRNGKeyArray) -> Any:
        """The learner's persistent state (default: none)."""
        return None

    def check_memory(self, n_params: int, batch_size: int, itemsize: int) -> None:
        """Refuse, before any compute, a problem whose arrays would not fit in memory.

        :func:`ceemx.fit` calls it (through the solver's ``check_problem``) before the start
        states are computed, so that a learner that cannot run fails at once rather than after
        the first smoothing step. Default: nothing (matrix-free learners).
        """
        del n_params, batch_size, itemsize

    @abc.abstractmethod
    def run(
        self, problem: AbstractLearningProblem, theta: Theta, state: Any
    ) -> tuple[Theta, Any, LearnInfo]:
        """Minimise ``problem.value`` from ``theta``; returns (θ, state, LearnInfo)."""


class LMLearner(AbstractLearner):
    """Levenberg–Marquardt on the (generalised) Gauss–Newton model of the learning objective.

    A dense θ-Jacobian per step; Marquardt's per-parameter damping makes it invariant to parameter
    scales. The default for gray-box models with up to a few thousand parameters. The ρ_θ term and
    the log-prior's Hessian are added to the normal equations; accepted steps decrease the learning
    objective (up to round-off once the predicted decrease is below tolerance).

    Attributes:
        max_steps: bound on LM iterations (accepted or rejected) per EM epoch.
        rtol, atol: convergence on the decrease of the objective.
        damping: initial λ (> 0 and below 1/rtol: :mod:`ceemx.infra.options`).
        max_accepted: also stop after this many accepted steps (``None``: no such bound, the
            M-step is solved to ``rtol``). ``1`` is a generalised-EM M-step: one Gauss–Newton
            build and the first step that lowers the objective (rejected trials cost a value
            each) — the default of :class:`ceemx.Alternating`.
    """

    max_steps: int = eqx.field(default=100, static=True)
    rtol: float = 1e-12
    atol: float = 0.0
    damping: float = 1e-3
    max_accepted: int | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        check_int("max_steps", self.max_steps, 1)
        check_int("max_accepted", self.max_accepted, 1, none=True)
        check_rtol("rtol", self.rtol)
        check_nonnegative("atol", self.atol)
        check_damping("damping", self.damping, self.rtol)

    def check_memory(self, n_params: int, batch_size: int, itemsize: int) -> None:
        """The B + 4 dense P × P Gauss–Newton matrices of a step must fit in memory."""
        P, B = n_params, batch_size
        check_fits(
            f"LMLearner's {B} per-trajectory dense {P} × {P} Gauss–Newton matrices",
            (B + 4) * P * P * itemsize,
            "use ceemx.GaussNewtonCGLearner (Gauss–Newton by Jacobian-vector products and CG) or "
            "ceemx.LBFGSLearner (matrix-free) for this many parameters.",
        )

    def run(
        self, problem: AbstractLearningProblem, theta: Theta, state: Any
    ) -> tuple[Theta, Any, LearnInfo]:
        """LM iterations from θ."""
        self.check_memory(theta.shape[0], problem.batch_size, theta.dtype.itemsize)
        offset = problem.offset(
            theta
        )  # tolerances are relative to the objective less its constants

        def evaluate(th):
            value, grad, hess = problem.gauss_newton(th)
            return value - offset, (grad, hess)

        def solve(lin, lam):
            grad, hess = lin
            damped = hess + jnp.diag(marquardt_scale(jnp.diagonal(hess), lam))
            delta, ok = cholesky_solve(damped, -grad)
            return delta, ok

        out = levenberg_marquardt(
            evaluate,
            lambda lin: lin[0],
            solve,
            lambda lin, d: d @ lin[1] @ d,
            theta,
            rtol=self.rtol,
            atol=self.atol,
            max_steps=self.max_steps,
            damping=self.damping,
            max_accepted=self.max_accepted,
            # Trial points need only the objective's value: the dense Gauss–Newton matrix is formed
            # at the start and where an accepted step is followed by another (not at rejected
            # trials nor at the final point).
            value=lambda th: problem.value(th) - offset,
        )
        v0 = problem.value(theta)
        return out.z, state, LearnInfo(v0, out.value + offset, out.steps, out.status)


class LBFGSLearner(AbstractLearner):
    """L-BFGS (``optax.lbfgs`` with its zoom line search) on the learning objective.

    Attributes:
        max_steps: bound on L-BFGS iterations per EM epoch.
        gtol: stop when the gradient's max-norm falls below ``gtol``.
        memory_size: number of curvature pairs kept.
    """

    max_steps: int = eqx.field(default=100, static=True)
    gtol: float = 1e-9
    memory_size: int = eqx.field(default=20, static=True)

    def __check_init__(self):
        check_int("max_steps", self.max_steps, 1)
        check_nonnegative("gtol", self.gtol)
        check_int("memory_size", self.memory_size, 1)

    def run(
        self, problem: AbstractLearningProblem, theta: Theta, state: Any
    ) -> tuple[Theta, Any, LearnInfo]:
        """L-BFGS iterations from θ (fresh curvature memory every epoch)."""
        opt = optax.lbfgs(memory_size=self.memory_size)
        fun = problem.value
        vg = optax.value_and_grad_from_state(fun)
        v0 = fun(theta)

        def cond(c):
            th, st, k, g = c
            return (
                (k < self.max_steps) & (jnp.max(jnp.abs(g)) > self.gtol) & jnp.all(jnp.isfinite(g))
            )

        def body(c):
            th, st, k, _ = c
            # optax (0.2.8) adds its int32 memory index to a default-int range: standard
            # promotion for its L-BFGS, so that strict-promotion users can fit.
            with jax.numpy_dtype_promotion("standard"):
                value, grad = vg(th, state=st)
                upd, st = opt.update(grad, st, th, value=value, grad=grad, value_fn=fun)
            th = cast(Array, optax.apply_updates(th, upd))
            return th, st, k + 1, grad

        g0 = jax.grad(fun)(theta)
        th, _, k, g = jax.lax.while_loop(
            cond, body, (theta, opt.init(theta), jnp.zeros((), jnp.int32), g0)
        )
        v1 = fun(th)
        ok = jnp.isfinite(v1) & (v1 <= v0)
        th = jnp.where(ok, th, theta)
        status = RESULTS.where(k < self.max_steps, RESULTS.successful, RESULTS.max_steps_reached)
        status = RESULTS.where(ok, status, RESULTS.nonfinite)
        return th, state, LearnInfo(v0, jnp.where(ok, v1, v0), k, status)


class OptaxLearner(AbstractLearner):
    """Any Optax gradient transformation (e.g. ``optax.adam(1e-3)``), optionally on minibatches.

    The optimiser state and the minibatch PRNG key persist across EM epochs. Not monotone: the
    EM objective may rise when the step size is too large.

    Attributes:
        transform: the Optax transformation.
        steps: gradient steps per EM epoch.
        batch_size: trajectories per minibatch (``None``: the whole batch).
    """

    transform: optax.GradientTransformation = eqx.field(static=True)
    steps: int = eqx.field(default=100, static=True)
    batch_size: int | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        if not isinstance(self.transform, optax.GradientTransformation):
            raise TypeError(
                "`transform` must be an Optax gradient transformation such as "
                f"optax.adam(1e-3); got {self.transform!r}."
            )
        check_int("steps", self.steps, 1)
        check_int("batch_size", self.batch_size, 1, none=True)

    def init(self, theta: Theta, key: PRNGKeyArray) -> Any:
        """(optimiser state, PRNG key)."""
        return (self.transform.init(theta), key)

    def run(
        self, problem: AbstractLearningProblem, theta: Theta, state: Any
    ) -> tuple[Theta, Any, LearnInfo]:
        """``steps`` gradient steps."""
        opt_state, key = state
        B = problem.batch_size
        v0 = problem.value(theta)

        def body(c, _):
            th, st, k = c
            if self.batch_size is None or self.batch_size >= B:
                grad = jax.grad(problem.value)(th)
            else:
                k, sub = jax.random.split(k)
                idx = jax.random.choice(sub, B, (self.batch_size,), replace=False)
                grad = jax.grad(problem.minibatch_value)(th, idx)
            # optax (0.2.8) mixes its int32 step count with floats (adam's bias correction):
            # standard promotion for the transform, so that strict-promotion users can fit.
            with jax.numpy_dtype_promotion("standard"):
                upd, st = self.transform.update(grad, st, th)
            return (cast(Array, optax.apply_updates(th, upd)), st, k), None

        (th, opt_state, key), _ = jax.lax.scan(
            body, (theta, opt_state, key), None, length=self.steps
        )
        v1 = problem.value(th)
        ok = jnp.isfinite(v1)
        status = RESULTS.where(ok, RESULTS.successful, RESULTS.nonfinite)
        th = jnp.where(ok, th, theta)
        return (
            th,
            (opt_state, key),
            LearnInfo(v0, jnp.where(ok, v1, v0), jnp.asarray(self.steps), status),
        )


class NelderMeadLearner(AbstractLearner):
    """Nelder–Mead simplex (``optimistix.NelderMead``): derivative-free, for a few parameters.

    Compiled like every other learner (no host round trips). Stops when both the simplex's spread
    in θ and in the objective (less its normalising constants) are within ``rtol·|·| + atol``.

    Attributes:
        max_steps: iteration bound per EM epoch (``None``: 200 per parameter, SciPy's default).
        rtol, atol: relative and absolute tolerances on θ and on the objective.
    """

    max_steps: int | None = eqx.field(default=None, static=True)
    rtol: float = 1e-8
    atol: float = 1e-8

    def __check_init__(self):
        check_int("max_steps", self.max_steps, 1, none=True)
        check_rtol("rtol", self.rtol)
        check_nonnegative("atol", self.atol)

    def run(
        self, problem: AbstractLearningProblem, theta: Theta, state: Any
    ) -> tuple[Theta, Any, LearnInfo]:
        """Nelder–Mead from θ."""
        import optimistix as optx  # here: importing it costs every `import ceemx` 0.26 s

        offset = problem.offset(theta)
        v0 = problem.value(theta)

        def fun(th, _):
            v = problem.value(th) - offset
            return jnp.where(jnp.isfinite(v), v, jnp.inf)

        max_steps = 200 * theta.shape[0] if self.max_steps is None else self.max_steps
        sol = optx.minimise(
            fun,
            optx.NelderMead(rtol=self.rtol, atol=self.atol),
            theta,
            max_steps=max_steps,
            throw=False,
        )
        v1 = problem.value(sol.value)
        ok = jnp.isfinite(v1) & (v1 <= v0)
        th = jnp.where(ok, sol.value, theta)
        status = RESULTS.where(
            sol.result == optx.RESULTS.successful, RESULTS.successful, RESULTS.max_steps_reached
        )
        status = RESULTS.where(ok, status, RESULTS.nonfinite)
        return th, state, LearnInfo(v0, jnp.where(ok, v1, v0), sol.stats["num_steps"], status)
