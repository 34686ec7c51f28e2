"""State-space systems: x_{t+1} = f_θ(x_t, u_t, t) + w_t,  y_t = g_θ(x_t, u_t, t) + v_t  (Eq. 1)."""

from __future__ import annotations

import abc
import dataclasses
import functools
import math
from typing import Any, ClassVar, Literal, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float, Real

from ceemx.lib.tree import as_jax, value_repr
from ceemx.lib.typing import Scalar, State
from ceemx.models.constraint_checks import check_constraints
from ceemx.models.noise import AbstractNoise, as_noise

__all__ = [
    "AbstractSystem",
    "AbstractContinuousSystem",
    "GaussianPrior",
    "float_dtype",
    "rk4_step",
    "with_noise",
]

_S = TypeVar("_S", bound="AbstractSystem")


class GaussianPrior(eqx.Module):
    """Initial-state prior x₁ ~ N(mean, Σ), Σ given by a noise model on the deviation x₁ − mean."""

    def __repr__(self) -> str:
        """Equinox's form, with the values of small arrays (``scale=0.05``, not ``f64[]``)."""
        return value_repr(self)

    mean: State
    noise: AbstractNoise

    def __init__(self, mean: ArrayLike, noise: AbstractNoise):
        self.mean = as_jax(mean)  # a NumPy value transferred, not staged through a program
        self.noise = noise

    def nll(self, x1: State) -> Scalar:
        """−log p(x₁)."""
        return self.noise.nll(x1 - self.mean)


def _unset() -> Any:
    return None


def _noise_argument(value: AbstractNoise | ArrayLike | None) -> Any:
    """Converter of the noise fields: their ``__init__`` also takes scales and ``None``.

    Scales and ``None`` are resolved by the generated ``__init__`` (see
    :meth:`AbstractSystem.__init_subclass__`); ``__check_init__`` rejects anything left unresolved.
    """
    return value


_NOISE_FIELDS = ("process_noise", "obs_noise", "initial_prior")


class _DefaultsHook:
    """``AbstractSystem.__post_init__``: resolves the noise defaults (``None``, scales).

    A descriptor that exists only on classes with Equinox's generated ``__init__``: on a class
    with a hand-written ``__init__`` (which sets the noise itself) attribute lookup fails, so
    Equinox does not warn about a ``__post_init__`` that would never run.
    """

    def __get__(self, instance, owner):
        if not getattr(owner, "_generated_init", True):
            raise AttributeError("__post_init__")
        if instance is None:
            return _resolve_defaults
        return functools.partial(_resolve_defaults, instance)


def _resolve_defaults(system: AbstractSystem) -> None:
    system._resolve_defaults()


