"""Batches of observed trajectories, validated on construction, and simulation of systems."""

from __future__ import annotations

from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from ceemx.data.arrays import (
    as_array,
    as_numeric,
    back_like,
    cast_checked,
    first_bad,
    host_index,
    is_concrete,
    on_host,
)
from ceemx.data.info import DataInfo
from ceemx.data.records import is_record_list, missing_as_masked, one_or_batch, pad_records
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


class Trajectories(eqx.Module):
    """A batch of B trajectories of T steps: observations y, inputs u and an observation mask.

    Args:
        y: (B, T, m) observations. Entries where ``mask`` is False are ignored and may be NaN.
        u: (B, T, p) inputs held constant over each step, or ``None`` (no input; p = 0).
        mask: ``None`` (everything observed), (B, T) booleans (whole steps observed or not) or
            (B, T, m) booleans (per dimension). Trajectories of different lengths are padded to a
            common T and their padding masked: states past the last observation then follow the
            dynamics and add nothing to the objective at its optimum
            (:meth:`from_arrays` does it from a list of records).
        info: optional :class:`~ceemx.data.info.DataInfo` (sample time, channel names and
            units), a static field: kept by slicing, :meth:`windows` and :meth:`with_info`, and
            read by the score tables and :func:`ceemx.save`.

    Raises:
        ValueError: naming the argument and the first offending index, for wrong ranks,
            mismatched B or T, NaN/inf in unmasked ``y`` or anywhere in ``u`` (checked after the
            cast to the stored dtype: a finite value that overflows it is refused), an empty
            batch, T < 2, no observed component (m = 0), a ragged nested sequence, a
            non-floating ``y``, a mask of the wrong shape or dtype, or an ``info`` whose names
            or units do not match m or p.
        TypeError: for a complex or non-numeric (e.g. string) ``y`` or ``u``, or an ``info``
            that is not a :class:`~ceemx.data.info.DataInfo`.

    ``y`` and ``u`` are stored in ``y``'s floating dtype as JAX stores it (float64 becomes
    float32 without ``jax_enable_x64``); integer or boolean ``u`` is converted.

    The stored ``y`` has masked entries replaced by zeros and ``mask`` is always (B, T, m) bool.
    NaN outputs are refused here; :meth:`from_arrays`, the constructor for a user's arrays,
    takes them as missing samples.
    """

    y: Observations
    u: Inputs
    mask: ObservationMask
    info: DataInfo | None = eqx.field(static=True, default=None)

    def __init__(self, y, u=None, mask=None, *, info: DataInfo | None = None):
        if info is not None and not isinstance(info, DataInfo):
            raise TypeError(f"`info` must be a ceemx.data.DataInfo or None; got {info!r}.")
        self.info = info
        concrete = is_concrete(y) and is_concrete(u) and is_concrete(mask)
        if concrete:
            y_np = as_numeric("y", y)
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
                mask_np = as_array("mask", mask)
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
                b, t, j = first_bad(bad)
                raise ValueError(
                    f"`y` has a non-finite value {y_np[b, t, j]} at unmasked index "
                    f"[{b}, {t}, {j}]; mask it or fix it."
                )
            if u is None:
                u_np = np.zeros((B, T, 0), dtype)
            else:
                u_np = as_numeric("u", u)
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
                    b, t, j = first_bad(~np.isfinite(u_np))
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
        if info is not None:
            info.check(self.y.shape[2], self.u.shape[2])

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
        host_idx = host_index(idx)
        if host_idx is not None and on_host(self):
            try:  # NumPy indexes exactly as JAX does; no program per shape (see on_host)
                return jax.tree_util.tree_map(
                    lambda a: back_like(np.asarray(a)[host_idx], a) if np.ndim(a) else a, self
                )
            except (IndexError, TypeError):  # NumPy refuses what JAX clamps: JAX decides
                pass
        return jax.tree_util.tree_map(lambda a: a[idx] if jnp.ndim(a) else a, self)

    @classmethod
    @no_type_check  # validates its arguments
    def from_arrays(
        cls,
        y,
        u=None,
        mask=None,
        *,
        dt: float | None = None,
        output_names=None,
        output_units=None,
        input_names=None,
        input_units=None,
        time_unit: str = "s",
    ) -> Trajectories:
        """Trajectories from a user's arrays: one record, a batch, or a list of records.

        Args:
            y: (T,) one record of a scalar output, (T, m) one record, (B, T, m) a batch, or a
                list (or tuple) of NumPy/JAX arrays, one record each, (T_b,) or (T_b, m) of any
                lengths T_b: padded at the end to the longest and the padding masked
                (:func:`~ceemx.data.records.pad_records`; every score counts real samples only).
                NaN outputs are missing samples: masked (``mask`` records them).
            u: ``None``, or the inputs with the same leading axes (a list with a list of ``y``).
                NaN inputs are refused: a model needs every input sample.
            mask: ``None``, or booleans shaped like ``y`` (or (T,) / (B, T): whole steps; a list
                with a list of ``y``).
            dt: the sample time (in ``time_unit``), stored in ``info``
                (:class:`~ceemx.data.info.DataInfo`; this and the following are optional).
            output_names: one name per output (a string: one output).
            output_units: one unit per output.
            input_names: one name per input.
            input_units: one unit per input.
            time_unit: the unit of ``dt``.

        Returns:
            :class:`Trajectories` with a batch axis (B = 1 for one record), validated as the
            constructor does, with ``info`` when any metadata was given.

        Raises:
            ValueError: as the constructor; a NaN input (naming record, step and input); records
                with different numbers of channels; names or units not one per channel.

        Example:
            >>> data = Trajectories.from_arrays(
            ...     [np.ones(5), np.ones(3)], [np.zeros(5), np.zeros(3)], dt=0.1, output_names="h"
            ... )
            >>> data.y.shape, data.mask[1, :, 0].tolist(), data.info.dt
            ((2, 5, 1), [True, True, True, False, False], 0.1)
        """
        meta = (dt, output_names, output_units, input_names, input_units)
        info = None
        if any(v is not None for v in meta) or time_unit != "s":
            info = DataInfo(dt, time_unit, output_names, output_units, input_names, input_units)
        if is_record_list(y):
            y, u, mask = pad_records(y, u, mask)
        else:
            y, u, mask = one_or_batch(y, u, mask)
        if isinstance(y, np.ndarray) and all(
            isinstance(a, np.ndarray) or a is None for a in (u, mask)
        ):
            B, T, m = y.shape
            full = np.ones((B, T, m), bool) if mask is None else np.asarray(mask)
            if full.dtype == np.bool_ and full.shape in ((B, T), (B, T, m)):
                full = np.broadcast_to(full[:, :, None] if full.ndim == 2 else full, (B, T, m))
                y, missing = missing_as_masked(y, u, full)
                mask = mask if missing is full else missing
        return cls(y, u, mask, info=info)

    def with_info(self, info: DataInfo | None = None, **changes) -> Trajectories:
        """The same data with ``info`` (replaced), or with ``changes`` to the current one.

        ``data.with_info(dt=0.1, output_units=("V",))`` keeps the other fields of ``data.info``
        (a fresh :class:`~ceemx.data.info.DataInfo` when there is none).

        Raises:
            ValueError, TypeError: as :class:`~ceemx.data.info.DataInfo`, or names and units not
                one per channel.
        """
        if info is None:
            info = (self.info or DataInfo()).replace(**changes)
        elif changes:
            info = info.replace(**changes)
        if not isinstance(info, DataInfo):
            raise TypeError(f"`info` must be a ceemx.data.DataInfo; got {info!r}.")
        info.check(self.obs_dim, self.input_dim)
        return Trajectories(self.y, self.u, self.mask, info=info)

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
        host = on_host(self)
        if not host:
            idx = as_jax(idx)

        def cut(a):
            shape = (a.shape[0] * len(starts), length) + a.shape[2:]
            if host:  # NumPy's gather: no program per shape (see on_host)
                return back_like(np.asarray(a)[:, idx].reshape(shape), a)
            return a[:, idx].reshape(shape)

        return Trajectories(cut(self.y), cut(self.u), cut(self.mask), info=self.info)


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
        u = as_jax(np.zeros((B, T, 0), dtype))
    else:
        if isinstance(u, Tracer):
            u = u.astype(dtype)
        else:
            u = as_jax(np.asarray(cast_checked("u", as_numeric("u", u), dtype), dtype))
        if u.shape != (B, T, system.input_dim):
            raise ValueError(
                f"`u` must have shape (B, T, p) = {(B, T, system.input_dim)}; got {u.shape}."
            )
    pn = _resolve_noise("process_noise", process_noise, system.process_noise)
    on = _resolve_noise("obs_noise", obs_noise, system.obs_noise)
    xs, y = _simulate(system, key, x0, u, pn, on)
    if is_concrete(xs):
        where = nonfinite_run(xs, y)
        if where is not None:
            raise ValueError(f"simulate: the simulation is not finite: {where}")
    # Built outside the compiled program, so that concrete observations are validated.
    return xs, Trajectories(y, u if u.shape[-1] else None)


