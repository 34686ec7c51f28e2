"""A system's own methods checked once, before any compute: the shape and dtype they return.

A user model whose ``dynamics``, ``vector_field`` or ``observe`` returns the wrong shape or dtype
used to fail deep inside a compiled program ("Cannot stack arrays with different numbers of
dimensions", "add got incompatible shapes (2,), (3,)"). :func:`check_methods` evaluates each
method abstractly (``jax.eval_shape``: a trace, no compilation and no arithmetic) on a state of
shape (n,), an input (p,) and a time step, and names the method, the shape and dtype expected and
those returned. Every entry point runs it — through ``ceemx.data.checks.check_inputs``, or
directly where there are no data (:func:`ceemx.simulate`, :func:`ceemx.free_run`); the answer
depends only on the system's structure and its leaves' shapes and dtypes, so it is remembered for
those and each model is traced once.

:func:`nonfinite_run` reads a noise-free or simulated run after the fact: where it first stops
being finite, and which method made it so.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.core import Tracer

from ceemx.models.system import AbstractContinuousSystem, AbstractSystem, float_dtype

__all__ = ["check_methods", "nonfinite_run"]

_CHECKED: dict[Any, bool] = {}
_MAX_REMEMBERED = 256


def _key(system: AbstractSystem) -> Any:
    leaves, treedef = jtu.tree_flatten(system)
    if any(isinstance(a, Tracer) for a in leaves):
        return False  # traced: checked on the host already
    key = (treedef, tuple((np.shape(a), str(getattr(a, "dtype", type(a)))) for a in leaves))
    try:
        hash(key)
    except TypeError:  # an unhashable static field: check every time
        return None
    return key


def check_methods(system: AbstractSystem) -> None:
    """Raise when ``dynamics``, ``vector_field`` (continuous systems) or ``observe`` misbehave.

    Each must accept x (n,), u (p,) and t (a scalar; an integer step, continuous time for
    ``vector_field``, whose u is the input at that time) and return one array: (n,) for the
    state maps, (m,) for ``observe``, in the dtype of the system's parameters.

    Raises:
        ValueError: naming the method (e.g. ``system.dynamics``), the shape and dtype expected and
            returned — or the error the method raised when traced with those arguments.
    """
    key = _key(system)
    if key is False or (key is not None and key in _CHECKED):
        return
    dtype = jnp.dtype(float_dtype(system))
    n, m, p = system.state_dim, system.obs_dim, system.input_dim
    x = jax.ShapeDtypeStruct((n,), dtype)
    u = jax.ShapeDtypeStruct((p,), dtype)
    step = jax.ShapeDtypeStruct((), jnp.arange(1).dtype)
    if isinstance(system, AbstractContinuousSystem):
        # What ``dynamics`` passes on: u itself under zero-order hold, u_t's p entries under foh.
        width = system.control_dim if system.hold == "foh" else p
        q = jax.ShapeDtypeStruct((width,), dtype)
        _check_one(system, "vector_field", (x, q, jax.ShapeDtypeStruct((), dtype)), (n,), dtype)
    _check_one(system, "dynamics", (x, u, step), (n,), dtype)
    _check_one(system, "observe", (x, u, step), (m,), dtype)
    if key is not None:
        if len(_CHECKED) >= _MAX_REMEMBERED:
            _CHECKED.clear()
        _CHECKED[key] = True


def _describe(args: tuple) -> str:
    return ", ".join(
        f"{name}: {tuple(a.shape)} {a.dtype}" for name, a in zip(("x", "u", "t"), args, strict=True)
    )


def _check_one(system: AbstractSystem, name: str, args: tuple, shape: tuple, dtype) -> None:
    where = f"system.{name}"
    try:
        out = eqx.filter_eval_shape(lambda s, *a: getattr(s, name)(*a), system, *args)
    except Exception as err:  # noqa: BLE001 — the user's method: say which and with what
        raise ValueError(
            f"`{where}` failed when called with {_describe(args)} (n = {system.state_dim}, "
            f"m = {system.obs_dim}, p = {system.input_dim}): {type(err).__name__}: {err}"
        ) from err
    if not isinstance(out, jax.ShapeDtypeStruct):
        kind = type(out).__name__
        raise ValueError(
            f"`{where}` must return one array of shape {shape}; it returned a {kind} "
            f"({jtu.tree_map(lambda a: getattr(a, 'shape', a), out)})."
        )
    if tuple(out.shape) != shape:
        raise ValueError(
            f"`{where}` must return shape {shape} (n = {system.state_dim}, m = "
            f"{system.obs_dim}); it returned shape {tuple(out.shape)} when called with "
            f"{_describe(args)}."
        )
    if out.dtype != dtype:
        raise ValueError(
            f"`{where}` must return the dtype of the system's parameters, {dtype}; it returned "
            f"{out.dtype} (a constant or array of another precision inside the method?)."
        )


def nonfinite_run(states, outputs) -> str | None:
    """Where a run of a model first stops being finite, and which method did it (else ``None``).

    Args:
        states: (B, T, n) the run's states, ``states[:, 0]`` the given (finite) initial states.
        outputs: (B, T, m) its outputs (``observe`` at each state).

    Returns:
        ``None`` when everything is finite; otherwise one sentence naming the trajectory, the
        step, the method (``system.dynamics`` for the first non-finite state, ``system.observe``
        for a non-finite output at a finite state) and the value.
    """
    xs, ys = np.asarray(states), np.asarray(outputs)
    T = xs.shape[1]
    bad_x = np.asarray(~np.isfinite(xs).all(axis=-1))  # (B, T)
    bad_y = np.asarray(~np.isfinite(ys).all(axis=-1))
    if not (bad_x.any() or bad_y.any()):
        return None
    first_x = np.where(bad_x.any(axis=1), bad_x.argmax(axis=1), T)
    first_y = np.where(bad_y.any(axis=1), bad_y.argmax(axis=1), T)
    b = int(np.argmin(np.minimum(first_x, first_y)))
    if first_x[b] <= first_y[b]:
        t = int(first_x[b])
        value = xs[b, t][~np.isfinite(xs[b, t])][0]
        return (
            f"`system.dynamics` returned a non-finite state ({value} at step {t}) from the finite "
            f"state at step {t - 1} of trajectory {b}: the model returns NaN or inf there, or "
            "the run diverges until it overflows."
        )
    t = int(first_y[b])
    value = ys[b, t][~np.isfinite(ys[b, t])][0]
    return (
        f"`system.observe` returned a non-finite output ({value}) at the finite state of step "
        f"{t} of trajectory {b}: the model returns NaN or inf there (e.g. a log or a square root "
        "outside its domain)."
    )
