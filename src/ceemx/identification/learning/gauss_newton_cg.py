"""Matrix-free Gauss–Newton: products with J_rᵀ W J_r by Jacobian-vector products, and a learner.

For many parameters (P ≈ 10⁵: K = 100 coupled Lorenz) neither the P × P Gauss–Newton matrix of the
learning step nor the joint method's border E_b (B·T·n·P) fits in memory. Both are only ever
needed as products: with r(x, θ) the residuals of every trajectory (observation and dynamics,
:func:`ceemx.inference.objective.residuals`) and W = SᵀS the noise models' curvature at the
current residuals (exactly the factors :func:`ceemx.inference.objective.linearize` uses),

    [A  E; Eᵀ  D] (δx, δθ) = J_rᵀ W J_r (δx, δθ),

one ``jax.linearize`` of r at the point (its residuals are kept) and, per product, one JVP and
one transposed JVP. :func:`gauss_newton_product` builds that product; :func:`gauss_newton_diagonal`
the exact diagonal of the θθ block (for Marquardt's scaling and a Jacobi preconditioner) one time
step at a time; :class:`GaussNewtonCGLearner` is Levenberg–Marquardt on the learning step (Eq. 11)
with the damped normal equations solved by truncated preconditioned CG
(:func:`ceemx.lib.arrowhead.pcg`). Nothing here is specific to a model.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ceemx.data.trajectories import Trajectories
from ceemx.identification.learning.learners import AbstractLearner, LearnInfo
from ceemx.identification.learning.learning_problem import AbstractLearningProblem, LearningProblem
from ceemx.inference.objective import residuals
from ceemx.infra.options import (
    check_choice,
    check_damping,
    check_int,
    check_nonnegative,
    check_rtol,
)
from ceemx.lib.arrowhead import pcg
from ceemx.lib.lm import levenberg_marquardt, marquardt_scale
from ceemx.lib.typing import PerTrajectory, States, Theta
from ceemx.models.system import AbstractSystem

__all__ = [
    "GaussNewtonCGLearner",
    "gauss_newton_diagonal",
    "gauss_newton_product",
]

Build = Callable[[Theta], AbstractSystem]


def _curvature(system: AbstractSystem, r_obs, r_dyn, mask, weights):
    """``(apply_v, apply_w)``: multiply (B, T, m) / (B, T−1, n) tangents by w_b·SᵀS per step."""
    on, pn = system.obs_noise, system.process_noise
    wb = weights[:, None, None]
    if on.diagonal_curvature:
        sv = jax.vmap(jax.vmap(on.sqrt_curvature_diagonal))(r_obs, mask)
        Wv = wb * sv**2
    else:
        Sv = jax.vmap(jax.vmap(on.sqrt_curvature))(r_obs, mask)
        Wv = wb[..., None] * jnp.swapaxes(Sv, -1, -2) @ Sv
    if pn.diagonal_curvature:
        sw = jax.vmap(jax.vmap(pn.sqrt_curvature_diagonal))(r_dyn)
        Ww = wb * sw**2
    else:
        Sw = jax.vmap(jax.vmap(pn.sqrt_curvature))(r_dyn)
        Ww = wb[..., None] * jnp.swapaxes(Sw, -1, -2) @ Sw

    def weigh(W, a):  # a per-step diagonal (B, T, d) or matrix (B, T, d, d) curvature
        return W * a if W.ndim == a.ndim else jnp.einsum("btij,btj->bti", W, a)

    return (lambda a: weigh(Wv, a)), (lambda a: weigh(Ww, a))


def gauss_newton_product(
    build: Build,
    theta: Theta,
    states: States,
    data: Trajectories,
    weights: PerTrajectory,
    *,
    wrt_x: bool = True,
) -> Callable[..., Any]:
    """The Gauss–Newton matrix of Σ_b w_b·(−J_b) as a product, linearised once at (x, θ).

    Observation and dynamics factors only (as :func:`ceemx.inference.objective.linearize`: the
    initial-state prior's curvature in x is not included, its θ-curvature is not part of D).
    Every trajectory must be finite at (x, θ); give excluded ones weight 0 (and finite stand-in
    states, as :meth:`AbstractLearningProblem.participating` does).

    Args:
        build: θ → system.
        theta: the flat parameter vector (P,).
        states: (B, T, n) states.
        data: the B trajectories' observations.
        weights: (B,) non-negative weights w_b.
        wrt_x: linearise in (x, θ) (the joint method) or in θ alone (the learning step).

    Returns:
        With ``wrt_x``: ``(dx, dθ) -> (A dx + E dθ, Eᵀ dx + D dθ)`` with dx (B, T, n) (A, E
        stacked over trajectories, the θ-part summed); else ``dθ -> D dθ``. Call it inside a
        compiled function; each call costs one JVP and one transposed JVP of the residuals.
    """

    def res(x, th):
        return jax.vmap(residuals, in_axes=(None, 0, 0, 0))(build(th), x, data.y, data.u)

    if wrt_x:
        (r_obs, r_dyn), jvp = jax.linearize(res, states, theta)
        primals: tuple = (states, theta)
    else:
        (r_obs, r_dyn), jvp = jax.linearize(lambda th: res(states, th), theta)
        primals = (theta,)
    transpose = jax.linear_transpose(jvp, *primals)
    apply_v, apply_w = _curvature(build(theta), r_obs, r_dyn, data.mask, weights)

    def product(*tangents):
        tv, tw = jvp(*tangents)
        out = transpose((apply_v(tv), apply_w(tw)))
        return out if wrt_x else out[0]

    return product


def _rows_jacobian(fun, theta, rows: int):
    """The (rows, P) Jacobian of ``fun`` at θ, by the cheaper mode."""
    if theta.shape[0] <= rows:
        return jax.jacfwd(fun)(theta)
    return jax.jacrev(fun)(theta)


def gauss_newton_diagonal(
    build: Build,
    theta: Theta,
    states: States,
    data: Trajectories,
    weights: PerTrajectory,
) -> Float[Array, " theta"]:
    """diag(D), D = Σ_b w_b J_θᵀ W J_θ (observation and dynamics factors), exactly.

    One time step at a time (``lax.scan`` over trajectories and steps): peak memory O((m + n)·P),
    cost about one dense θ-Jacobian (the per-step rows by reverse mode when P is the larger side).
    """
    system = build(theta)
    on, pn = system.obs_noise, system.process_noise
    T = states.shape[1]
    ts = jnp.arange(T)

    def one(carry, inp):
        x, y, u, mask, w = inp
        r_obs, r_dyn = residuals(system, x, y, u)

        def obs_step(acc, s):
            xt, yt, ut, mt, rt, t = s
            S = on.sqrt_curvature(rt, mt)
            J = _rows_jacobian(lambda th: S @ (yt - build(th).observe(xt, ut, t)), theta, rt.size)
            return acc + jnp.sum(J**2, axis=0), None

        def dyn_step(acc, s):
            xt, ut, rt, t = s
            S = pn.sqrt_curvature(rt)
            J = _rows_jacobian(lambda th: S @ build(th).dynamics(xt, ut, t), theta, rt.size)
            return acc + jnp.sum(J**2, axis=0), None

        zero = jnp.zeros_like(theta)
        d_obs, _ = jax.lax.scan(obs_step, zero, (x, y, u, mask, r_obs, ts))
        d_dyn, _ = jax.lax.scan(dyn_step, zero, (x[:-1], u[:-1], r_dyn, ts[:-1]))
        return carry + w * (d_obs + d_dyn), None

    out, _ = jax.lax.scan(one, jnp.zeros_like(theta), (states, data.y, data.u, data.mask, weights))
    return out


class GaussNewtonCGLearner(AbstractLearner):
    """Matrix-free Levenberg–Marquardt for the learning step: truncated CG on the normal equations.

    The learner for many parameters, where :class:`LMLearner`'s dense P × P Gauss–Newton
    matrices do not fit. Each iteration solves (H + λ·s) δ = −g by preconditioned CG, H the
    Gauss–Newton matrix of Σ_b w_b (−J_b) at fixed states plus 2ρ_θ and the log-prior's Hessian,
    applied as products (one JVP and one transposed JVP of the residuals per CG step:
    :func:`gauss_newton_product`); steps are accepted on actual against predicted decrease and λ
    is adapted as in :class:`LMLearner`. CG stops at ``cg_rtol`` or ``cg_max_steps`` (an inexact
    step: a truncated CG iterate is still a descent direction of the model). Needs a
    :class:`~ceemx.identification.learning.LearningProblem` (CE-EM's Eq. 11) and Gauss–Newton
    noise factors (any noise model with a curvature factor, as the dense learner).

    Scaling (``scaling``):

    * ``"diagonal"`` (default): s = diag(H) (the observation, dynamics and ρ_θ parts), Marquardt's
      per-parameter damping as :class:`LMLearner`, and (diag(H) + λ·s) as CG's Jacobi
      preconditioner. The exact diagonal costs about one dense θ-Jacobian, one time step at a
      time (:func:`gauss_newton_diagonal`), once per ``run`` (at the starting θ).
    * ``"identity"``: s = 1 (Levenberg's damping) and no preconditioner: nothing beyond the
      products, for when the diagonal costs too much.

    With ``damping=0`` and CG to convergence one iteration is the Gauss–Newton step, equal to
    :class:`LMLearner`'s (tested).

    Attributes:
        max_steps: bound on LM iterations (accepted or rejected) per EM epoch.
        rtol, atol: convergence on the decrease of the objective (as :class:`LMLearner`).
        damping: initial λ.
        cg_rtol: CG's relative residual tolerance.
        cg_max_steps: bound on CG iterations per LM iteration.
        scaling: ``"diagonal"`` or ``"identity"`` (above).
    """

    max_steps: int = eqx.field(default=20, static=True)
    rtol: float = 1e-12
    atol: float = 0.0
    damping: float = 1e-3
    cg_rtol: float = 1e-3
    cg_max_steps: int = eqx.field(default=50, static=True)
    scaling: str = eqx.field(default="diagonal", static=True)

    def __check_init__(self):
        check_int("max_steps", self.max_steps, 1)
        check_int("cg_max_steps", self.cg_max_steps, 1)
        check_nonnegative("atol", self.atol)
        for name in ("rtol", "cg_rtol"):
            check_rtol(name, getattr(self, name))
        check_choice("scaling", self.scaling, ("diagonal", "identity"))
        # λ is relative to the curvature (Marquardt) only with diagonal scaling
        check_damping("damping", self.damping, self.rtol if self.scaling == "diagonal" else 0.0)

    def run(
        self, problem: AbstractLearningProblem, theta: Theta, state: Any
    ) -> tuple[Theta, Any, LearnInfo]:
        """LM iterations from θ, each a truncated CG solve."""
        if not isinstance(problem, LearningProblem):
            raise TypeError(
                "GaussNewtonCGLearner needs a LearningProblem (the CE-EM learning step at fixed "
                f"states); got {type(problem).__name__}. Use LMLearner or LBFGSLearner."
            )
        offset = problem.offset(theta)
        states, data = problem.participating(problem.states, problem.data)
        w = jnp.where(problem.weights > 0, problem.weights, 0.0)
        build = problem.build
        rho2 = 2.0 * problem.rho_theta
        reg_hvp = _prior_hvp(problem)

        def value(th):
            return problem.value(th) - offset

        if self.scaling == "diagonal":
            diag = gauss_newton_diagonal(build, theta, states, data, w) + rho2
        else:
            diag = jnp.ones_like(theta)

        def matvec_at(th):
            product = gauss_newton_product(build, th, states, data, w, wrt_x=False)
            return lambda v: product(v) + rho2 * v + reg_hvp(th, v)

        def evaluate(th):
            v, g = jax.value_and_grad(value)(th)
            return v, (th, g)

        def solve(lin, lam):
            th, g = lin
            H = matvec_at(th)
            if self.scaling == "diagonal":
                damp = marquardt_scale(diag, lam)
                precond = diag + damp
            else:
                damp = lam * diag
                precond = None
            if precond is None:
                m_inv = jnp.ones_like(th)
            else:  # a parameter without curvature (and λ = 0) keeps a unit preconditioner
                m_inv = jnp.where(precond > 0, 1.0 / jnp.where(precond > 0, precond, 1.0), 1.0)
            delta, steps, _, broken = pcg(
                lambda v: H(v) + damp * v, -g, m_inv, self.cg_rtol, self.cg_max_steps
            )
            # Non-positive curvature (an indefinite prior): keep the CG iterate before it when
            # there is one (still a descent direction), otherwise fail (λ grows).
            ok = jnp.all(jnp.isfinite(delta)) & (~broken | (steps > 1))
            return delta, ok

        def quad(lin, d):
            return d @ matvec_at(lin[0])(d)

        out = levenberg_marquardt(
            evaluate,
            lambda lin: lin[1],
            solve,
            quad,
            theta,
            rtol=self.rtol,
            atol=self.atol,
            max_steps=self.max_steps,
            damping=self.damping,
            value=value,
        )
        v0 = problem.value(theta)
        return out.z, state, LearnInfo(v0, out.value + offset, out.steps, out.status)


def _prior_hvp(problem: LearningProblem):
    """``(θ, v) -> ∇²(−log p)(θ) v`` (zeros without a prior)."""
    if problem.problem.log_prior is None:
        return lambda th, v: jnp.zeros_like(v)

    def hvp(th, v):
        return jax.jvp(jax.grad(problem.problem.neg_log_prior), (th,), (v,))[1]

    return hvp
