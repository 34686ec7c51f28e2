"""The input boundary: every public entry point promotes and validates its inputs here, once.

An entry point (:func:`ceemx.fit`, :func:`ceemx.smooth`, :func:`ceemx.learn`, the filters, the
scores, ...) calls :func:`prepare` once with what the user passed and works on the returned
:class:`Prepared` values from then on: the system, data and states in ONE dtype — the system's
(:func:`working_dtype`) — checked for shapes, finiteness, noise parameters and the model's own
methods before any compute. What an entry point calls inside receives prepared values and does
not check them again.

- :func:`prepare` — promotion and the one validation pass, returning a :class:`Prepared`.
- :func:`promote_inputs`, :func:`promote_array`, :func:`promote_tree` — the casts alone.
- :func:`check_inputs` — the validation alone (inputs already in the working dtype);
  :func:`check_states` — the part of it that reads the states.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import numpy as np
from jax.core import Tracer

from ceemx.data.arrays import cast_checked
from ceemx.data.trajectories import Trajectories
from ceemx.infra.warn import warn
from ceemx.lib.tree import as_jax, is_weak
from ceemx.lib.typing import no_type_check
from ceemx.models.method_check import check_methods
from ceemx.models.system import AbstractSystem, float_dtype

__all__ = [
    "Prepared",
    "check_inputs",
    "check_states",
    "prepare",
    "promote_array",
    "promote_inputs",
    "promote_tree",
    "working_dtype",
]


@dataclasses.dataclass(frozen=True)
class Prepared:
    """An entry point's inputs after :func:`prepare`: in the working dtype and validated.

    Attributes:
        system: the model, its floating arrays (noise models and prior included) in the dtype of
            its parameters θ.
        data: the observations in that dtype.
        states: the (B, T, n) states passed with them in that dtype, or ``None``.
    """

    system: AbstractSystem
    data: Trajectories
    states: Any = None

    @property
    def dtype(self) -> np.dtype:
        """The working dtype (the system's parameters')."""
        return np.dtype(self.data.y.dtype)


@no_type_check  # validates its arguments
def prepare(
    system: AbstractSystem,
    data: Trajectories,
    states=None,
    *,
    name: str = "x_init",
    identify: bool | None = None,
    unobserved_warning: bool = True,
) -> Prepared:
    """:func:`promote_inputs`, then the one validation pass (:func:`check_inputs`).

    Args:
        system: the model.
        data: the observations.
        states: (B, T, n) states, or ``None``.
        name: the name of ``states`` in messages.
        identify: the caller estimates states and θ: warn for a float32 working dtype (default:
            when ``states`` are given).
        unobserved_warning: warn when a linear observation matrix is rank-deficient or
            ill-conditioned.

    Returns:
        The :class:`Prepared` inputs.

    Raises:
        TypeError, ValueError: as :func:`promote_inputs` and :func:`check_inputs`.
    """
    system, data, states = promote_inputs(system, data, states, name=name)
    _validate(
        system,
        data,
        states,
        name=name,
        identify=states is not None if identify is None else identify,
        unobserved_warning=unobserved_warning,
    )
    return Prepared(system, data, states)


def _working_dtype(system: AbstractSystem) -> np.dtype:
    """The system's floating dtype (:func:`float_dtype`), refusing float16 and non-floats."""
    dtype = np.dtype(float_dtype(system))
    if dtype not in (np.float32, np.float64):
        raise ValueError(
            f"the system's parameters have dtype {dtype}; ceemx works in float32 or float64 "
            "(float16 is too coarse for its second-order solves): cast the parameters."
        )
    return dtype


def working_dtype(system: AbstractSystem) -> np.dtype:
    """The dtype every entry point computes in: the system's parameters' (float32 or float64).

    Raises:
        ValueError: for a float16 (or non-floating) system.
    """
    return _working_dtype(system)


def promote_array(name: str, x, system: AbstractSystem) -> Any:
    """``x`` (states, inputs, …) cast to the system's working dtype, as :func:`promote_inputs`.

    ``None`` stays ``None``; a finite value that overflows the cast is refused, naming ``name``.

    Raises:
        TypeError: a complex or non-numeric ``x``.
        ValueError: a ragged ``x``, or a value that overflows the cast.
    """
    return _promote_array(name, x, _working_dtype(system))


