"""The learning step's objective (paper Eq. 11) over a flat vector of the trainable parameters."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from ..data import Trajectories
from ..models.system import AbstractSystem
from ..objective import linearize, neg_log_joint_single, nll_offset

__all__ = ["LearningProblem", "trainable_mask", "split_system"]


def trainable_mask(system: AbstractSystem, trainable=None):
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
        as_tuple = isinstance(trainable(system), tuple)

        def where(s):
            return tuple(trainable(s)) if as_tuple else (trainable(s),)

        replace = tuple(jtu.tree_map(eqx.is_inexact_array, c) for c in where(system))
        return eqx.tree_at(where, mask, replace=replace)
    return trainable


def split_system(system: AbstractSystem, trainable=None):
    """(θ flat, params template, static part) for the trainable leaves of ``system``."""
    params, static = eqx.partition(system, trainable_mask(system, trainable))
    theta, _ = ravel_pytree(params)
    return theta, params, static


class LearningProblem(eqx.Module):
    """min_θ Σ_b w_b (−J_b(x_b, θ)) + ρ_θ‖θ − θ_ref‖² − log p(θ)  (Eq. 11), θ the trainable leaves.

    Attributes:
        template: the trainable sub-tree (its structure and shapes define the flat θ).
        static: the rest of the system.
        states: (B, T, n) fixed state trajectories.
        data: the observations.
        weights: (B,) 1 for trajectories that take part, 0 for excluded (failed) ones.
        theta_ref: θᵏ, the centre of the trust region.
        rho_theta: ρ_θ.
        log_prior: ``None`` or a callable on the system returning log p(θ).
    """

    template: Any
    static: Any
    states: Float[Array, "B T n"]
    data: Trajectories
    weights: Float[Array, " B"]
    theta_ref: Float[Array, " P"]
    rho_theta: Array
    log_prior: Callable | None = eqx.field(static=True, default=None)

    def build(self, theta: Array) -> AbstractSystem:
        """The system with trainable leaves set from the flat vector θ."""
        _, unravel = ravel_pytree(self.template)
        return eqx.combine(unravel(theta), self.static)

    def _regulariser(self, theta):
        d = theta - self.theta_ref
        val = self.rho_theta * jnp.sum(d**2)
        if self.log_prior is not None:
            val = val - self.log_prior(self.build(theta))
        return val

    def per_trajectory(self, theta: Array, states=None, data=None) -> Array:
        """(B,) −J_b(x_b, θ)."""
        states = self.states if states is None else states
        data = self.data if data is None else data
        system = self.build(theta)
        return jax.vmap(neg_log_joint_single, in_axes=(None, 0, 0, 0, 0))(
            system, states, data.y, data.u, data.mask
        )

    def _participating(self):
        """(states, data) with each excluded trajectory replaced by a participating one.

        Excluded trajectories (weight 0, e.g. failed smoothing) can have non-finite terms; masking
        their values with ``jnp.where`` is not enough under differentiation (0·∞ = NaN in the
        gradient), so their inputs are swapped for finite ones before evaluation.
        """
        ok = self.weights > 0
        ref = jnp.argmax(ok)

        def pick(a):
            return jnp.where(ok.reshape((-1,) + (1,) * (a.ndim - 1)), a, a[ref][None])

        return pick(self.states), jtu.tree_map(pick, self.data)

    def value(self, theta: Array) -> Array:
        """The learning objective (scalar)."""
        states, data = self._participating()
        nll = jnp.sum(jnp.where(self.weights > 0, self.per_trajectory(theta, states, data), 0.0))
        return nll + self._regulariser(theta)

    def minibatch_value(self, theta: Array, idx: Array) -> Array:
        """Unbiased estimate of :meth:`value` from the trajectories ``idx``."""
        states, data = self._participating()
        states = states[idx]
        data = data[idx]
        w = self.weights[idx]
        nll = jnp.sum(jnp.where(w > 0, self.per_trajectory(theta, states, data), 0.0))
        scale = jnp.sum(self.weights) / jnp.maximum(jnp.sum(w), 1.0)
        return scale * nll + self._regulariser(theta)

    def offset(self, theta: Array) -> Array:
        """The x-independent constants of the objective (see :func:`ceemx.objective.nll_offset`)."""
        off = nll_offset(self.build(theta), self.data)
        return jnp.sum(jnp.where(self.weights > 0, off, 0.0))

    def gauss_newton(self, theta: Array):
        """(value, gradient, Gauss–Newton matrix) of the objective at θ."""
        lin = jax.vmap(
            lambda x, y, u, m: linearize(self.build, theta, x, y, u, m, wrt_theta=True, wrt_x=False)
        )(self.states, self.data.y, self.data.u, self.data.mask)
        ok = self.weights > 0
        value = jnp.sum(jnp.where(ok, lin.value, 0.0))
        grad = jnp.sum(jnp.where(ok[:, None], lin.grad_theta, 0.0), axis=0)
        hess = jnp.sum(jnp.where(ok[:, None, None], lin.D, 0.0), axis=0)
        reg, reg_grad = jax.value_and_grad(self._regulariser)(theta)
        value = value + reg
        grad = grad + reg_grad
        hess = hess + 2.0 * self.rho_theta * jnp.eye(theta.shape[0], dtype=theta.dtype)
        if self.log_prior is not None:
            h = jax.hessian(lambda th: -self.log_prior(self.build(th)))(theta)
            hess = hess + 0.5 * (h + h.T)
        return value, grad, hess
