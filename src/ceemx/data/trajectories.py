"""Batches of observed trajectories, validated on construction, and simulation of systems."""

from __future__ import annotations

from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from ceemx.infra.options import check_int
from ceemx.infra.policy import Runs, program
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import (
    Inputs,
    ObservationMask,
    Observations,
    State,
    States,
    Trajectory,
    no_type_check,
)
from ceemx.models.method_check import check_methods, nonfinite_run
from ceemx.models.noise import AbstractNoise
from ceemx.models.system import AbstractSystem, float_dtype

__all__ = ["Trajectories", "foh_inputs", "rollout_one", "simulate"]


def _is_concrete(a) -> bool:
    return not isinstance(a, Tracer)


def _on_host(tree) -> bool:
    """Whether every array leaf of ``tree`` may be indexed by NumPy instead of JAX.

    Eager JAX indexing compiles a small program per new shape (≈ 20 ms each); a NumPy view of a
    concrete array held on one CPU device gives the same values at no compile. Traced, sharded,
    accelerator-held (a round trip through the host) and weakly typed leaves (whose type a round
    trip through NumPy would not keep) stay with JAX.
    """
    for a in jax.tree_util.tree_leaves(tree):
        if isinstance(a, np.ndarray):
            continue
        if (
            not isinstance(a, jax.Array)
            or isinstance(a, Tracer)
            or a.weak_type
            or len(a.sharding.device_set) != 1
            or next(iter(a.sharding.device_set)).platform != "cpu"
        ):
            return False
    return True


def _host_index(idx):
    """``idx`` for NumPy, or ``None`` where JAX indexes (traced, a list or tuple).

    An int, slice or NumPy array is kept, a concrete JAX array becomes a NumPy one; lists and
    tuples stay with JAX, which reads them its own way (a list is refused).
    """
    if isinstance(idx, Tracer):
        return None
    if isinstance(idx, jax.Array):
        return np.asarray(idx)
    if isinstance(idx, (slice, np.ndarray, int, np.integer)):
        return idx
    return None


def _back_like(out: np.ndarray, like) -> jax.Array | np.ndarray:
    """NumPy's result ``out`` as a JAX array placed as ``like`` is (a transfer, no program)."""
    if isinstance(like, np.ndarray):
        return out
    if isinstance(like, jax.Array) and like.committed:
        return jax.device_put(out, like.sharding)
    return as_jax(out)


def _first_bad(bad: np.ndarray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(bad)[0])


def _as_array(name: str, value) -> np.ndarray:
    """``np.asarray(value)``, with a ragged nesting reported as a ``ValueError`` naming ``name``."""
    try:
        return np.asarray(value)
    except ValueError as err:  # NumPy refuses ragged nested sequences
        raise ValueError(
            f"`{name}` must be a rectangular array; got a ragged sequence ({err})."
        ) from None


def _as_numeric(name: str, value) -> np.ndarray:
    """``value`` as a real numeric NumPy array (bool, integer or floating), else ``TypeError``."""
    a = _as_array(name, value)
    if np.issubdtype(a.dtype, np.complexfloating):
        raise TypeError(f"`{name}` must be real; got complex dtype {a.dtype}.")
    if not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
        raise TypeError(f"`{name}` must be a numeric array; got dtype {a.dtype}.")
    return a


def cast_checked(name: str, a: np.ndarray, dtype, where: np.ndarray | None = None) -> np.ndarray:
    """``a`` cast to ``dtype``, raising ``ValueError`` where a finite value overflows the cast.

    Args:
        name: the argument, for the message.
        a: a real NumPy array.
        dtype: the target floating-point dtype.
        where: optional booleans broadcastable to ``a``; only these entries are checked.
    """
    dtype = np.dtype(dtype)
    if a.dtype == dtype:
        return a
    with np.errstate(over="ignore", invalid="ignore"):
        out = a.astype(dtype)
    overflow = np.isfinite(a) & ~np.isfinite(out)
    if where is not None:
        overflow = overflow & where
    if overflow.any():
        idx = tuple(int(i) for i in np.argwhere(overflow)[0])
        raise ValueError(
            f"`{name}` has the value {a[idx]} at index {list(idx)}, which overflows {dtype} "
            f"(largest finite value {np.finfo(dtype).max})."
        )
    return out