class AbstractSystem(eqx.Module):
    """A discrete-time partially observed system with additive noise (paper Eq. 1).

    Subclasses define the model class f_θ, g_θ (:meth:`dynamics`, :meth:`observe`, and the
    dimensions :attr:`state_dim`, :attr:`obs_dim`, :attr:`input_dim`); their array fields are the
    parameters θ (which of them are learned is chosen at fit time by a filter; a field declared
    with :func:`ceemx.param` carries a constraint). Every system has three keyword-only fields with
    defaults, so a subclass declares only its parameters and Equinox's generated ``__init__``
    takes them positionally or by name, and these by name::

        class Decay(ceemx.AbstractSystem):
            a: Array = ceemx.param(lower=0.0, upper=1.0)
            ...

        Decay(0.9)                                          # unit noise, no prior
        Decay(a=0.9, process_noise=0.1, obs_noise=ceemx.StudentT(0.2, 4.0, 1))

    Attributes:
        process_noise: density p_w of w_t = x_{t+1} − f_θ(x_t, u_t, t). ``None`` (default): unit
            ``DiagonalGaussian``; a scalar or length-n vector of standard deviations:
            ``DiagonalGaussian`` of those scales in the parameters' dtype; or a noise model.
        obs_noise: density p_v of v_t = y_t − g_θ(x_t, u_t, t); the same choices (length m).
        initial_prior: optional prior on x₁ (``None``, the default: flat).

    The defaults are resolved in the generated ``__init__`` (after the fields are set, before any
    user ``__post_init__``, which need not call ``super().__post_init__()``). A subclass with a
    hand-written ``__init__`` sets all three itself (as :class:`ceemx.systems.LinearSystem`
    does, with :func:`ceemx.models.noise.as_noise`); it may re-declare them as plain fields.

    On construction (``__check_init__``, host-side; traced values are skipped) a system checks,
    naming the field: that the noise fields are noise models whose dimensions match
    ``state_dim``/``obs_dim``; that the prior's mean is (n,) and its noise n-dimensional; that
    every floating-point parameter is finite and all share one dtype (weakly typed Python scalars
    excepted); and that every :func:`ceemx.param` value satisfies its constraint.
    """

    def __repr__(self) -> str:
        """Equinox's form, with the values of small arrays (``scale=0.05``, not ``f64[]``)."""
        return value_repr(self)

    process_noise: AbstractNoise = eqx.field(
        kw_only=True, default_factory=_unset, converter=_noise_argument
    )
    obs_noise: AbstractNoise = eqx.field(
        kw_only=True, default_factory=_unset, converter=_noise_argument
    )
    initial_prior: GaussianPrior | None = eqx.field(kw_only=True, default_factory=_unset)

    # Whether the class gets Equinox's generated __init__ (False below a hand-written one).
    _generated_init: ClassVar[bool] = True
    __post_init__: ClassVar[Any] = _DefaultsHook()

    def __init_subclass__(cls, **kwargs):
        """Keep the noise defaults resolved in the generated ``__init__`` of every subclass.

        The resolution needs ``state_dim``/``obs_dim``, so it runs in ``__post_init__``, which
        exists only on classes with Equinox's generated ``__init__`` (see :class:`_DefaultsHook`).
        A ``__post_init__`` a subclass defines is wrapped to resolve the defaults first.
        """
        super().__init_subclass__(**kwargs)
        if "__init__" in cls.__dict__:
            cls._generated_init = False
        own = cls.__dict__.get("__post_init__")
        if cls._generated_init and own is not None and not isinstance(own, _DefaultsHook):

            @functools.wraps(own)
            def __post_init__(self):
                self._resolve_defaults()
                own(self)

            cls.__post_init__ = __post_init__

    def _resolve_defaults(self) -> None:
        dtype = float_dtype([getattr(self, f.name) for f in _parameter_fields(self)])

        def resolve(value, dim):
            if isinstance(value, AbstractNoise):
                return value
            value = 1.0 if value is None else value
            return as_noise(jnp.asarray(value, dtype), dim)

        self.process_noise = resolve(self.process_noise, self.state_dim)
        self.obs_noise = resolve(self.obs_noise, self.obs_dim)

    def __check_init__(self):
        for name in ("process_noise", "obs_noise"):
            noise = getattr(self, name)
            if not isinstance(noise, AbstractNoise):
                raise TypeError(
                    f"`system.{name}` must be a noise model; got {type(noise).__name__}. A "
                    "hand-written `__init__` sets it itself, e.g. with "
                    "`ceemx.models.noise.as_noise(scale, dim)`."
                )
        prior = self.initial_prior
        if prior is not None and not isinstance(prior, GaussianPrior):
            raise TypeError(
                f"`system.initial_prior` must be a ceemx.GaussianPrior or None; got "
                f"{type(prior).__name__}."
            )
        n, m = self.state_dim, self.obs_dim
        self.process_noise.check_dimension("system.process_noise", n, "state_dim")
        self.obs_noise.check_dimension("system.obs_noise", m, "obs_dim")
        if prior is not None:
            if tuple(jnp.shape(prior.mean)) != (n,):
                raise ValueError(
                    f"`system.initial_prior.mean` must have shape (state_dim,) = ({n},); got "
                    f"{tuple(jnp.shape(prior.mean))}."
                )
            prior.noise.check_dimension("system.initial_prior.noise", n, "state_dim")
        _check_parameters(self)
        check_constraints(self)

    @property
    @abc.abstractmethod
    def state_dim(self) -> int:
        """n, the dimension of x."""

    @property
    @abc.abstractmethod
    def obs_dim(self) -> int:
        """m, the dimension of y."""

    @property
    def input_dim(self) -> int:
        """p, the dimension of u (0 when the system has no input)."""
        return 0

    @abc.abstractmethod
    def dynamics(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """f_θ(x, u, t): the next state's mean (t: the integer time step)."""

    @abc.abstractmethod
    def observe(
        self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " m"]:
        """g_θ(x, u, t): the observation's mean."""

    def linear_observation(
        self, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> tuple[Float[Array, "m n"], Float[Array, " m"]] | None:
        """(C, d) when the observation is linear in x, g_θ(x, u, t) = C x + d; else ``None``.

        The default, ``None``, claims nothing. A system whose observation is linear in the state
        (for any u, t) overrides this; particle filters then use the fully adapted proposal
        p(x_t | x_{t−1}, y_t) in closed form (:func:`ceemx.particle_filter`). The structure (None
        or a pair) must not depend on the values of u and t.
        """
        return None

    def check(self) -> None:
        """Host-side validation of the noise models (raises ``ValueError`` naming the field)."""
        self.process_noise.check("system.process_noise")
        self.obs_noise.check("system.obs_noise")
        if self.initial_prior is not None:
            self.initial_prior.noise.check("system.initial_prior.noise")


def _parameter_fields(system: AbstractSystem) -> list[dataclasses.Field]:
    """The dataclass fields of ``system`` that hold model parameters (not noise, prior, static)."""
    return [
        f
        for f in dataclasses.fields(system)
        if f.name not in _NOISE_FIELDS and not f.metadata.get("static", False)
    ]


def _check_parameters(system: AbstractSystem) -> None:
    """Every floating-point parameter finite, all of one dtype (weak Python scalars excepted)."""
    first: tuple[str, Any] | None = None
    for f in _parameter_fields(system):
        pairs, _ = jtu.tree_flatten_with_path(getattr(system, f.name))
        for path, leaf in pairs:
            if not eqx.is_inexact_array(leaf):
                continue
            name = f"system.{f.name}{jtu.keystr(path)}"
            if not getattr(leaf, "weak_type", False):
                if first is None:
                    first = (name, leaf.dtype)
                elif leaf.dtype != first[1]:
                    raise ValueError(
                        f"`{name}` has dtype {leaf.dtype} but `{first[0]}` has {first[1]}: give "
                        "every parameter of a system one floating-point dtype."
                    )
            if isinstance(leaf, Tracer):
                continue
            value = np.asarray(leaf)
            bad = ~np.isfinite(value)
            if np.any(bad):
                idx = tuple(int(i) for i in np.argwhere(bad)[0])
                where = f" at index {idx}" if idx else ""
                raise ValueError(f"`{name}` must be finite; got a non-finite value{where}.")


def float_dtype(tree) -> jnp.dtype:
    """The dtype of the first floating-point array of ``tree`` (a system's working precision).

    Noise models and initial-state priors are skipped (for a system: the dtype of its model
    parameters θ). Falls back to JAX's default float dtype when there is no such array.
    """
    skip = lambda x: isinstance(x, AbstractNoise | GaussianPrior)  # noqa: E731
    for leaf in jtu.tree_leaves(tree, is_leaf=skip):
        if not skip(leaf) and eqx.is_inexact_array(leaf):
            return leaf.dtype
    return jnp.zeros(()).dtype


def with_noise(
    system: _S,
    process_noise: AbstractNoise | ArrayLike | None = None,
    obs_noise: AbstractNoise | ArrayLike | None = None,
) -> _S:
    """The same system with other noise models (the weights of the residuals in J, Eq. 9).

    Args:
        system: any system.
        process_noise: the new p_w: a noise model, or a scale (scalar or length-n vector of
            standard deviations) for ``DiagonalGaussian(scale, n)``; ``None`` keeps the current one.
        obs_noise: the new p_v, likewise (length-m scales).

    Returns:
        A copy of ``system``; scales are cast to the system's floating-point dtype
        (:func:`float_dtype`), noise models are used as given.
    """
    dtype = float_dtype(system)

    def make(value, current, dim):
        if value is None:
            return current
        if not isinstance(value, AbstractNoise):
            value = jnp.asarray(value, dtype)
        return as_noise(value, dim)

    pn = make(process_noise, system.process_noise, system.state_dim)
    on = make(obs_noise, system.obs_noise, system.obs_dim)
    return eqx.tree_at(lambda s: (s.process_noise, s.obs_noise), system, (pn, on))


def _as_period(value: float | int) -> float:
    """``dt``'s converter: a Python float (a static field must not hold an array)."""
    return float(value)


INTEGRATORS = ("rk4", "midpoint", "euler")


def rk4_step(vector_field, x, u, t, dt):
    """One classic fourth-order Runge–Kutta step of ẋ = F(x, u, t), u constant over the step."""
    k1 = vector_field(x, u, t)
    k2 = vector_field(x + 0.5 * dt * k1, u, t + 0.5 * dt)
    k3 = vector_field(x + 0.5 * dt * k2, u, t + 0.5 * dt)
    k4 = vector_field(x + dt * k3, u, t + dt)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


class AbstractContinuousSystem(AbstractSystem):
    """A continuous-time vector field ẋ = F_θ(x, u, t) discretised by classic RK4 with fixed ``dt``.

    f_θ(x_t, u_t, t) integrates ẋ = F_θ(x, u(τ), τ) over τ ∈ [t·dt, (t+1)·dt] from x_t with
    ``substeps`` classic RK4 steps of length dt/``substeps``. The input between samples follows
    ``hold``:

    - ``"zoh"`` (default), zero-order hold: u(τ) = u_t over the whole step. The system's input is
      u_t: ``input_dim`` = ``control_dim`` = p.
    - ``"foh"``, first-order hold: u(τ) = u_t + (τ/dt − t)(u_{t+1} − u_t), linear between the
      samples. ``dynamics(x, u, t)`` sees one step's input only, so a first-order-hold system
      takes the pair [u_t, u_{t+1}] stacked as its input: ``input_dim`` = 2p, and the data's
      inputs are built with :func:`ceemx.data.trajectories.foh_inputs`. :meth:`vector_field`
      receives the interpolated p-vector; :meth:`observe` receives the stacked pair, and
      :meth:`current_input` returns its u_t part.

    A subclass with inputs declares p by overriding :attr:`control_dim` (``input_dim`` follows
    from it and ``hold``), implements :meth:`vector_field`, :meth:`observe`, ``state_dim`` and
    ``obs_dim``, and sets ``dt``. (Overriding ``input_dim`` directly still works under
    zero-order hold.)

    Attributes:
        dt: the sampling period (keyword-only; a static Python float).
        hold: ``"zoh"`` or ``"foh"`` (keyword-only, static; default ``"zoh"``).
        substeps: integration steps per sample (keyword-only, static; default 1).
        integrator: ``"rk4"`` (classic fourth-order Runge–Kutta, default), ``"midpoint"``
            (explicit midpoint, second order — the authors' single-Lorenz scripts) or
            ``"euler"`` (keyword-only, static).
    """

    dt: float = eqx.field(static=True, kw_only=True, converter=_as_period)
    hold: Literal["zoh", "foh"] = eqx.field(static=True, kw_only=True, default="zoh")
    substeps: int = eqx.field(static=True, kw_only=True, default=1)
    integrator: Literal["rk4", "midpoint", "euler"] = eqx.field(
        static=True, kw_only=True, default="rk4"
    )

    def __check_init__(self):
        dt = self.dt
        if isinstance(dt, bool) or not isinstance(dt, int | float) or not (0 < dt < math.inf):
            raise ValueError(f"`system.dt` must be a positive finite number; got {dt!r}.")
        if self.hold not in ("zoh", "foh"):
            raise ValueError(f"`system.hold` must be 'zoh' or 'foh'; got {self.hold!r}.")
        if self.integrator not in INTEGRATORS:
            raise ValueError(
                f"`system.integrator` must be one of {INTEGRATORS}; got {self.integrator!r}."
            )
        k = self.substeps
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
            raise ValueError(f"`system.substeps` must be an integer >= 1; got {k!r}.")
        p, width = self.control_dim, self.input_dim
        if self.hold == "foh" and width != 2 * p:
            raise ValueError(
                f"with hold='foh' the input is the stacked pair [u_t, u_{{t+1}}]: declare the "
                f"number of inputs p with `control_dim` (input_dim is then 2p); got control_dim = "
                f"{p}, input_dim = {width}. See ceemx.data.trajectories.foh_inputs."
            )
        if self.hold == "zoh" and p and width != p:
            raise ValueError(
                f"`input_dim` ({width}) must equal `control_dim` ({p}) under zero-order hold."
            )

    @abc.abstractmethod
    def vector_field(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """F_θ(x, u, t), the continuous-time derivative of the state (t: continuous time).

        ``u`` is the input at time t, of length ``control_dim``: u_t under zero-order hold, the
        linear interpolation between u_t and u_{t+1} under first-order hold.
        """

    def default_state_mean(self) -> State | None:
        """A typical state (n,), or ``None`` (the default) when the system has none.

        :func:`ceemx.evaluation.metrics.dynamics_error` compares vector fields at states sampled
        around it unless given a ``mean``.
        """
        return None

    @property
    def control_dim(self) -> int:
        """p, the number of inputs the vector field takes (0: none; override to declare them)."""
        return 0

    @property
    def input_dim(self) -> int:
        """The width of the input the library passes: p, or 2p under first-order hold."""
        return 2 * self.control_dim if self.hold == "foh" else self.control_dim

    def current_input(self, u: Float[Array, " p"]) -> Float[Array, " q"]:
        """u_t from the input the library passes: ``u`` itself (zoh), its first p entries (foh)."""
        if self.hold == "foh":
            return u[: self.control_dim]
        return u

    def dynamics(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """Integrate from time t·dt over one sample: ``substeps`` steps of ``integrator``."""
        t0 = jnp.asarray(t, x.dtype) * self.dt
        if self.hold == "zoh" and self.substeps == 1 and self.integrator == "rk4":
            return rk4_step(self.vector_field, x, u, t0, self.dt)
        if self.hold == "foh":
            u0 = self.current_input(u)
            du = u[self.control_dim :] - u0
        else:
            u0, du = u, jnp.zeros_like(u)
        n, dt = self.substeps, self.dt
        h = dt / n

        def field(xx, frac):  # frac ∈ [0, 1]: the position inside the sampling interval
            return self.vector_field(xx, u0 + frac * du, t0 + frac * dt)

        def step(k, xx):
            f0 = jnp.asarray(k, x.dtype) / n
            k1 = field(xx, f0)
            if self.integrator == "euler":
                return xx + h * k1
            k2 = field(xx + 0.5 * h * k1, f0 + 0.5 / n)
            if self.integrator == "midpoint":
                return xx + h * k2
            k3 = field(xx + 0.5 * h * k2, f0 + 0.5 / n)
            k4 = field(xx + h * k3, f0 + 1.0 / n)
            return xx + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

        if n == 1:
            return step(0, x)
        return jax.lax.fori_loop(0, n, step, x)