def promote_tree(tree, system: AbstractSystem):
    """Every floating array of ``tree`` (e.g. a prior) in the system's working dtype.

    As :func:`promote_inputs` casts the system's own noise models and prior.
    """
    return _cast_floating(tree, _working_dtype(system))


def _promote_array(name: str, x, dtype):
    if x is None:
        return None
    if isinstance(x, Tracer):
        return x.astype(dtype) if x.dtype != dtype else x
    if isinstance(x, jax.Array) and x.dtype == dtype:
        return x
    try:
        a = np.asarray(x)
    except ValueError:  # a ragged nested sequence
        raise ValueError(f"`{name}` must be a rectangular (B, T, n) array.") from None
    if np.issubdtype(a.dtype, np.complexfloating):
        raise TypeError(f"`{name}` must be real; got complex dtype {a.dtype}.")
    if not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
        raise TypeError(f"`{name}` must be a numeric array; got dtype {a.dtype}.")
    return as_jax(np.asarray(cast_checked(name, a, dtype), dtype))


def _cast_floating(tree, dtype):
    def cast(leaf):
        # Weakly typed leaves (a scale given as a Python float) are made strong too (is_weak).
        if eqx.is_inexact_array(leaf) and (leaf.dtype != dtype or is_weak(leaf)):
            return jax.lax.convert_element_type(leaf, dtype)
        return leaf

    return jax.tree_util.tree_map(cast, tree)


@no_type_check  # validates its arguments
def promote_inputs(
    system: AbstractSystem, data: Trajectories, x_init=None, *, name: str = "x_init"
) -> tuple[AbstractSystem, Trajectories, Any]:
    """Cast the data, ``x_init`` and all the system's floating arrays to ONE dtype: the system's.

    The working dtype is that of the system's parameters θ
    (:func:`ceemx.models.system.float_dtype`); its noise models and prior, ``data.y``,
    ``data.u`` and ``x_init`` are cast to it, so mixed precision never reaches a compiled loop.
    Arrays already in that dtype are returned as they are. Float16 data or states are
    promoted; a float16 system is refused.

    Args:
        system: the model.
        data: the observations.
        x_init: (B, T, n) states, or ``None``.
        name: the name of ``x_init`` in messages.

    Returns:
        ``(system, data, x_init)`` in the working dtype (``x_init`` stays ``None`` if it was).

    Raises:
        TypeError: ``data`` is not :class:`Trajectories`; ``x_init`` is complex or non-numeric.
        ValueError: the system is not float32/float64; a finite value overflows the cast (e.g.
            1e300 into float32), naming the argument and the index.
    """
    if not isinstance(data, Trajectories):
        raise TypeError(f"`data` must be a ceemx.Trajectories; got {type(data).__name__}.")
    dtype = _working_dtype(system)
    system = _cast_floating(system, dtype)
    if data.y.dtype != dtype or data.u.dtype != dtype:
        y, u, mask = data.y, data.u, data.mask
        if all(not isinstance(a, Tracer) for a in (y, u, mask)):
            y = as_jax(
                np.asarray(cast_checked("data.y", np.asarray(y), dtype, np.asarray(mask)), dtype)
            )
            u = as_jax(np.asarray(cast_checked("data.u", np.asarray(u), dtype), dtype))
        data = eqx.tree_at(lambda d: (d.y, d.u), data, (y.astype(dtype), u.astype(dtype)))
    return system, data, _promote_array(name, x_init, dtype)


def _check_observation_matrix(system: AbstractSystem) -> None:
    """Warn when a linear observation map C is rank-deficient or ill-conditioned (cheap, host)."""
    try:
        u = as_jax(np.zeros((system.input_dim,), float_dtype(system)))
        lin = system.linear_observation(u, 0)
        if lin is None or isinstance(lin[0], Tracer):
            return
        C = np.asarray(lin[0], dtype=np.float64)
    except Exception:  # a diagnostic only: a system whose map needs real inputs is not checked
        return
    if C.ndim != 2 or C.size == 0 or C.shape[0] * C.shape[1] > 250_000:
        return
    sv = np.linalg.svd(C, compute_uv=False)
    rank = int(np.sum(sv > sv[0] * max(C.shape) * np.finfo(np.float64).eps)) if sv[0] > 0 else 0
    cond = sv[0] / sv[-1] if sv[-1] > 0 else np.inf
    if rank < min(C.shape) or cond > 1e12:
        warn(
            f"the system's observation matrix C {C.shape} has rank {rank} and condition number "
            f"{cond:.3g}: some state directions are (nearly) unobserved, so the states and θ may "
            "be poorly identifiable."
        )