def _start_states(x0, n: int, dtype) -> Array:
    """``x0`` as finite (B, n) states in ``dtype`` (a traced one is only cast), or raise."""
    if isinstance(x0, Tracer):
        return x0.astype(dtype)
    a = cast_checked("x0", as_numeric("x0", x0), dtype)
    if a.ndim != 2 or a.shape[1] != n:
        raise ValueError(f"`x0` must have shape (B, n) with n = {n}; got {a.shape}.")
    if not np.all(np.isfinite(a)):
        bad = list(first_bad(~np.isfinite(a)))
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
        out = eqx.tree_at(lambda d: d.u, data, foh_inputs(data.u))
        if data.info is None:
            return out
        names = [f"{n} (next)" for n in data.info.input_names or ()]
        return out.with_info(data.info.with_more_inputs(names, data.info.input_units or ()))
    u = as_jax(data)
    if u.ndim < 2:
        raise ValueError(f"inputs must have shape (..., T, p); got {u.shape}.")
    host = on_host(u)  # NumPy on the host: no program per shape
    xp, a = (np, np.asarray(u)) if host else (jnp, u)
    following = xp.concatenate([a[..., 1:, :], a[..., -1:, :]], axis=-2)
    out = xp.concatenate([a, following], axis=-1)
    return back_like(out, u) if host else out