class Trajectories(eqx.Module):
    """A batch of B trajectories of T steps: observations y, inputs u and an observation mask.

    Args:
        y: (B, T, m) observations. Entries where ``mask`` is False are ignored and may be NaN.
        u: (B, T, p) inputs held constant over each step, or ``None`` (no input; p = 0).
        mask: ``None`` (everything observed), (B, T) booleans (whole steps observed or not) or
            (B, T, m) booleans (per dimension). Trajectories of different lengths are padded to a
            common T and their padding masked: states past the last observation then follow the
            dynamics and add nothing to the objective at its optimum.

    Raises:
        ValueError: naming the argument and the first offending index, for wrong ranks,
            mismatched B or T, NaN/inf in unmasked ``y`` or anywhere in ``u`` (checked after the
            cast to the stored dtype: a finite value that overflows it is refused), an empty
            batch, T < 2, no observed component (m = 0), a ragged nested sequence, a
            non-floating ``y``, or a mask of the wrong shape or dtype.
        TypeError: for a complex or non-numeric (e.g. string) ``y`` or ``u``.

    ``y`` and ``u`` are stored in ``y``'s floating dtype as JAX stores it (float64 becomes
    float32 without ``jax_enable_x64``); integer or boolean ``u`` is converted.

    The stored ``y`` has masked entries replaced by zeros and ``mask`` is always (B, T, m) bool.
    """

    y: Observations
    u: Inputs
    mask: ObservationMask

    def __init__(self, y, u=None, mask=None):
        concrete = _is_concrete(y) and _is_concrete(u) and _is_concrete(mask)
        if concrete:
            y_np = _as_numeric("y", y)
            if y_np.ndim != 3:
                raise ValueError(
                    f"`y` must have shape (B, T, m); got rank {y_np.ndim} {y_np.shape}."
                )
            B, T, m = y_np.shape
            if B == 0:
                raise ValueError("`y` is an empty batch (B = 0).")
            if T < 2:
                raise ValueError(f"`y` must have T >= 2 time steps; got T = {T}.")
            if m == 0:
                raise ValueError(
                    f"`y` has shape {y_np.shape}: no observed components (m = 0). Give each "
                    "step's observations as the last axis, m >= 1."
                )
            if not np.issubdtype(y_np.dtype, np.floating):
                raise ValueError(f"`y` must be a floating-point array; got dtype {y_np.dtype}.")
            # The dtype JAX will store (float64 becomes float32 without x64): cast first, so that
            # the finiteness checks see the stored values.
            dtype = np.dtype(jax.dtypes.canonicalize_dtype(y_np.dtype))
            if mask is None:
                mask_np = np.ones((B, T, m), bool)
            else:
                mask_np = _as_array("mask", mask)
                if mask_np.dtype != np.bool_:
                    raise ValueError(f"`mask` must be boolean; got dtype {mask_np.dtype}.")
                if mask_np.shape == (B, T):
                    mask_np = np.broadcast_to(mask_np[:, :, None], (B, T, m))
                elif mask_np.shape != (B, T, m):
                    raise ValueError(
                        f"`mask` must have shape (B, T) = {(B, T)} or (B, T, m) = {(B, T, m)}; "
                        f"got {mask_np.shape}."
                    )
            y_np = cast_checked("y", y_np, dtype, mask_np)
            bad = mask_np & ~np.isfinite(y_np)
            if bad.any():
                b, t, j = _first_bad(bad)
                raise ValueError(
                    f"`y` has a non-finite value {y_np[b, t, j]} at unmasked index "
                    f"[{b}, {t}, {j}]; mask it or fix it."
                )
            if u is None:
                u_np = np.zeros((B, T, 0), dtype)
            else:
                u_np = _as_numeric("u", u)
                if u_np.ndim != 3:
                    raise ValueError(
                        f"`u` must have shape (B, T, p); got rank {u_np.ndim} {u_np.shape}."
                    )
                if u_np.shape[0] != B:
                    raise ValueError(f"`u` has batch size {u_np.shape[0]} but `y` has B = {B}.")
                if u_np.shape[1] != T:
                    raise ValueError(f"`u` has {u_np.shape[1]} time steps but `y` has T = {T}.")
                u_np = cast_checked("u", u_np, dtype)
                if not np.all(np.isfinite(u_np)):
                    b, t, j = _first_bad(~np.isfinite(u_np))
                    raise ValueError(
                        f"`u` has a non-finite value {u_np[b, t, j]} at index [{b}, {t}, {j}]."
                    )
            self.y = jnp.asarray(np.where(mask_np, y_np, np.zeros((), dtype)), dtype)
            self.u = jnp.asarray(u_np, dtype)
            self.mask = as_jax(mask_np)
        else:  # inside a transformation: trust the caller, only normalise.
            y = jnp.asarray(y)
            B, T, m = y.shape
            self.u = jnp.zeros((B, T, 0), y.dtype) if u is None else jnp.asarray(u)
            if mask is None:
                mask = jnp.ones((B, T, m), bool)
            elif mask.ndim == 2:
                mask = jnp.broadcast_to(mask[:, :, None], (B, T, m))
            self.mask = mask
            self.y = jnp.where(mask, y, 0.0)

    @property
    def batch_size(self) -> int:
        """B, the number of trajectories."""
        return self.y.shape[0]

    @property
    def num_steps(self) -> int:
        """T, the number of time steps."""
        return self.y.shape[1]

    @property
    def obs_dim(self) -> int:
        """The observation dimension m."""
        return self.y.shape[2]

    @property
    def input_dim(self) -> int:
        """The input dimension p (0 without inputs)."""
        return self.u.shape[2]

    def __getitem__(self, idx) -> Trajectories:
        """Select trajectories along the batch axis (the result keeps a batch axis)."""
        if isinstance(idx, (int, np.integer)):
            idx = slice(idx, idx + 1) if idx != -1 else slice(-1, None)
        host_idx = _host_index(idx)
        if host_idx is not None and _on_host(self):
            try:  # NumPy indexes exactly as JAX does; no program per shape (see _on_host)
                return jax.tree_util.tree_map(
                    lambda a: _back_like(np.asarray(a)[host_idx], a) if np.ndim(a) else a, self
                )
            except (IndexError, TypeError):  # NumPy refuses what JAX clamps: JAX decides
                pass
        return jax.tree_util.tree_map(lambda a: a[idx] if jnp.ndim(a) else a, self)

    @classmethod
    @no_type_check  # validates its arguments
    def from_arrays(cls, y, u=None, mask=None) -> Trajectories:
        """Trajectories from arrays of one record or of a batch.

        Args:
            y: (T,) one record of a scalar output, (T, m) one record, or (B, T, m) a batch.
            u: ``None``, or the inputs with the same leading axes: (T,) / (T, p) for one record
                (y of rank 1 or 2), (B, T, p) for a batch.
            mask: ``None``, or booleans shaped like ``y`` (or (T,) / (B, T): whole steps).

        Returns:
            :class:`Trajectories` with a batch axis (B = 1 for one record), validated as the
            constructor does.
        """
        y = _as_array("y", y) if _is_concrete(y) else y
        if y.ndim == 3:
            return cls(y, u, mask)
        if y.ndim not in (1, 2):
            raise ValueError(f"`y` must have shape (T,), (T, m) or (B, T, m); got {y.shape}.")

        def one(a, name):
            if a is None:
                return None
            a = _as_array(name, a) if _is_concrete(a) else a
            if a.ndim not in (1, 2):
                raise ValueError(
                    f"`{name}` of one record must have shape (T,) or (T, k); got {a.shape}."
                )
            return (a[:, None] if a.ndim == 1 and name != "mask" else a)[None]

        return cls(one(y, "y"), one(u, "u"), one(mask, "mask"))

    @no_type_check  # validates its arguments
    def head(self, steps: int) -> Trajectories:
        """The first ``steps`` steps of every record (inputs and mask with them).

        Raises:
            ValueError: ``steps`` outside [2, T].
        """
        T = self.num_steps
        if not (isinstance(steps, (int, np.integer)) and 2 <= steps <= T):
            raise ValueError(f"`steps` must be an integer in [2, T = {T}]; got {steps!r}.")
        return self.windows(steps, step=T)  # one window per record, at its start

    @no_type_check  # validates its arguments
    def windows(self, length: int, step: int | None = None) -> Trajectories:
        """Cut every record into windows of ``length`` steps, starting every ``step`` steps.

        Window i of record b holds steps ``[i·step, i·step + length)`` of it, with its inputs and
        mask; the tail that does not fill a window is dropped. Windows are ordered record by
        record (all windows of record 0 first). Windows that fall on a record's masked padding
        are kept (their entries stay masked).

        Args:
            length: steps per window, in [2, T].
            step: steps between window starts (≥ 1); ``None``: ``length`` (no overlap).

        Returns:
            (B·W, length, ·) :class:`Trajectories` with W = (T − length) // step + 1.

        Raises:
            ValueError: ``length`` outside [2, T] or ``step < 1``.
        """
        T = self.num_steps
        step = length if step is None else step
        if not (isinstance(length, (int, np.integer)) and 2 <= length <= T):
            raise ValueError(f"`length` must be an integer in [2, T = {T}]; got {length!r}.")
        if not (isinstance(step, (int, np.integer)) and step >= 1):
            raise ValueError(f"`step` must be an integer >= 1; got {step!r}.")
        starts = np.arange(0, T - length + 1, step)
        idx = starts[:, None] + np.arange(length)
        host = _on_host(self)
        if not host:
            idx = as_jax(idx)

        def cut(a):
            shape = (a.shape[0] * len(starts), length) + a.shape[2:]
            if host:  # NumPy's gather: no program per shape (see _on_host)
                return _back_like(np.asarray(a)[:, idx].reshape(shape), a)
            return a[:, idx].reshape(shape)

        return Trajectories(cut(self.y), cut(self.u), cut(self.mask))


