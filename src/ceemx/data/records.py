"""Records of different lengths as one padded, masked batch; NaN outputs as missing samples.

The one implementation behind :meth:`ceemx.Trajectories.from_arrays` (a list of records) and
:func:`ceemx.data.from_nonlinear_benchmarks`:

- :func:`pad_records` — records (T_b, k) of different lengths stacked into (B, T, k) with
  T = max T_b: outputs padded with zeros and masked, inputs padded by holding the last one (the
  padding is never scored, and a held input keeps a free run past the end bounded where the
  record left it).
- :func:`missing_as_masked` — NaN outputs become masked samples (the mask records them); NaN
  inputs are refused (a model is driven by every input sample: there is no "missing" input).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np

from ceemx.data.arrays import as_array, is_concrete

__all__ = ["is_record_list", "missing_as_masked", "one_or_batch", "pad_records"]


def _column(a, what: str, b: int) -> np.ndarray:
    """One record's array as (T_b, k) (a (T_b,) array is one channel)."""
    try:
        arr = np.asarray(a)
    except ValueError:
        raise ValueError(f"record {b}: `{what}` must be a rectangular array.") from None
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"record {b}: `{what}` must have shape (T,) or (T, k); got {arr.shape}.")
    return arr


def pad_records(
    ys: Sequence, us: Sequence | None = None, masks: Sequence | None = None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """B records stacked into one batch, the shorter ones padded at the end and the padding masked.

    Args:
        ys: B outputs, each (T_b,) or (T_b, m) with the same m.
        us: ``None``, or B inputs, each (T_b,) or (T_b, p) with the same p (T_b as its output's).
        masks: ``None``, or B masks of present samples, each (T_b,) or (T_b, m) booleans.

    Returns:
        ``(y, u, mask)``: (B, T, m) outputs (zeros in the padding), (B, T, p) inputs (the last
        sample held in the padding; ``None`` without ``us``) and (B, T, m) booleans, False in
        the padding; T = max T_b. Dtypes are the records' (promoted across records).

    Raises:
        ValueError: no records; different numbers of records, outputs or inputs; an input or
            mask whose length is not its output's.
    """
    if len(ys) == 0:
        raise ValueError("no records given.")
    B = len(ys)
    for what, given in (("u", us), ("mask", masks)):
        if given is not None and len(given) != B:
            raise ValueError(f"{B} records of `y` but {len(given)} of `{what}`.")
    y_cols = [_column(y, "y", b) for b, y in enumerate(ys)]
    u_cols = None if us is None else [_column(u, "u", b) for b, u in enumerate(us)]
    lengths = [y.shape[0] for y in y_cols]
    for what, cols in (("outputs", y_cols), ("inputs", u_cols)):
        if cols is not None and len({c.shape[1] for c in cols}) > 1:
            widths = [c.shape[1] for c in cols]
            raise ValueError(f"the records have different numbers of {what}: {widths}.")
    if u_cols is not None:
        for b, (u, n) in enumerate(zip(u_cols, lengths, strict=True)):
            if u.shape[0] != n:
                raise ValueError(f"record {b}: `u` has {u.shape[0]} samples, `y` {n}.")
    T = max(lengths)
    y = np.zeros((B, T, y_cols[0].shape[1]), np.result_type(*y_cols))
    mask = np.zeros(y.shape, bool)
    for b, (yb, n) in enumerate(zip(y_cols, lengths, strict=True)):
        y[b, :n] = yb
        if masks is None:
            mask[b, :n] = True
        else:
            mb = np.asarray(masks[b])
            if mb.dtype != np.bool_ or mb.shape[0] != n or mb.ndim not in (1, 2):
                raise ValueError(
                    f"record {b}: `mask` must be booleans of shape ({n},) or ({n}, m); "
                    f"got {mb.dtype} {mb.shape}."
                )
            mask[b, :n] = mb[:, None] if mb.ndim == 1 else mb
    if u_cols is None:
        return y, None, mask
    u = np.zeros((B, T, u_cols[0].shape[1]), np.result_type(*u_cols))
    for b, (ub, n) in enumerate(zip(u_cols, lengths, strict=True)):
        u[b, :n] = ub
        u[b, n:] = ub[-1]  # the padding's input: the last one held (never scored: masked)
    return y, u, mask


def missing_as_masked(
    y: np.ndarray, u: np.ndarray | None, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """NaN outputs as missing: masked, and zero in the returned outputs; NaN inputs refused.

    Args:
        y: (B, T, m) outputs.
        u: (B, T, p) inputs, or ``None``.
        mask: (B, T, m) booleans of present samples.

    Returns:
        ``(y, mask)`` with every NaN of ``y`` masked (a ±inf stays: it is an error, not a gap,
        and the :class:`~ceemx.Trajectories` constructor refuses it).

    Raises:
        ValueError: a NaN input, naming the record, step and channel.
    """
    if u is not None and np.issubdtype(u.dtype, np.floating):
        nan_u = np.isnan(u)
        if nan_u.any():
            b, t, j = (int(i) for i in np.argwhere(nan_u)[0])
            raise ValueError(
                f"`u` is NaN at record {b}, step {t}, input {j} ({int(nan_u.sum())} NaN inputs "
                "in all): a model is driven by every input sample, so an input cannot be "
                "missing. Fill the gap (e.g. hold the last value) or split the record there."
            )
    if not np.issubdtype(y.dtype, np.floating):
        return y, mask
    nan_y = np.isnan(y)
    if not nan_y.any():
        return y, mask
    return np.where(nan_y, np.zeros((), y.dtype), y), mask & ~nan_y


def is_record_list(y) -> bool:
    """Whether ``y`` is a list or tuple of arrays, one record each (not a nested list)."""
    return (
        isinstance(y, (list, tuple))
        and len(y) > 0
        and all(isinstance(r, (np.ndarray, jax.Array)) for r in y)
    )


def one_or_batch(y, u, mask):
    """(B, T, ·) arrays (NumPy where concrete) from one record's or a batch's arrays."""
    y = as_array("y", y) if is_concrete(y) else y
    if y.ndim == 3:
        return y, as_array("u", u) if is_concrete(u) and u is not None else u, mask
    if y.ndim not in (1, 2):
        raise ValueError(f"`y` must have shape (T,), (T, m) or (B, T, m); got {y.shape}.")

    def one(a, name):
        if a is None:
            return None
        a = as_array(name, a) if is_concrete(a) else a
        if a.ndim not in (1, 2):
            raise ValueError(
                f"`{name}` of one record must have shape (T,) or (T, k); got {a.shape}."
            )
        return (a[:, None] if a.ndim == 1 and name != "mask" else a)[None]

    return one(y, "y"), one(u, "u"), one(mask, "mask")
