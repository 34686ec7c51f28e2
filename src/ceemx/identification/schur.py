"""The Schur complement of the joint (x, θ) Gauss–Newton system.

Shared by the joint method (:class:`ceemx.JointLM`), the identifiability analysis and the
parameter covariance.

The joint normal equations are an arrowhead: per trajectory b a block-tridiagonal
A_b = J_xᵀWJ_x, a shared dense D = Σ_b J_θᵀWJ_θ and the border E_b = J_xᵀWJ_θ.
:func:`linearize_joint` forms them at (x, θ); :func:`schur_complement` eliminates the states,
S = D − Σ_b E_bᵀ A_b⁻¹ E_b: the Gauss–Newton curvature of −J in θ with the states integrated out
(its inverse is the Laplace covariance of θ; its near-null directions are the parameter
combinations the data do not determine).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ceemx.identification.problem import FitProblem
from ceemx.inference.objective import linearize
from ceemx.infra.compilation import jit
from ceemx.infra.policy import Runs, program, schur_work
from ceemx.lib.arrowhead import factor, schur_terms
from ceemx.lib.blocktri import BlockTridiagonal, is_finite
from ceemx.lib.dense import symmetrize
from ceemx.lib.typing import PerTrajectory, Scalar, States, Theta

__all__ = [
    "JointLinearization",
    "joint_evaluator",
    "linearize_joint",
    "schur_complement",
    "schur_complement_work",
]


class JointLinearization(NamedTuple):
    """The joint Gauss–Newton model at (x, θ), summed over the trajectories taking part."""

    grad_x: Float[Array, "B T n"]
    grad_theta: Float[Array, " theta"]
    A: BlockTridiagonal  # x-blocks per trajectory, leaves (B, T, ...)
    E: Float[Array, "B T n theta"]  # border
    D: Float[Array, "theta theta"]
    nll: Float[Array, " B"]  # −J_b (normalising constants included)


def _mask_tree(ok, tree):
    return jax.tree_util.tree_map(
        lambda a: jnp.where(ok.reshape(ok.shape + (1,) * (a.ndim - 1)), a, jnp.zeros_like(a)), tree
    )


def joint_evaluator(problem: FitProblem, weights: PerTrajectory, offset: Scalar):
    """``z = (x, θ) -> (value, JointLinearization)``; value = −J − offset − log p(θ)."""
    data = problem.data
    ok_b = weights > 0

    def evaluate(z):
        x, th = z
        lin = jax.vmap(
            lambda xb, y, u, m: linearize(problem.build, th, xb, y, u, m, wrt_theta=True)
        )(x, data.y, data.u, data.mask)
        # wrt_theta=True with wrt_x=True: every part of the linearisation is there.
        assert lin.grad_x is not None and lin.hess_x is not None
        assert lin.grad_theta is not None and lin.E is not None and lin.D is not None
        eye_n = jnp.eye(x.shape[-1], dtype=x.dtype)
        # Excluded trajectories get an identity x-block (their states stay put).
        A = BlockTridiagonal(
            jnp.where(ok_b[:, None, None, None], lin.hess_x.diagonal, eye_n),
            _mask_tree(ok_b, lin.hess_x.lower),
        )
        prior, prior_grad, prior_hess = problem.prior_terms(th)
        nll = jnp.where(ok_b, lin.value, 0.0)
        value = jnp.sum(nll) - offset + prior
        out = JointLinearization(
            grad_x=_mask_tree(ok_b, lin.grad_x),
            grad_theta=jnp.sum(_mask_tree(ok_b, lin.grad_theta), axis=0) + prior_grad,
            A=A,
            E=_mask_tree(ok_b, lin.E),
            D=jnp.sum(_mask_tree(ok_b, lin.D), axis=0) + prior_hess,
            nll=lin.value,
        )
        return value, out

    return evaluate


@jit
def linearize_joint(
    problem: FitProblem, weights: PerTrajectory, theta: Theta, states: States
) -> tuple[Scalar, JointLinearization]:
    """(value, :class:`JointLinearization`) at (x, θ) (the standard errors' Schur complement)."""
    offset = problem.offset(theta, weights)
    return joint_evaluator(problem, weights, offset)((states, theta))


def schur_complement_work(problem: FitProblem, theta: Theta, states: States, *rest):
    """:func:`schur_complement`'s work at these shapes (:func:`ceemx.infra.policy.schur_work`)."""
    del problem, rest
    B, T, n = states.shape
    return schur_work(B, T, n, theta.shape[0])


# once or twice per fit (the identifiability check, uncertainty): one-shot while that pays
@program(runs=Runs.ONCE, work=schur_complement_work)
def schur_complement(
    problem: FitProblem, theta: Theta, states: States, weights: PerTrajectory
) -> tuple[Float[Array, "theta theta"], Bool[Array, ""]]:
    """``(S, ok)``: the Schur complement of the joint Gauss–Newton matrix at (x, θ).

    S = D − Σ_b E_bᵀ A_b⁻¹ E_b (no damping, no proximal terms; weight-0 trajectories take no
    part): the Gauss–Newton curvature of −J in θ with the states eliminated. ``ok`` is False when
    some ``A_b`` factor is not finite (``S`` is then unreliable). The factorisation precedes the
    solves that read it: no two LAPACK calls are independent in this program.
    """
    _, lin = linearize_joint(problem, weights, theta, states)
    L, inv = factor(lin.A)
    a_ok = jnp.all(jax.vmap(is_finite)(L))
    EtZ, _ = schur_terms(L, inv, lin.E)  # Σ_b E_bᵀ A_b⁻¹ E_b by forward passes
    return symmetrize(lin.D - EtZ), a_ok