def _resolve_noise(name: str, flag, default: AbstractNoise) -> AbstractNoise | None:
    if isinstance(flag, bool | np.bool_):
        return default if flag else None
    if flag is None:
        return None
    if not isinstance(flag, AbstractNoise):
        raise TypeError(
            f"`{name}` must be True, False or a noise model such as ceemx.DiagonalGaussian; "
            f"got {flag!r:.80}."
        )
    return flag


def _num_steps(num_steps, u) -> int:
    """``num_steps`` checked (an integer in [1, 2**31 - 1]) and equal to the inputs' T."""
    T = cast(int, check_int("num_steps", num_steps, 1))
    if u is not None and np.ndim(u) == 3 and np.shape(u)[1] != T:
        raise ValueError(f"`num_steps` = {T} but `u` has T = {np.shape(u)[1]} steps.")
    return T


def sample_noise(noise: AbstractNoise, key: PRNGKeyArray, shape, dtype) -> Array:
    """Draws of a noise model with leading axes ``shape`` (see :meth:`AbstractNoise.sample`)."""
    return noise.sample(key, tuple(shape), dtype)


def rollout_one(
    system: AbstractSystem,
    x1: State,
    u: Float[Array, "T p"],
    w: Float[Array, "T-1 n"] | None = None,
) -> Trajectory:
    """States (T, n) of one trajectory: x_{t+1} = f(x_t, u_t, t) + w_t from x₁, T = len(u)."""
    T = u.shape[0]
    ts = jnp.arange(T)
    w = jnp.zeros((T - 1, x1.shape[0]), x1.dtype) if w is None else w

    def step(x, inp):
        ut, t, wt = inp
        nxt = system.dynamics(x, ut, t) + wt
        return nxt, nxt

    _, xs = jax.lax.scan(step, x1, (u[:-1], ts[:-1], w))
    return jnp.concatenate([x1[None], xs], axis=0)


