"""The identification problem shared by every fit solver: data, the trainable split of θ, prior.

A :class:`FitProblem` knows how to rebuild the system from the flat vector θ of its trainable
leaves and how to evaluate the CE-EM objective −J(x, θ) (paper Eq. 9) and the log-prior. It holds no
iterate: solvers keep (θ, x) in their state.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float, PyTree

from .data import Trajectories
from .lib.dense import symmetrize
from .models.system import AbstractSystem
from .objective import neg_log_joint_single, nll_offset
from .typing import PerTrajectory, Scalar, States, Theta

__all__ = ["FitProblem", "Trainable", "split_system", "trainable_mask"]

Trainable = Callable[[AbstractSystem], Any] | PyTree | None
"""Which leaves of a system learn: see :func:`trainable_mask`."""


def trainable_mask(system: AbstractSystem, trainable: Trainable = None) -> PyTree:
    """A boolean pytree over ``system`` marking the leaves that learn.

    Args:
        system: the model.
        trainable: ``None`` — every floating-point array of the model except its noise models and
            initial-state prior; a callable ``where(system)`` returning the leaves or sub-trees to
            learn (as in ``eqx.tree_at``), e.g. ``lambda s: (s.sigma, s.rho, s.beta)``; or a boolean
            pytree with the structure of ``system`` (an Equinox filter spec).
    """
    if trainable is None:
        mask = jtu.tree_map(eqx.is_inexact_array, system)
        frozen = jtu.tree_map(
            lambda _: False, (system.process_noise, system.obs_noise, system.initial_prior)
        )
        return eqx.tree_at(
            lambda s: (s.process_noise, s.obs_noise, s.initial_prior),
            mask,
            replace=frozen,
            is_leaf=lambda v: v is None,
        )
    if callable(trainable):
        mask = jtu.tree_map(lambda _: False, system)

        def where(s) -> tuple[Any, ...]:
            picked = trainable(s)
            return picked if isinstance(picked, tuple) else (picked,)

        replace = tuple(jtu.tree_map(eqx.is_inexact_array, c) for c in where(system))
        return eqx.tree_at(where, mask, replace=replace)
    return trainable


def split_system(
    system: AbstractSystem, trainable: Trainable = None
) -> tuple[Theta, PyTree, PyTree]:
    """(θ flat, params template, static part) for the trainable leaves of ``system``."""
    params, static = eqx.partition(system, trainable_mask(system, trainable))
    theta, _ = ravel_pytree(params)
    return theta, params, static


def _strong(a):
    return jnp.asarray(a, dtype=jnp.result_type(a)) if eqx.is_array(a) else a


class FitProblem(eqx.Module):
    """Data, the model split into trainable θ and the rest, and an optional log-prior.

    Attributes:
        template: the trainable sub-tree (its structure and shapes define the flat θ).
        static: the rest of the system.
        data: the observations.
        log_prior: ``None`` or a callable on the system returning log p(θ).
    """

    template: Any
    static: Any
    data: Trajectories
    log_prior: Callable[[AbstractSystem], Any] | None = eqx.field(static=True, default=None)

    @classmethod
    def create(
        cls,
        system: AbstractSystem,
        data: Trajectories,
        *,
        trainable: Trainable = None,
        log_prior: Callable[[AbstractSystem], Any] | None = None,
    ) -> tuple[FitProblem, Theta]:
        """The problem and the flat θ of ``system``'s trainable leaves."""
        theta, template, static = split_system(system, trainable)
        # Strongly typed θ and template: a weakly typed leaf (e.g. from jnp.asarray(10.0)) would
        # make the second epoch, whose θ comes back from a solver strongly typed, compile again.
        template = jtu.tree_map(_strong, template)
        return cls(template, static, data, log_prior), _strong(theta)

    def build(self, theta: Theta) -> AbstractSystem:
        """The system with trainable leaves set from the flat vector θ."""
        _, unravel = ravel_pytree(self.template)
        return eqx.combine(unravel(theta), self.static)

    def per_trajectory(
        self, theta: Theta, states: States, data: Trajectories | None = None
    ) -> PerTrajectory:
        """(B,) −J_b(x_b, θ), the negative log-likelihood of each trajectory (Eq. 9)."""
        data = self.data if data is None else data
        return jax.vmap(neg_log_joint_single, in_axes=(None, 0, 0, 0, 0))(
            self.build(theta), states, data.y, data.u, data.mask
        )

    def offset(self, theta: Theta, weights: PerTrajectory) -> Scalar:
        """Σ_b w_b·c_b, the x-independent constants of −J (see :func:`ceemx.objective.nll_offset`).

        −J − offset is ½‖whitened residuals‖² for Gaussian noise: the scale of every relative
        tolerance (normalising constants can dwarf the fit).
        """
        c = nll_offset(self.build(theta), self.data)
        return jnp.sum(jnp.where(weights > 0, weights * c, 0.0))

    def neg_log_prior(self, theta: Theta) -> Scalar:
        """−log p(θ) (zero without a prior)."""
        if self.log_prior is None:
            return jnp.zeros((), theta.dtype)
        return -self.log_prior(self.build(theta))

    def prior_terms(
        self, theta: Theta
    ) -> tuple[Scalar, Float[Array, " theta"], Float[Array, "theta theta"]]:
        """(−log p(θ), its gradient, its symmetrised Hessian); zeros without a prior."""
        P = theta.shape[0]
        if self.log_prior is None:
            zero = jnp.zeros((), theta.dtype)
            return zero, jnp.zeros((P,), theta.dtype), jnp.zeros((P, P), theta.dtype)
        value, grad = jax.value_and_grad(self.neg_log_prior)(theta)
        return value, grad, symmetrize(jax.hessian(self.neg_log_prior)(theta))