def _check_system_data(system: AbstractSystem, data: Trajectories) -> np.dtype:
    """The system and data parts of the validation; returns the working dtype."""
    if not isinstance(data, Trajectories):
        raise TypeError(f"`data` must be a ceemx.Trajectories; got {type(data).__name__}.")
    system.check()
    dtype = _working_dtype(system)
    if data.y.dtype != dtype:
        raise ValueError(
            f"`data.y` has dtype {data.y.dtype} but the system's parameters have dtype {dtype}: "
            "give both one dtype (ceemx.data.checks.promote_inputs casts to the system's)."
        )
    if data.obs_dim != system.obs_dim:
        raise ValueError(
            f"`data.y` has m = {data.obs_dim} but the system observes m = {system.obs_dim}."
        )
    if data.input_dim != system.input_dim:
        raise ValueError(
            f"`data.u` has p = {data.input_dim} but the system takes p = {system.input_dim} inputs."
        )
    check_methods(system)  # the model's own methods: shapes and dtypes, traced once
    return dtype


def _warn_precision(dtype) -> None:
    if dtype == np.float32 or dtype == np.float16:
        warn(
            f"identifying in {np.dtype(dtype)}: CE-EM's second-order solves lose accuracy in "
            "single precision; enable float64 with jax.config.update('jax_enable_x64', True)."
        )


@no_type_check  # the validator itself
def check_states(system: AbstractSystem, data: Trajectories, x, *, name: str = "x_init") -> None:
    """``x`` must be finite real (B, T, n) states in ``data.y``'s dtype; warns in float32.

    The states part of :func:`check_inputs`, for states checked against other data than the ones
    the system and data were validated with (e.g. a window of them).
    """
    dtype = _working_dtype(system)
    if not hasattr(x, "shape"):
        x = np.asarray(_promote_array(name, x, dtype))
    shape = (data.batch_size, data.num_steps, system.state_dim)
    if tuple(x.shape) != shape:
        raise ValueError(f"`{name}` must have shape (B, T, n) = {shape}; got {tuple(x.shape)}.")
    xa = np.asarray(x)
    if not (np.issubdtype(xa.dtype, np.floating) or np.issubdtype(xa.dtype, np.integer)):
        raise TypeError(f"`{name}` must be a real array; got dtype {xa.dtype}.")
    if not np.all(np.isfinite(xa)):
        b, t, j = (int(i) for i in np.argwhere(~np.isfinite(xa))[0])
        raise ValueError(f"`{name}` has a non-finite value at index [{b}, {t}, {j}].")
    if xa.dtype != np.asarray(data.y).dtype:
        raise ValueError(f"`{name}` has dtype {xa.dtype} but `data.y` has dtype {data.y.dtype}.")
    _warn_precision(xa.dtype)


def _validate(
    system: AbstractSystem,
    data: Trajectories,
    x,
    *,
    name: str,
    identify: bool,
    unobserved_warning: bool,
) -> None:
    """The one validation pass of :func:`prepare` (see :func:`check_inputs`)."""
    dtype = _check_system_data(system, data)
    if unobserved_warning:
        _check_observation_matrix(system)
    if x is not None:
        check_states(system, data, x, name=name)
    elif identify:
        _warn_precision(dtype)


@no_type_check  # the validator itself
def check_inputs(
    system: AbstractSystem, data: Trajectories, x=None, *, name: str = "x_init"
) -> None:
    """Validate shapes, finiteness, noise parameters and dtype before any compute (host-side).

    The system's ``dynamics``, ``vector_field`` and ``observe`` are traced once (abstractly) to
    check the shape and dtype they return (:func:`ceemx.models.method_check.check_methods`).

    ``data.y`` and ``x`` must already have the system's dtype (see :func:`promote_inputs`); a
    float32 identification warns. Without ``x`` it also warns when a linear observation matrix is
    rank-deficient or has a condition number above 1e12.
    """
    _validate(system, data, x, name=name, identify=x is not None, unobserved_warning=x is None)