def simulate(
    system: AbstractSystem,
    key: PRNGKeyArray,
    x0: Float[ArrayLike, "B n"],
    num_steps: int,
    u: Float[ArrayLike, "B T p"] | None = None,
    *,
    process_noise: bool | AbstractNoise = True,
    obs_noise: bool | AbstractNoise = True,
) -> tuple[States, Trajectories]:
    """Simulate B trajectories of ``num_steps`` steps from initial states ``x0``.

    Args:
        system: the model to simulate.
        key: PRNG key; the result is a deterministic function of it.
        x0: (B, n) initial states x₁.
        num_steps: T.
        u: (B, T, p) inputs or ``None``.
        process_noise: ``True`` to sample the system's own process noise, ``False`` for none
            (deterministic dynamics), or a noise model to sample instead.
        obs_noise: likewise for the observation noise (``False``: exact observations).

    Returns:
        The true states (B, T, n) and the observations as :class:`Trajectories`, in the dtype
        of the system's parameters (``x0`` and ``u`` are cast to it).

    Raises:
        TypeError: a complex or non-numeric ``x0`` or ``u``.
        ValueError: ``x0`` not (B, n) or not finite, ``u`` not (B, T, p); a ``dynamics``,
            ``vector_field`` or ``observe`` that returns another shape or dtype than the
            system's, or not one array (:func:`ceemx.models.method_check.check_methods`, as
            :func:`ceemx.fit` and :func:`ceemx.smooth` check); a simulation that is not finite,
            naming the trajectory, the step and the method that returned NaN or inf.
    """
    check_methods(system)
    dtype = jnp.dtype(float_dtype(system))
    x0 = _start_states(x0, system.state_dim, dtype)
    B, _ = x0.shape
    T = _num_steps(num_steps, u)
    if u is None:
        u = jnp.zeros((B, T, 0), dtype)
    else:
        if isinstance(u, Tracer):
            u = u.astype(dtype)
        else:
            u = jnp.asarray(cast_checked("u", _as_numeric("u", u), dtype), dtype)
        if u.shape != (B, T, system.input_dim):
            raise ValueError(
                f"`u` must have shape (B, T, p) = {(B, T, system.input_dim)}; got {u.shape}."
            )
    pn = _resolve_noise("process_noise", process_noise, system.process_noise)
    on = _resolve_noise("obs_noise", obs_noise, system.obs_noise)
    xs, y = _simulate(system, key, x0, u, pn, on)
    if _is_concrete(xs):
        where = nonfinite_run(xs, y)
        if where is not None:
            raise ValueError(f"simulate: the simulation is not finite: {where}")
    # Built outside the compiled program, so that concrete observations are validated.
    return xs, Trajectories(y, u if u.shape[-1] else None)


