"""Hybrid models: a learned term inside any gray-box model (the paper's Eq. 17 idea, generalised).

A physics model a user can write rarely holds all of the physics (friction shapes, overflow, belt
slip). :class:`Hybrid` wraps any :class:`~ceemx.AbstractSystem` and adds a learned term — an
Equinox module, :func:`~ceemx.systems.learned_term.learned_term` builds an ``eqx.nn.MLP`` — to
its transition and/or its observation; :class:`HybridContinuous` does the same for an
:class:`~ceemx.AbstractContinuousSystem`, adding the term to the *vector field* so that the
integrator (RK4, substeps, zero/first-order hold) is the physics model's own:

    discrete:    x_{t+1} = f_phys(x̃_t, u_t, t) + N_f(x̃_t, u_t)
    continuous:  ẋ = F_phys(x̃, u, t) + N_F(x̃, u)
    both:        y_t = g_phys(x̃_t, u_t, t) + N_g(x̃_t, u_t)

with x̃ the state projected into its physical bounds (below). Each learned term
(:class:`~ceemx.systems.learned_term.LearnedTerm`) normalises its inputs from data statistics,
(x − μ_x)/s_x and (u − μ_u)/s_u, and scales its output by s_out, so a network of unit-scale
weights fits any units; its output layer is zero-initialised, so a fresh hybrid *is* the physics
model (J, simulation and gradients of the physics parameters agree exactly) and a fit starts from
the physics fit. The statistics are fixed parameters (:func:`ceemx.param` ``fixed=True``), never
learned; :func:`ceemx.identification.hybrid_builder.hybrid` computes them from a record.

**Bounded states.** ``lower``/``upper`` (n-vectors, ±inf where free) state that a hidden state is
physically bounded (a tank level ≥ 0). Every state the model reads is projected smoothly into the
bounds, x̃ = lower + softplus(β(x − lower))/β (and the mirror image at ``upper``), with the
sharpness β = ``bound_sharpness``/s_x; the transition's output is projected the same way. A
free-run simulation therefore never leaves the bounds, and in smoothing a state outside them
explains nothing the projected state does not, while its dynamics residual pulls it back in
(the smoothed state lies within the bounds up to the process noise). Far inside the bounds the
projection is the identity to ≈ e^{−β·distance}/β.

**Which parts learn.** :meth:`Hybrid.trainable` returns a ``trainable`` filter for
:func:`ceemx.fit`: ``"both"`` (physics θ and weights), ``"physics"`` or ``"term"``; the physics
model's own noise models and fixed parameters never learn.
:func:`~ceemx.systems.learned_term.weight_decay` is the Gaussian (weight-decay) prior on the
weights, for ``fit(..., log_prior=weight_decay)``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

from ceemx.lib.typing import State
from ceemx.models.noise import AbstractNoise
from ceemx.models.system import AbstractContinuousSystem, AbstractSystem, GaussianPrior
from ceemx.systems.learned_term import LearnedTerm

__all__ = ["Blank", "Hybrid", "HybridContinuous"]

Part = Literal["both", "physics", "term"]


def _project(x, lower, upper, sharpness):
    """Project: lower + softplus(β(x − lower))/β, then the mirror at upper (identity at ±inf)."""
    lo_ok, hi_ok = jnp.isfinite(lower), jnp.isfinite(upper)
    lo = jnp.where(lo_ok, lower, 0.0)
    hi = jnp.where(hi_ok, upper, 0.0)
    above = lo + jax.nn.softplus(sharpness * (x - lo)) / sharpness
    x = jnp.where(lo_ok, above, x)
    below = hi - jax.nn.softplus(sharpness * (hi - x)) / sharpness
    return jnp.where(hi_ok, below, x)


class _HybridMixin(eqx.Module):
    """What both hybrids share: the learned terms, the bounds and the trainable filter."""

    physics: eqx.AbstractVar[AbstractSystem]
    dynamics_term: eqx.AbstractVar[LearnedTerm | None]
    observation_term: eqx.AbstractVar[LearnedTerm | None]
    lower: eqx.AbstractVar[tuple[float, ...]]
    upper: eqx.AbstractVar[tuple[float, ...]]
    sharpness: eqx.AbstractVar[tuple[float, ...]]

    @property
    def state_dim(self) -> int:
        """n, the physics model's."""
        return self.physics.state_dim

    @property
    def obs_dim(self) -> int:
        """m, the physics model's."""
        return self.physics.obs_dim

    def project(self, x: State) -> State:
        """x̃: the state projected smoothly into [lower, upper] (identity where unbounded)."""
        if all(map(math.isinf, self.lower + self.upper)):
            return x

        def const(v):
            return jnp.asarray(v, x.dtype)

        return _project(x, const(self.lower), const(self.upper), const(self.sharpness))

    def observe(
        self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " m"]:
        """g_phys(x̃, u, t) + N_g(x̃, u)."""
        xt = self.project(x)
        y = self.physics.observe(xt, u, t)
        if self.observation_term is not None:
            y = y + self.observation_term(xt, self._current(u))
        return y

    def _current(self, u):
        return u

    def _wrap(self, physics, dynamics_term, observation_term, bounds, noise) -> None:
        """Set the parts, bounds, noise and prior (the physics' own where ``None``).

        The constructors' shared part, called from ``__init__`` only.
        """
        self.physics = physics
        self.dynamics_term = dynamics_term
        self.observation_term = observation_term
        self.lower, self.upper, self.sharpness = bounds
        fields = ("process_noise", "obs_noise", "initial_prior")
        for name, value in zip(fields, noise, strict=True):
            setattr(self, name, getattr(physics, name) if value is None else value)

    def trainable(self, part: Part = "both") -> Callable:
        """A ``trainable`` filter for :func:`ceemx.fit`: ``"both"``, ``"physics"`` or ``"term"``.

        ``"physics"``: the physics model's parameters (its noise models, prior and fixed
        parameters excepted); ``"term"``: the learned terms' weights; ``"both"``: both.
        """
        if part not in ("both", "physics", "term"):
            raise ValueError(f"`part` must be 'both', 'physics' or 'term'; got {part!r}.")

        names = _physics_parameters(self.physics) if part in ("both", "physics") else []
        nets = [t for t in ("dynamics_term", "observation_term") if getattr(self, t) is not None]
        nets = nets if part in ("both", "term") else []

        def select(s) -> tuple:  # structural: also called on Equinox's boolean masks
            return tuple(getattr(s.physics, f) for f in names) + tuple(
                getattr(s, t).net for t in nets
            )

        return select


