"""The joint method's iteration with a matrix-free border (``JointLM(border="matrix-free")``).

Where the border E_b (B·T·n·P) and D (P²) do not fit — P ≈ 10⁵ — only the x-blocks A_b are
formed (as the smoother forms them: one trajectory's linearisation at a time, ``lax.map``), and
E_b, Eᵀ_b and D enter as products of the residuals' Jacobian
(:func:`ceemx.identification.learning.gauss_newton_product`: one JVP and one transposed JVP each).
The Schur complement S = D − Σ_b E_bᵀA_b⁻¹E_b is applied by preconditioned CG
(:func:`ceemx.lib.arrowhead_solve_matrix_free`), truncated at ``cg_rtol``/``cg_max_steps`` (an
inexact Newton step; the LM acceptance test judges it like any other). Memory O(B·T·n² + P).

θ's Marquardt scaling and CG's Jacobi preconditioner use diag(D), computed exactly one time step
at a time (:func:`ceemx.identification.learning.gauss_newton_diagonal`, about one dense
θ-Jacobian's work per iteration) with ``border_scaling="diagonal"``, or 1 (Levenberg's damping in
θ, no preconditioner) with ``"identity"``. With the exact diagonal and CG run to convergence, an
iteration equals the dense border's (tested).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from jaxtyping import Array

from ceemx import lib
from ceemx.identification.learning.gauss_newton_cg import (
    gauss_newton_diagonal,
    gauss_newton_product,
)
from ceemx.identification.problem import FitProblem
from ceemx.inference.objective import linearize
from ceemx.lib.blocktri import BlockTridiagonal
from ceemx.lib.lm import levenberg_marquardt, marquardt_scale
from ceemx.lib.typing import PerTrajectory, Scalar, States, Theta

__all__ = ["iteration", "linearization_batch"]

#: Bytes of one trajectory's x-linearisation intermediates the ``lax.map`` may hold at once.
_CHUNK_BYTES = 2**30


def linearization_batch(T: int, n: int, m: int, itemsize: int, B: int) -> int:
    """Trajectories linearised together: as many as keep ~8·T·(m + n)·n numbers under 1 GiB."""
    per = 8 * T * (m + n) * n * itemsize
    return int(max(1, min(B, _CHUNK_BYTES // max(per, 1))))


def _participating(ok_b, *arrays):
    ref = jnp.argmax(ok_b)

    def pick(a):
        return jnp.where(ok_b.reshape((-1,) + (1,) * (a.ndim - 1)), a, a[ref][None])

    return jax.tree_util.tree_map(pick, arrays)


def iteration(
    opts: Any,
    problem: FitProblem,
    weights: PerTrajectory,
    theta: Theta,
    states: States,
    lam: Scalar,
):
    """One accepted LM step on (x, θ) with the matrix-free border (same contract as the dense one).

    Returns (θ, x, λ, status, accepted steps, trials, −J_b at the new point).
    """
    step = _Step.create(opts, problem, weights, theta, states)
    out = levenberg_marquardt(
        step.evaluate,
        lambda lin: (lin[0], lin[1]),
        step.solve,
        step.quad,
        (states, theta),
        rtol=opts.rtol,
        atol=0.0,
        max_steps=opts.max_trials,
        damping=lam,
        max_accepted=1,
        value=step.value,
    )
    x, th = out.z
    nll = problem.per_trajectory(th, x)
    return th, x, out.damping, out.status, out.accepted, out.steps, nll


@dataclass(frozen=True)
class _Step:
    """The LM driver's callbacks of one iteration, and what they share.

    A linearisation ``lin`` is (gx, gθ, A, diag(D) or 1, x, θ): the x-gradient, the θ-gradient,
    the x-blocks A_b (the identity for a trajectory that does not take part), θ's scaling, and
    the point; E_b, Eᵀ_b and D enter as Jacobian products at that point.
    """

    opts: Any
    problem: FitProblem
    ok_b: Array  # (B,) the trajectories that take part
    w: Array  # (B,) their weights, 1 or 0
    rho_x: Array
    rho_t: Array
    max_step: Array
    offset: Array
    eye_n: Array
    batch: int  # trajectories linearised together
    prior_hvp: Callable[[Theta, Theta], Theta]

    @classmethod
    def create(cls, opts, problem: FitProblem, weights, theta, states) -> _Step:
        """The shared values at the start of the iteration (weights > 0: taking part)."""
        ok_b = weights > 0
        w = jnp.where(ok_b, 1.0, 0.0).astype(states.dtype)
        dtype = states.dtype
        rho_x = jnp.asarray(opts.rho_x, dtype)
        rho_t = jnp.asarray(opts.rho_theta, dtype)
        max_step = jnp.asarray(opts.max_theta_step, dtype)
        offset = problem.offset(theta, weights)
        B, T, n = states.shape
        m = problem.data.y.shape[-1]
        eye_n = jnp.eye(n, dtype=dtype)
        batch = linearization_batch(T, n, m, dtype.itemsize, B)
        hvp = _prior_hvp(problem)
        return cls(opts, problem, ok_b, w, rho_x, rho_t, max_step, offset, eye_n, batch, hvp)

    def value(self, z):
        """−J at z = (x, θ) over the trajectories taking part, with θ's prior."""
        x, th = z
        nll = self.problem.per_trajectory(th, x)
        return (
            jnp.sum(jnp.where(self.ok_b, nll, 0.0)) - self.offset + self.problem.neg_log_prior(th)
        )

    def _participating(self, x):
        """(x, y, u, mask) with the trajectories not taking part replaced by one that does."""
        data = self.problem.data
        return _participating(self.ok_b, x, data.y, data.u, data.mask)

    def _data_of(self, ys, us, ms):
        return type(self.problem.data)(ys, us, ms)

    def evaluate(self, z):
        """(−J, lin) at z = (x, θ): the x-blocks one trajectory at a time, the θ-gradient."""
        x, th = z
        problem, ok_b = self.problem, self.ok_b
        xs, ys, us, ms = self._participating(x)

        def one(args):
            lin = linearize(problem.build, th, *args, wrt_theta=False)
            assert lin.grad_x is not None and lin.hess_x is not None
            return lin.value, lin.grad_x, lin.hess_x.diagonal, lin.hess_x.lower

        nll, gx, Ad, Al = jax.lax.map(one, (xs, ys, us, ms), batch_size=self.batch)
        okc = ok_b[:, None, None, None]
        A = BlockTridiagonal(jnp.where(okc, Ad, self.eye_n), jnp.where(okc, Al, 0.0))
        gx = jnp.where(ok_b[:, None, None], gx, 0.0)

        def theta_part(t):
            return jnp.sum(self.w * problem.per_trajectory(t, xs)) + problem.neg_log_prior(t)

        gt = jax.grad(theta_part)(th)
        if self.opts.border_scaling == "diagonal":
            dD = gauss_newton_diagonal(problem.build, th, xs, self._data_of(ys, us, ms), self.w)
        else:
            dD = jnp.ones_like(th)
        v = jnp.sum(jnp.where(ok_b, nll, 0.0)) - self.offset + problem.neg_log_prior(th)
        return v, (gx, gt, A, dD, x, th)

    def _product_at(self, lin):
        """``(z, v) -> (E z-part, Eᵀ/D part)``: the Gauss–Newton products at lin's point."""
        _, _, _, _, x, th = lin
        xs, ys, us, ms = self._participating(x)
        data = self._data_of(ys, us, ms)
        return gauss_newton_product(self.problem.build, th, xs, data, self.w, wrt_x=True)

    def _theta_damping(self, lin, lam):
        dD = lin[3]
        if self.opts.border_scaling == "diagonal":
            return marquardt_scale(dD, lam) + 2.0 * self.rho_t
        return lam * dD + 2.0 * self.rho_t

    def solve(self, lin, lam):
        """The damped step by the Schur complement on θ, applied by PCG; a capped θ-step."""
        gx, gt, A, dD, _, th = lin
        dA = jnp.diagonal(A.diagonal, axis1=-2, axis2=-1)
        A_d = lib.add_to_diagonal(A, marquardt_scale(dA, lam) + 2.0 * self.rho_x)
        sD = self._theta_damping(lin, lam)
        gn = self._product_at(lin)
        zeros_x = jnp.zeros_like(gx)

        def border(v):
            Ev, Dv = gn(zeros_x, v)
            return Ev, Dv + sD * v + self.prior_hvp(th, v)

        def border_t(z):
            return gn(z, jnp.zeros_like(th))[1]

        opts = self.opts
        precond = dD + sD if opts.border_scaling == "diagonal" else None
        sol = lib.arrowhead_solve_matrix_free(
            A_d,
            border,
            border_t,
            -gx,
            -gt,
            preconditioner=precond,
            cg_rtol=opts.cg_rtol,
            cg_max_steps=min(th.shape[0], 100) if opts.cg_max_steps is None else opts.cg_max_steps,
        )
        dx = jnp.where(self.ok_b[:, None, None], sol.dx, 0.0)
        ratio = jnp.max(jnp.abs(sol.dtheta) / jnp.maximum(jnp.abs(th), 1.0), initial=0.0)
        tiny = jnp.finfo(dx.dtype).tiny
        shrink = jnp.minimum(1.0, self.max_step / jnp.maximum(ratio, tiny))
        return (shrink * dx, shrink * sol.dtheta), sol.ok

    def quad(self, lin, delta):
        """The quadratic model's form δᵀ H δ (with the proximal terms) at lin."""
        dx, dth = delta
        _, _, A, _, _, th = lin
        gn = self._product_at(lin)
        Ex, Dt = gn(jnp.zeros_like(dx), dth)
        xAx = jnp.sum(dx * jax.vmap(lib.matvec)(A, dx))
        prox = self.rho_x * jnp.sum(dx**2) + self.rho_t * jnp.sum(dth**2)
        tDt = dth @ (Dt + self.prior_hvp(th, dth))
        return xAx + 2.0 * jnp.sum(dx * Ex) + tDt + 2.0 * prox


def _prior_hvp(problem: FitProblem):
    """``(θ, v) -> ∇²(−log p)(θ) v`` (zeros without a prior)."""
    if problem.log_prior is None:
        return lambda th, v: jnp.zeros_like(v)

    def hvp(th, v):
        return jax.jvp(jax.grad(problem.neg_log_prior), (th,), (v,))[1]

    return hvp