def _start_states(x0, n: int, dtype) -> Array:
    """``x0`` as finite (B, n) states in ``dtype`` (a traced one is only cast), or raise."""
    if isinstance(x0, Tracer):
        return x0.astype(dtype)
    a = cast_checked("x0", _as_numeric("x0", x0), dtype)
    if a.ndim != 2 or a.shape[1] != n:
        raise ValueError(f"`x0` must have shape (B, n) with n = {n}; got {a.shape}.")
    if not np.all(np.isfinite(a)):
        bad = list(_first_bad(~np.isfinite(a)))
        raise ValueError(f"`x0` has a non-finite value at index {bad}.")
    return as_jax(a)


@program(runs=Runs.ONCE)  # data generation: once per data set, cheap to run beside its compile
def _simulate(
    system: AbstractSystem,
    key: PRNGKeyArray,
    x0: Float[Array, "B n"],
    u: Float[Array, "B T p"],
    pn: AbstractNoise | None,
    on: AbstractNoise | None,
) -> tuple[States, Float[Array, "B T m"]]:
    """The compiled body of :func:`simulate`: one program per shape and system structure.

    Called eagerly, the same operations compiled one small program each, for every new shape
    (a scan per call: ≈ 0.1 s per simulation on a 2 GHz core).
    """
    B, n = x0.shape
    T, dtype = u.shape[1], x0.dtype
    kw, kv = jax.random.split(key)
    if pn is None:
        w = jnp.zeros((B, T - 1, n), dtype)
    else:
        w = sample_noise(pn, kw, (B, T - 1), dtype)
    xs = jax.vmap(lambda a, b, c: rollout_one(system, a, b, c))(x0, u, w)
    ts = jnp.arange(T)
    y = jax.vmap(jax.vmap(system.observe))(xs, u, jnp.broadcast_to(ts, (B, T)))
    if on is not None:
        y = y + sample_noise(on, kv, (B, T), dtype)
    return xs, y


def foh_inputs(data: Trajectories | ArrayLike):
    """The inputs of a first-order-hold system: [u_t, u_{t+1}] side by side at every step.

    A system with ``hold="foh"`` (:class:`ceemx.AbstractContinuousSystem`) interpolates the input
    linearly between samples, which needs u_{t+1} in step t while ``dynamics(x, u, t)`` is given
    one step's input. This stacks the next sample onto each step's input; the last step repeats
    u_T (the input after the record is unknown: a zero-order hold over the final interval, which
    only reaches the state after the last observation).

    Args:
        data: :class:`Trajectories` (its ``u`` is stacked; y and the mask are kept), or an input
            array (…, T, p), e.g. the ``u`` of :func:`simulate`.

    Returns:
        The same kind with inputs (…, T, 2p): entries [:p] are u_t, [p:] are u_{t+1}.
    """
    if isinstance(data, Trajectories):
        return eqx.tree_at(lambda d: d.u, data, foh_inputs(data.u))
    u = as_jax(data)
    if u.ndim < 2:
        raise ValueError(f"inputs must have shape (..., T, p); got {u.shape}.")
    following = jnp.concatenate([u[..., 1:, :], u[..., -1:, :]], axis=-2)
    return jnp.concatenate([u, following], axis=-1)