def _physics_parameters(physics: AbstractSystem) -> list[str]:
    """The physics model's parameter fields (not its noise models or prior, not static)."""
    out = []
    for f in dataclasses.fields(physics):
        if f.name in ("process_noise", "obs_noise", "initial_prior") or f.metadata.get("static"):
            continue
        if any(eqx.is_inexact_array(leaf) for leaf in jtu.tree_leaves(getattr(physics, f.name))):
            out.append(f.name)
    return out


def _bounds(physics: AbstractSystem, lower, upper, sharpness, *terms):
    """(lower, upper, β) as tuples of n floats; β = ``sharpness`` / the first term's state scale."""
    n = physics.state_dim

    def vector(v, fill):
        a = np.broadcast_to(np.asarray(fill if v is None else v, float), (n,))
        return tuple(float(e) for e in a)

    try:
        lo, hi = vector(lower, -math.inf), vector(upper, math.inf)
    except ValueError:
        shapes = (np.shape(lower), np.shape(upper))
        raise ValueError(
            f"`lower`/`upper` must be scalars or {n}-vectors; got shapes {shapes[0]} and "
            f"{shapes[1]}."
        ) from None
    for name, v in (("lower", lo), ("upper", hi)):
        if any(math.isnan(a) for a in v):
            raise ValueError(f"`{name}` must not be NaN; got {v}.")
    if any(a >= b for a, b in zip(lo, hi, strict=True)):
        raise ValueError(f"`lower` must be below `upper` in every entry; got {lo} and {hi}.")
    number = isinstance(sharpness, int | float) and not isinstance(sharpness, bool)
    if not (number and 0 < sharpness < math.inf):
        raise ValueError(f"`bound_sharpness` must be a positive finite number; got {sharpness!r}.")
    scales = [t.x_scale for t in terms if t is not None]
    scale = np.asarray(scales[0], float) if scales else np.ones(n)
    return lo, hi, tuple(float(sharpness / s) for s in scale)


