"""A model that reads the raw inputs of a model fitted with a constant input channel.

Affine linear models (:func:`ceemx.baselines.fit_affine_sid`) and the neural state-space models
built on them read their records with a constant channel appended, u → [u, 1]
(:func:`ceemx.baselines.with_constant_input`): that is how a linear model carries an offset.
:class:`ConstantInput` appends the channel itself, so the identified model is scored, simulated,
saved and exported on the records as measured — p inputs, not p + 1.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Real

from ceemx.lib.typing import State
from ceemx.models.system import AbstractSystem

__all__ = ["ConstantInput"]


class ConstantInput(AbstractSystem):
    """``inner`` driven by [u, 1]: the raw inputs u of a model that reads a constant channel last.

    x_{t+1} = f(x_t, [u_t; 1], t),  y_t = g(x_t, [u_t; 1], t), with f, g those of ``inner``;
    its noise models and initial prior are ``inner``'s. ``input_dim`` is ``inner.input_dim − 1``.

    Attributes:
        inner: the model that reads [u, 1] (e.g. a :class:`~ceemx.systems.LinearSystem` from
            :func:`ceemx.baselines.fit_affine_sid`, or a hybrid of one).

    Raises:
        TypeError: ``inner`` is not a system.
        ValueError: ``inner`` takes no input (there is no constant channel to supply).

    Example:
        >>> raw = ConstantInput(refined.system)  # doctest: +SKIP
        >>> ceemx.benchmark_score(raw, test, n_init)  # the record as measured  # doctest: +SKIP
    """

    inner: AbstractSystem

    def __init__(self, inner: AbstractSystem):
        if not isinstance(inner, AbstractSystem):
            raise TypeError(f"`inner` must be a ceemx system; got {type(inner).__name__}.")
        if inner.input_dim < 1:
            raise ValueError("`inner` takes no input: it has no constant channel to supply.")
        self.inner = inner
        self.process_noise = inner.process_noise
        self.obs_noise = inner.obs_noise
        self.initial_prior = inner.initial_prior

    @property
    def state_dim(self) -> int:
        """n, as ``inner``."""
        return self.inner.state_dim

    @property
    def obs_dim(self) -> int:
        """m, as ``inner``."""
        return self.inner.obs_dim

    @property
    def input_dim(self) -> int:
        """p: ``inner``'s inputs less the constant channel."""
        return self.inner.input_dim - 1

    def _with_one(self, u: Float[Array, " p"]) -> Float[Array, " q"]:
        return jnp.concatenate([u, jnp.ones((1,), u.dtype)])

    def dynamics(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """``inner.dynamics(x, [u, 1], t)``."""
        return self.inner.dynamics(x, self._with_one(u), t)

    def observe(
        self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " m"]:
        """``inner.observe(x, [u, 1], t)``."""
        return self.inner.observe(x, self._with_one(u), t)

    def linear_observation(
        self, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> tuple[Float[Array, "m n"], Float[Array, " m"]] | None:
        """``inner.linear_observation([u, 1], t)``."""
        return self.inner.linear_observation(self._with_one(u), t)
