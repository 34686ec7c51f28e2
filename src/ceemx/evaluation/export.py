"""An identified model for deployment: a pure step function and an exported simulation program.

- :func:`export_step` — ``step(x, u, t) -> (x_next, y)``, the model's one step as a pure JAX
  function (no host-side checks, unlike :func:`ceemx.free_run`): usable inside ``jax.jit``,
  ``vmap``, ``lax.scan``, a controller's or an estimator's own loop.
- :func:`export_simulate` — the model's free run ``(x1, u) -> (states, outputs)`` as a
  ``jax.export.Exported``: a serialised StableHLO program that runs with JAX alone (no ceemx, no
  model class), for any batch size and length (symbolic B and T), on the platforms it was
  exported for.

Both compute exactly what :func:`ceemx.free_run` does: y_t = g(x_t, u_t, t) and
x_{t+1} = f(x_t, u_t, t) with the integer time index t from 0, in the dtype of the model's
parameters.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ceemx.evaluation.simulation import check_system, free_run_one, strongly_typed
from ceemx.infra.checkpoint import atomic_write
from ceemx.models.system import AbstractSystem, float_dtype

__all__ = ["export_simulate", "export_step"]


def _step(system: AbstractSystem, x, u, t):
    dtype = float_dtype(system)
    x, u = jnp.asarray(x, dtype), jnp.asarray(u, dtype)
    return system.dynamics(x, u, t).astype(dtype), system.observe(x, u, t).astype(dtype)


def export_step(system: AbstractSystem) -> jax.tree_util.Partial:
    """The model's one step, ``step(x, u, t) -> (x_next, y)``, as a pure JAX function.

    ``x_next = f(x, u, t)`` and ``y = g(x, u, t)``: the output at the current state, as
    :func:`ceemx.free_run` computes it (its outputs are ``y`` of each step, its states ``x``).

    Args:
        system: the identified model (:class:`ceemx.AbstractSystem`).

    Returns:
        A ``jax.tree_util.Partial`` over the model: callable, jittable and vmappable, and a pytree
        (the model's parameters are its leaves, so passing ``step`` into a jitted function
        traces them rather than baking them in). ``x`` is (n,), ``u`` (p,) (an empty array for
        p = 0), ``t`` the integer step index; both outputs are in the model's dtype.

    Raises:
        TypeError: ``system`` is not a :class:`ceemx.AbstractSystem`.

    Example:
        >>> sys = ceemx.systems.LinearSystem(jnp.array([[0.5]]), jnp.array([[2.0]]))
        >>> step = ceemx.export_step(sys)
        >>> x_next, y = jax.jit(step)(jnp.array([1.0]), jnp.zeros(0), 0)
        >>> float(x_next[0]), float(y[0])
        (0.5, 2.0)
    """
    check_system(system)
    return jax.tree_util.Partial(_step, strongly_typed(system))


def _simulate(system: AbstractSystem, x1, u):
    return jax.vmap(lambda x, ub: free_run_one(system, x, ub, 0))(x1, u)


def export_simulate(
    system: AbstractSystem,
    path: str | os.PathLike | None = None,
    *,
    batch_size: int | None = None,
    num_steps: int | None = None,
    platforms: Sequence[str] | None = None,
) -> jax.export.Exported:
    """The model's free run as a ``jax.export`` program: ``(x1, u) -> (states, outputs)``.

    The program takes x1 (B, n) and u (B, T, p) in the model's dtype and returns the (B, T, n)
    states and (B, T, m) outputs of :func:`ceemx.free_run` (the model's parameters are
    constants in it). Run it where ceemx is not installed::

        exported = jax.export.deserialize(open("model.jaxexport", "rb").read())
        states, outputs = exported.call(x1, u)

    Args:
        system: the identified model.
        path: where to write the serialised program (``exported.serialize()``), atomically;
            ``None``: not written.
        batch_size: a fixed B; ``None``: symbolic (any B).
        num_steps: a fixed T; ``None``: symbolic (any T ≥ 1).
        platforms: the platforms to export for (e.g. ``("cpu", "cuda")``); ``None``: the default
            backend's.

    Returns:
        The ``jax.export.Exported`` (``.call(x1, u)`` runs it; ``.serialize()`` gives the bytes).

    Raises:
        TypeError: ``system`` is not a :class:`ceemx.AbstractSystem`.
        ValueError: ``batch_size`` or ``num_steps`` below 1.

    Example:
        >>> sys = ceemx.systems.LinearSystem(jnp.array([[0.5]]), jnp.array([[2.0]]))
        >>> exported = ceemx.export_simulate(sys)
        >>> states, outputs = exported.call(jnp.ones((1, 1)), jnp.zeros((1, 3, 0)))
        >>> outputs[0, :, 0].tolist()
        [2.0, 1.0, 0.5]
    """
    check_system(system)
    for name, value in (("batch_size", batch_size), ("num_steps", num_steps)):
        if value is not None and (not isinstance(value, (int, np.integer)) or value < 1):
            raise ValueError(f"`{name}` must be a positive integer or None; got {value!r}.")
    system = strongly_typed(system)
    dtype = float_dtype(system)
    B, T = jax.export.symbolic_shape(
        f"{batch_size or 'b'}, {num_steps or 't'}", constraints=("t >= 1",) if not num_steps else ()
    )
    n, p = system.state_dim, system.input_dim
    args = (jax.ShapeDtypeStruct((B, n), dtype), jax.ShapeDtypeStruct((B, T, p), dtype))
    fn = jax.jit(lambda x1, u: _simulate(system, x1, u))
    exported = jax.export.export(fn, platforms=platforms)(*args)
    if path is not None:
        blob = exported.serialize()
        atomic_write(os.fspath(path), lambda f: f.write(blob))
    return exported