class Hybrid(_HybridMixin, AbstractSystem):
    """x_{t+1} = f_phys(x̃, u, t) + N_f(x̃, u) (projected), y = g_phys(x̃, u, t) + N_g(x̃, u).

    A discrete-time physics model with learned terms (module notes). Build it with
    :func:`ceemx.identification.hybrid_builder.hybrid` (statistics from a record) or directly.

    Attributes:
        physics: the physics model (its θ is learned with the weights, or alone).
        dynamics_term: the learned transition term (n outputs) or ``None``.
        observation_term: the learned observation term (m outputs) or ``None``.
        lower, upper: n state bounds (static floats; ±inf where free).
        sharpness: n values of the projection's β per state (static).
    """

    physics: AbstractSystem
    dynamics_term: LearnedTerm | None
    observation_term: LearnedTerm | None
    lower: tuple[float, ...] = eqx.field(static=True)
    upper: tuple[float, ...] = eqx.field(static=True)
    sharpness: tuple[float, ...] = eqx.field(static=True)

    def __init__(
        self,
        physics: AbstractSystem,
        dynamics_term: LearnedTerm | None = None,
        observation_term: LearnedTerm | None = None,
        *,
        lower: ArrayLike | None = None,
        upper: ArrayLike | None = None,
        bound_sharpness: float = 50.0,
        process_noise: AbstractNoise | None = None,
        obs_noise: AbstractNoise | None = None,
        initial_prior: GaussianPrior | None = None,
    ):
        """Wrap ``physics`` (noise and prior default to the physics model's own)."""
        _check_physics(physics, AbstractSystem)
        self._wrap(
            physics,
            dynamics_term,
            observation_term,
            _bounds(physics, lower, upper, bound_sharpness, dynamics_term, observation_term),
            (process_noise, obs_noise, initial_prior),
        )

    @property
    def input_dim(self) -> int:
        """p, the physics model's."""
        return self.physics.input_dim

    def dynamics(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """The projected f_phys(x̃, u, t) + N_f(x̃, u)."""
        xt = self.project(x)
        nxt = self.physics.dynamics(xt, u, t)
        if self.dynamics_term is not None:
            nxt = nxt + self.dynamics_term(xt, u)
        return self.project(nxt)


class HybridContinuous(_HybridMixin, AbstractContinuousSystem):
    """ẋ = F_phys(x̃, u, t) + N_F(x̃, u), y = g_phys(x̃, u, t) + N_g(x̃, u), integrated as the physics.

    A continuous-time physics model with learned terms (module notes): ``dt``, ``hold``,
    ``substeps`` and ``integrator`` are the physics model's, so the learned term is integrated by
    the same RK4 steps as the physics. Under a first-order hold the term sees the interpolated
    input (the vector field's) and the observation term u_t.

    Attributes:
        physics: the continuous-time physics model.
        dynamics_term: the learned vector-field term (n outputs) or ``None``.
        observation_term: the learned observation term (m outputs) or ``None``.
        lower, upper: n state bounds (static floats; ±inf where free).
        sharpness: n values of the projection's β per state (static).
    """

    physics: AbstractContinuousSystem  # pyright: ignore[reportIncompatibleVariableOverride]
    dynamics_term: LearnedTerm | None
    observation_term: LearnedTerm | None
    lower: tuple[float, ...] = eqx.field(static=True)
    upper: tuple[float, ...] = eqx.field(static=True)
    sharpness: tuple[float, ...] = eqx.field(static=True)

    def __init__(
        self,
        physics: AbstractContinuousSystem,
        dynamics_term: LearnedTerm | None = None,
        observation_term: LearnedTerm | None = None,
        *,
        lower: ArrayLike | None = None,
        upper: ArrayLike | None = None,
        bound_sharpness: float = 50.0,
        process_noise: AbstractNoise | None = None,
        obs_noise: AbstractNoise | None = None,
        initial_prior: GaussianPrior | None = None,
    ):
        """Wrap ``physics`` (noise, prior and integration options default to the physics')."""
        _check_physics(physics, AbstractContinuousSystem)
        self._wrap(
            physics,
            dynamics_term,
            observation_term,
            _bounds(physics, lower, upper, bound_sharpness, dynamics_term, observation_term),
            (process_noise, obs_noise, initial_prior),
        )
        self.dt = physics.dt
        self.hold = physics.hold
        self.substeps = physics.substeps
        self.integrator = physics.integrator

    @property
    def control_dim(self) -> int:
        """p, the physics model's."""
        return self.physics.control_dim

    def vector_field(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """F_phys(x̃, u, t) + N_F(x̃, u)."""
        xt = self.project(x)
        dx = self.physics.vector_field(xt, u, t)
        if self.dynamics_term is not None:
            dx = dx + self.dynamics_term(xt, u)
        return dx

    def dynamics(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """The physics model's integration step of the hybrid vector field, projected."""
        return self.project(AbstractContinuousSystem.dynamics(self, x, u, t))

    def _current(self, u):
        return self.current_input(u)

    def default_state_mean(self) -> State | None:
        """The physics model's."""
        return self.physics.default_state_mean()


def _check_physics(physics, cls) -> None:
    if not isinstance(physics, cls):
        raise TypeError(f"`physics` must be a ceemx.{cls.__name__}; got {type(physics).__name__}.")


class Blank(AbstractContinuousSystem):
    """ẋ = 0, y = x[observed]: no physics — a learned term alone is a neural state-space model.

    ``hybrid(Blank(...), data)`` gives ẋ = N(x, u), y = x[observed] (+ a learned observation term
    if asked for): the "learned term alone" of an ablation, trained by CE-EM like any hybrid.

    Attributes:
        n: the state dimension (static).
        observed: the state entries that are the outputs, one per output (static).
        p: the number of inputs (static).
    """

    n: int = eqx.field(static=True)
    observed: tuple[int, ...] = eqx.field(static=True)
    p: int = eqx.field(static=True, default=0)

    def __check_init__(self):
        if not (isinstance(self.n, int) and self.n >= 1):
            raise ValueError(f"`n` must be a positive integer; got {self.n!r}.")
        if not self.observed or not all(0 <= i < self.n for i in self.observed):
            raise ValueError(f"`observed` must be indices in [0, {self.n}); got {self.observed}.")

    @property
    def state_dim(self) -> int:
        """The state dimension n."""
        return self.n

    @property
    def obs_dim(self) -> int:
        """The number of observed states."""
        return len(self.observed)

    @property
    def control_dim(self) -> int:
        """The number of inputs p."""
        return self.p

    def vector_field(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """Zero."""
        return jnp.zeros_like(x)

    def observe(
        self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " m"]:
        """x[observed]."""
        return x[jnp.asarray(self.observed)]
