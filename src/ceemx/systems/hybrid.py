"""Hybrid models: a learned term inside any gray-box model (the paper's Eq. 17 idea, generalised).

A physics model a user can write rarely holds all of the physics (friction shapes, overflow, belt
slip). :class:`Hybrid` wraps any :class:`~ceemx.AbstractSystem` and adds a learned term — an
Equinox module, :func:`learned_term` builds an ``eqx.nn.MLP`` — to its transition and/or its
observation; :class:`HybridContinuous` does the same for an
:class:`~ceemx.AbstractContinuousSystem`, adding the term to the *vector field* so that the
integrator (RK4, substeps, zero/first-order hold) is the physics model's own:

    discrete:    x_{t+1} = f_phys(x̃_t, u_t, t) + N_f(x̃_t, u_t)
    continuous:  ẋ = F_phys(x̃, u, t) + N_F(x̃, u)
    both:        y_t = g_phys(x̃_t, u_t, t) + N_g(x̃_t, u_t)

with x̃ the state projected into its physical bounds (below). Each learned term
(:class:`LearnedTerm`) normalises its inputs from data statistics, (x − μ_x)/s_x and
(u − μ_u)/s_u, and scales its output by s_out, so a network of unit-scale weights fits any units;
its output layer is zero-initialised, so a fresh hybrid *is* the physics model (J, simulation and
gradients of the physics parameters agree exactly) and a fit starts from the physics fit. The
statistics are fixed parameters (:func:`ceemx.param` ``fixed=True``), never learned;
:func:`ceemx.identification.hybrid_builder.hybrid` computes them from a record.

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
model's own noise models and fixed parameters never learn. :func:`weight_decay` is the Gaussian
(weight-decay) prior on the weights, for ``fit(..., log_prior=weight_decay)``.
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
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray, Real, Scalar

from ceemx.infra.options import check_int, check_positive
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import State
from ceemx.models.constraints import param
from ceemx.models.noise import AbstractNoise
from ceemx.models.system import AbstractContinuousSystem, AbstractSystem, GaussianPrior
from ceemx.systems.neural import init_mlp

__all__ = [
    "Blank",
    "Hybrid",
    "HybridContinuous",
    "LearnedTerm",
    "learned_term",
    "weight_decay",
]

Part = Literal["both", "physics", "term"]


class LearnedTerm(eqx.Module):
    """s_out ⊙ net([(x − μ_x)/s_x, (u − μ_u)/s_u]): a network on normalised states and inputs.

    Attributes:
        net: any Equinox module mapping the normalised (n + p) vector (only the state inputs
            when ``use_input`` is False) to an out-dimensional vector.
        x_mean, x_scale: (n,) state normalisation (fixed).
        u_mean, u_scale: (p,) input normalisation (fixed; empty when there is no input).
        out_scale: (out,) output scale s_out (fixed).
        prior_std: the weight-decay prior's standard deviation of each weight
            (:func:`weight_decay`; static).
        use_input: whether the network sees the input (static).
        targets: the entries of the model's vector the term adds to (static; ``None``: all, the
            network's output is then the whole vector). Restricting a dynamics term to the
            equations that miss physics (a friction force enters the velocity equation only)
            keeps the hidden states' meaning: a term on every equation can trade a change of
            the hidden coordinates for the missing physics.
        size: the length of the model's vector (static; the output length when ``targets`` is
            ``None``).
    """

    net: eqx.Module
    x_mean: Float[Array, " n"] = param(fixed=True)
    x_scale: Float[Array, " n"] = param(fixed=True)
    u_mean: Float[Array, " p"] = param(fixed=True)
    u_scale: Float[Array, " p"] = param(fixed=True)
    out_scale: Float[Array, " out"] = param(fixed=True)
    prior_std: float = eqx.field(static=True, default=1.0)
    use_input: bool = eqx.field(static=True, default=True)
    targets: tuple[int, ...] | None = eqx.field(static=True, default=None)
    size: int | None = eqx.field(static=True, default=None)

    def __call__(self, x: Float[Array, " n"], u: Float[Array, " p"]) -> Float[Array, " size"]:
        """The term's value at (x, u): a vector of the model's length."""
        z = (x - self.x_mean) / self.x_scale
        if self.use_input and self.u_mean.shape[0]:
            z = jnp.concatenate([z, (u - self.u_mean) / self.u_scale])
        out = self.out_scale * self.net(z)  # type: ignore[operator]
        if self.targets is None:
            return out
        assert self.size is not None
        return jnp.zeros((self.size,), out.dtype).at[jnp.asarray(self.targets)].set(out)


def learned_term(
    key: PRNGKeyArray,
    *,
    x_mean: ArrayLike,
    x_scale: ArrayLike,
    out_scale: ArrayLike,
    u_mean: ArrayLike | None = None,
    u_scale: ArrayLike | None = None,
    width: int = 16,
    depth: int = 2,
    activation: Callable = jnp.tanh,
    prior_std: float = 1.0,
    use_input: bool = True,
    targets: tuple[int, ...] | None = None,
    size: int | None = None,
    net: eqx.Module | None = None,
    dtype=None,
) -> LearnedTerm:
    """A :class:`LearnedTerm` around an ``eqx.nn.MLP`` whose output layer is zero.

    Args:
        key: PRNG key of the hidden layers' initial weights.
        x_mean: (n,) state mean μ_x.
        x_scale: (n,) state scale s_x (positive).
        out_scale: (out,) scale of the output (positive); its length is the network's output
            dimension (``len(targets)`` when given).
        u_mean: (p,) input mean μ_u (``None``: no input).
        u_scale: (p,) input scale s_u (positive; ``None``: no input).
        width: the MLP's hidden width.
        depth: the MLP's number of hidden layers.
        activation: the MLP's hidden activation.
        prior_std: standard deviation of the weight-decay prior (:func:`weight_decay`).
        use_input: whether the network sees the input.
        targets: the entries of the model's ``size``-vector the output is added to (``None``:
            all; :class:`LearnedTerm`).
        size: the model vector's length (required with ``targets``).
        net: any Equinox module instead of the MLP (used as given: zero its output yourself to
            start at the physics model).
        dtype: floating dtype (default: ``x_mean``'s, else JAX's default float).

    Raises:
        ValueError: non-positive or non-finite scales, mismatched lengths, bad width/depth.
    """
    # Host-side (NumPy) conversions and checks: op by op in JAX each compiled a small program.
    x_mean = np.asarray(x_mean)
    x_dtype = jax.dtypes.canonicalize_dtype(x_mean.dtype)
    dtype = dtype or (x_dtype if jnp.issubdtype(x_dtype, jnp.floating) else None)
    dtype = dtype or jax.dtypes.canonicalize_dtype(float)
    stored = jax.dtypes.canonicalize_dtype(dtype)  # what jnp.asarray(·, dtype) would store
    arrays = {
        "x_mean": np.atleast_1d(np.asarray(x_mean, stored)),
        "x_scale": np.atleast_1d(np.asarray(x_scale, stored)),
        "u_mean": np.asarray(() if u_mean is None else u_mean, stored).reshape(-1),
        "u_scale": np.asarray(() if u_scale is None else u_scale, stored).reshape(-1),
        "out_scale": np.atleast_1d(np.asarray(out_scale, stored)),
    }
    n, p, out = arrays["x_mean"].shape[0], arrays["u_mean"].shape[0], arrays["out_scale"].shape[0]
    for name, length in (("x_scale", n), ("u_scale", p)):
        if arrays[name].shape[0] != length:
            raise ValueError(
                f"`{name}` must have the length of its mean ({length}); got "
                f"{arrays[name].shape[0]}."
            )
    for name in ("x_scale", "u_scale", "out_scale"):
        a = arrays[name]
        if not bool(np.all(np.isfinite(a) & (a > 0))):
            raise ValueError(f"`{name}` must be positive and finite; got {a}.")
    for name in ("x_mean", "u_mean"):
        if not bool(np.all(np.isfinite(arrays[name]))):
            raise ValueError(f"`{name}` must be finite; got {arrays[name]}.")
    if targets is not None:
        targets = tuple(int(i) for i in targets)
        if size is None or len(targets) != out or len(set(targets)) != out:
            raise ValueError(
                f"`targets` must be {out} distinct indices (one per output) with `size` given; "
                f"got targets={targets}, size={size}."
            )
        if not all(0 <= i < size for i in targets):
            raise ValueError(f"`targets` must lie in [0, size = {size}); got {targets}.")
    check_positive("prior_std", prior_std)
    if net is None:
        check_int("width", width, 1)
        check_int("depth", depth, 0)
        n_in = n + (p if use_input else 0)
        net = init_mlp(key, n_in, out, width, depth, activation, dtype, 0.0)  # output zero
    assert net is not None
    return LearnedTerm(
        net,
        prior_std=float(prior_std),
        use_input=use_input,
        targets=targets,
        size=size,
        **{k: as_jax(a) for k, a in arrays.items()},
    )


def weight_decay(system: AbstractSystem) -> Scalar:
    """The weight-decay log-prior −½ Σ w²/σ² over every :class:`LearnedTerm` of ``system``.

    σ is each term's ``prior_std``.

    A Gaussian prior on the networks' weights and biases (weight decay), for
    ``ceemx.fit(model, data, log_prior=weight_decay)``; 0 for a system without learned terms.
    Constants are dropped (they do not move the fit).
    """
    terms = [
        leaf
        for leaf in jtu.tree_leaves(system, is_leaf=lambda v: isinstance(v, LearnedTerm))
        if isinstance(leaf, LearnedTerm)
    ]
    total = jnp.zeros(())
    for term in terms:
        weights = jtu.tree_leaves(eqx.filter(term.net, eqx.is_inexact_array))
        ss = sum((jnp.sum(jnp.square(w)) for w in weights), jnp.zeros(()))
        total = total - 0.5 * ss / term.prior_std**2
    return total


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
    if not (isinstance(sharpness, int | float) and 0 < sharpness < math.inf):
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
