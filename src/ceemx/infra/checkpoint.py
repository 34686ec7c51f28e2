"""Atomic, verified checkpoints of a fit: arrays via Equinox serialisation, the rest as JSON.

Layout of a checkpoint folder: ``state-<epoch>.eqx`` (the leaves of the fit state) and
``latest.json`` (the epoch, the state file's name and its sha256, the history, and the
*fingerprint* of the fit that wrote it). Each file is written to a temporary name and moved into
place with ``os.replace`` (atomic on POSIX); ``latest.json`` is replaced last, so a run killed at
any instant leaves either the previous or the new checkpoint, never a torn one.

The fingerprint (:func:`fingerprint`) describes the fit: the layout of the state, the method and
its options, the system's structure and fixed parameters, and the data. :func:`load` resumes only
when it matches; otherwise — and when a file is corrupt or the saved state is not finite — it
raises :class:`CheckpointError`, or, with ``mismatch="restart"``, warns and starts afresh.
:func:`lock` holds the folder for one writer (:mod:`ceemx.infra.folder_lock`). See
``docs/guarantees.md`` ("Checkpoints").
"""

from __future__ import annotations

import errno
import hashlib
import io
import os
import re
import tempfile
import uuid
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, Literal

import equinox as eqx
import jax
import jax.tree_util as jtu
import numpy as np

from ceemx.infra.folder_lock import folder_lock
from ceemx.infra.json_values import from_json, to_json
from ceemx.lib.tree import as_jax

__all__ = [
    "CheckpointError",
    "atomic_write",
    "check_folder",
    "fingerprint",
    "load",
    "load_leaf",
    "lock",
    "save",
]

_LATEST = "latest.json"
_FORMAT = 2
_MISMATCH = ("raise", "restart")
# Readable names of the fingerprint's parts, in the order a mismatch reports them.
_PARTS = {
    "method": "fit method",
    "options": "method options",
    "system_structure": "system (structure, static fields, trainable leaves, log-prior)",
    "system_values": "system (initial θ or fixed parameter values, sha256)",
    "data": "data (y, u, mask; sha256)",
    "state_layout": "state layout (shapes and dtypes)",
}


class CheckpointError(ValueError):
    """A checkpoint that cannot be resumed: another problem's, corrupt, or not finite."""


def _load_leaf(f, x: Any) -> Any:
    """Equinox's default deserialisation, a JAX leaf read by a transfer.

    ``jnp.load`` (the default's) converts with ``jnp.asarray``, which compiles a small program
    per new shape and dtype (≈ 20 ms each); the values, dtype and bfloat16 handling are its.
    """
    if not isinstance(x, (jax.Array, jax.ShapeDtypeStruct)):
        return eqx.default_deserialise_filter_spec(f, x)
    out = np.load(f)
    if isinstance(out, np.ndarray):
        if out.dtype == "V2":  # bfloat16, which NumPy saves as void16
            out = out.view(jax.dtypes.bfloat16)
        try:
            return as_jax(out)
        except (TypeError, AssertionError):  # an unsupported dtype: as jnp.load, left as it is
            return out
    return out


def check_folder(folder: str, mismatch: str = "raise") -> None:
    """Validate the checkpoint options and that ``folder`` is writable, before any compute.

    Creates ``folder`` if needed and writes and removes a probe file in it.

    Raises:
        ValueError: for a ``mismatch`` other than ``"raise"`` or ``"restart"``.
        CheckpointError: naming the folder, when it cannot be created or written to.
    """
    if mismatch not in _MISMATCH:
        raise ValueError(f'`checkpoint_mismatch` must be "raise" or "restart"; got {mismatch!r}.')
    probe = os.path.join(folder, f".tmp-probe-{uuid.uuid4().hex}")
    try:
        os.makedirs(folder, exist_ok=True)
        try:
            with open(probe, "wb") as f:
                f.write(b"probe")
        finally:  # also when the write fails (a full disk): no stray probe left behind
            if os.path.exists(probe):
                os.remove(probe)
    except OSError as err:
        raise CheckpointError(
            f"checkpoint folder {folder!r} is not writable ({err.strerror or err}); "
            "pass a writable folder or `checkpoint=None`."
        ) from err


@contextmanager
def lock(folder: str | None) -> Iterator[None]:
    """Hold ``folder`` for this fit alone (nothing for ``None``); call after :func:`check_folder`.

    An advisory ``fcntl.flock`` lock on ``folder/.lock``, released when the block ends or the
    process dies; see :mod:`ceemx.infra.folder_lock`.

    Raises:
        CheckpointError: at once, when another fit (another process, or another fit in this one)
            holds the folder; the message names its pid, host and start time.
    """
    if folder is None:
        yield
        return
    with folder_lock(folder, CheckpointError):
        yield


#: Bytes handed to one ``os.write``: Linux writes at most 0x7ffff000 bytes per call, so a larger
#: request would come back short on a disk with room; a short write of a smaller one means the
#: file system is out of space (or the file-size limit is reached).
_WRITE_CHUNK = 1 << 30


def _atomic_write(path: str, data: bytes, mode: int | None = None) -> None:
    """``data`` into ``path`` atomically: a temporary in the folder, fsync, ``os.replace``.

    ``mode``: the file's permissions (``None``: the temporary's 0o600, as a checkpoint keeps).

    Any failure — a short or failed write, fsync, close — removes the temporary and raises an
    ``OSError`` with its errno; ``path`` is untouched.
    """
    folder = os.path.dirname(path) or "."
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-")
    try:
        try:
            _write_all(fd, data, tmp)
            if mode is not None:
                os.fchmod(fd, mode)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _write_all(fd: int, data: bytes, name: str) -> None:
    """Write all of ``data`` to ``fd``; a short write is retried once, then is ``ENOSPC``.

    A file system with less room than asked writes what fits and returns the count; only the
    next write fails with the reason (ENOSPC, EFBIG past ``ulimit -f``, EDQUOT). The retry
    surfaces that errno; a retry that again writes short, or nothing, raises ``ENOSPC`` naming
    the counts (NumPy's own writer reported such a disk as "3200 requested and 476 written").
    """
    view = memoryview(data)
    done = 0
    while done < len(view):
        want = min(len(view) - done, _WRITE_CHUNK)
        n = os.write(fd, view[done : done + want])
        done += n
        if n == want:
            continue
        retry = os.write(fd, view[done : done + want - n]) if n > 0 else 0
        done += retry
        if retry != want - n:
            raise OSError(
                errno.ENOSPC,
                f"No space left on device (a write stopped short: {done} of {len(view)} bytes "
                "written, and a retry wrote no more than part of the rest)",
                name,
            )


def atomic_write(path: str, write) -> None:
    """Write ``path`` by ``write(f)`` on a temporary file beside it, then ``os.replace`` it there.

    A reader sees the previous file or the whole new one, never a torn one (``os.replace`` is
    atomic on POSIX); the temporary is removed when ``write`` fails. As the checkpoints are
    written, but with the permissions ``open`` gives a new file (0o666 less the umask) where a
    checkpoint keeps the temporary's 0o600; :func:`ceemx.save` writes a model by it.
    """
    umask = os.umask(0)
    os.umask(umask)
    buffer = io.BytesIO()
    write(buffer)
    _atomic_write(path, buffer.getvalue(), mode=0o666 & ~umask)


def load_leaf(f, x: Any) -> Any:
    """Equinox's default deserialisation of one leaf, a JAX leaf read by a transfer (no compile).

    The ``filter_spec`` of ``eqx.tree_deserialise_leaves`` that the checkpoints and
    :func:`ceemx.load` use.
    """
    return _load_leaf(f, x)


def _sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _clean(text: str) -> str:
    """``text`` without memory addresses (``<function f at 0x7f…>``), stable across processes."""
    return re.sub(r" at 0x[0-9a-fA-F]+", "", text)


def _hash_arrays(*trees) -> str:
    """sha256 of the shapes, dtypes and bytes of every array leaf of ``trees``."""
    h = hashlib.sha256()
    for leaf in jtu.tree_leaves(trees):
        if eqx.is_array_like(leaf) and not isinstance(leaf, str):
            arr = np.ascontiguousarray(np.asarray(leaf))
            h.update(f"{arr.shape}{arr.dtype.str}".encode())
            h.update(arr.tobytes())
        else:
            h.update(_clean(repr(leaf)).encode())
    return h.hexdigest()


def _layout(tree) -> str:
    leaves, treedef = jtu.tree_flatten(tree)
    shapes = [
        f"{np.dtype(leaf.dtype).name}{list(np.shape(leaf))}" if eqx.is_array(leaf) else repr(leaf)
        for leaf in leaves
    ]
    return _clean(f"{treedef} {shapes}")


def _options(solver) -> str:
    """``field=value`` per leaf of ``solver`` (small arrays as numbers), plus its structure."""
    items = []
    for path, leaf in jtu.tree_flatten_with_path(solver)[0]:
        if eqx.is_array(leaf) and np.size(leaf) <= 16:
            value = repr(np.asarray(leaf).tolist())
        elif eqx.is_array(leaf):
            value = f"{np.dtype(leaf.dtype).name}{list(np.shape(leaf))} sha256 {_hash_arrays(leaf)}"
        else:
            value = repr(leaf)
        items.append(f"{jtu.keystr(path)}={value}")
    return _clean(f"{', '.join(items)}; {jtu.tree_structure(solver)}")


def fingerprint(template, problem, theta, solver) -> dict[str, str]:
    """What identifies a fit: compared on resume (all strings, stored in ``latest.json``).

    Args:
        template: the fit state as checkpointed (shapes and dtypes are compared).
        problem: the :class:`~ceemx.identification.problem.FitProblem` (structure, fixed
            parameters, data).
        theta: the initial flat θ (its values are part of the system's identity).
        solver: the fit solver (its class name and options).
    """
    return {
        "method": type(solver).__name__,
        "options": _options(solver),
        "system_structure": _layout((problem.template, problem.static, problem)),
        "system_values": _hash_arrays(problem.static, theta),
        "data": _hash_arrays(problem.data.y, problem.data.u, problem.data.mask),
        "state_layout": _layout(template),
    }


def save(folder: str, tree, history: list[dict], fingerprint: dict | None = None) -> None:
    """Write the fit state ``tree`` (a pytree of arrays), ``history`` and ``fingerprint``."""
    os.makedirs(folder, exist_ok=True)
    epoch = len(history)
    name = f"state-{epoch}.eqx"
    path = os.path.join(folder, name)
    buffer = io.BytesIO()  # serialised first: the disk sees one plain write (_write_all)
    eqx.tree_serialise_leaves(buffer, tree)
    data = buffer.getvalue()
    try:
        _atomic_write(path, data)
    except Exception as err:
        _raise_write_error(folder, err)
        raise
    meta = {
        "format": _FORMAT,
        "epoch": epoch,
        "state": name,
        "state_sha256": hashlib.sha256(data).hexdigest(),
        "fingerprint": fingerprint,
        "history": history,
    }
    text = to_json(meta)
    try:
        _atomic_write(os.path.join(folder, _LATEST), text.encode())
    except Exception as err:
        if os.path.exists(path):  # latest.json still names the previous state: keep that one
            os.remove(path)
        _raise_write_error(folder, err)
        raise
    for other in os.listdir(folder):
        # Older states, and temporaries of a write that was killed half-way.
        if (other.startswith("state-") and other != name) or other.startswith(".tmp-"):
            try:
                os.remove(os.path.join(folder, other))
            except FileNotFoundError:
                pass


def _raise_write_error(folder: str, err: BaseException) -> None:
    """A :class:`CheckpointError` naming the OS error behind ``err`` and its errno, if any.

    The message says what the user needs: the folder, the reason ("No space left on device",
    "File too large" past the file-size limit), and that the previous checkpoint is intact.
    """
    cause: BaseException | None = err
    while cause is not None and not isinstance(cause, OSError):
        cause = cause.__cause__ or cause.__context__
    if cause is None:
        return
    code = cause.errno
    name = f"{errno.errorcode[code]}, " if code is not None and code in errno.errorcode else ""
    limit = " — the process's file-size limit, `ulimit -f`" if code == errno.EFBIG else ""
    raise CheckpointError(
        f"could not write the checkpoint in {folder!r}: {cause.strerror or cause} "
        f"({name}errno {code}{limit}); the previous checkpoint there, if any, is kept unchanged. "
        "Free space or pass another folder to go on."
    ) from err


def _first_difference(saved: str, now: str, width: int = 40) -> str:
    if len(saved) == 64 and len(now) == 64:  # digests
        return f"sha256 {saved[:12]}… in the checkpoint, {now[:12]}… now"
    pairs = enumerate(zip(saved, now, strict=False))
    i = next((k for k, (a, b) in pairs if a != b), min(len(saved), len(now)))
    lo = max(0, i - width // 2)
    return f"…{saved[lo : i + width]!r}… in the checkpoint, …{now[lo : i + width]!r}… now"


def _describe_mismatch(saved: dict, now: dict) -> list[str]:
    """One line per differing part; another method's options and state layout go without saying."""
    parts = list(_PARTS)
    if saved.get("method") != now.get("method") and saved.get("method") is not None:
        parts = [p for p in parts if p not in ("options", "state_layout")]
    diffs = []
    for part in parts:
        label, a, b = _PARTS[part], saved.get(part), now.get(part)
        if a == b:
            continue
        if part == "method":
            diffs.append(f"{label}: written by {a}, resumed with {b}")
        elif a is None:
            diffs.append(f"{label}: not recorded in the checkpoint")
        else:
            diffs.append(f"{label}: {_first_difference(str(a), str(b))}")
    return diffs


def _non_finite(tree) -> list[str]:
    """Fields of a fit state with NaN/inf where they must be finite.

    θ and the weights everywhere; the states and J of the trajectories taking part (weight > 0);
    and every floating leaf of the solver's state — its scalars (the joint method's damping λ),
    Laplace EM's per-trajectory log-evidence and smoother start, Particle EM's stored draws, the
    learner's state — everywhere except, in a leaf of per-trajectory values (leading axis B), at
    the excluded trajectories, whose values no epoch reads.
    """
    bad = []
    theta = getattr(tree, "theta", None)
    if theta is not None and not np.all(np.isfinite(np.asarray(theta))):
        bad.append("theta")
    weights = getattr(tree, "weights", None)
    if weights is not None and not np.all(np.isfinite(np.asarray(weights))):
        bad.append("weights")
    active = None if weights is None else np.asarray(weights) > 0
    for path, leaf in jtu.tree_flatten_with_path(getattr(tree, "solver_state", None))[0]:
        if not eqx.is_inexact_array(leaf):
            continue
        arr = np.asarray(leaf)
        if active is not None and arr.ndim and arr.shape[0] == active.shape[0]:
            arr = arr[active]
        if not np.all(np.isfinite(arr)):
            bad.append(f"solver_state{jtu.keystr(path)}")
    for name in ("states", "J"):
        value = getattr(tree, name, None)
        if value is None or active is None:
            continue
        arr = np.asarray(value)
        finite = np.asarray(np.isfinite(arr).reshape(arr.shape[0], -1).all(axis=1))
        if not np.all(finite[active]):
            bad.append(name)
    return bad


def load(
    folder: str,
    template,
    fingerprint: dict | None = None,
    *,
    mismatch: Literal["raise", "restart"] = "raise",
) -> tuple[Any, list[dict]] | None:
    """(tree, history) from ``folder``'s latest checkpoint, or ``None`` when there is none.

    Args:
        folder: the checkpoint folder.
        template: a pytree with the structure, shapes and dtypes of the saved state.
        fingerprint: this fit's :func:`fingerprint`; compared with the stored one (``None``:
            not compared).
        mismatch: ``"raise"``: raise on a checkpoint that cannot be resumed; ``"restart"``: warn
            and return ``None`` (the fit starts afresh and overwrites it).

    Raises:
        CheckpointError: naming the folder and the reason: ``latest.json`` or the state file is
            corrupt (unreadable JSON, missing keys or file, sha256 mismatch, wrong leaves); the
            checkpoint was written for another fit (naming each differing part: method, options,
            system, data, state layout); or its state is not finite.

    A checkpoint of the format before fingerprints (no ``"fingerprint"`` key) is resumed with a
    warning: its state file is still checked against ``template`` and for finiteness.
    """
    path = os.path.join(folder, _LATEST)
    if not os.path.exists(path):
        return None
    try:
        return _load(folder, path, template, fingerprint)
    except CheckpointError as err:
        if mismatch == "restart":
            warnings.warn(
                f"{err} Starting afresh (`checkpoint_mismatch='restart'`); the checkpoint will "
                "be overwritten.",
                stacklevel=3,
            )
            return None
        raise


def _load(folder: str, path: str, template, fingerprint: dict | None):
    hint = 'pass a new folder or `checkpoint_mismatch="restart"` to start afresh.'
    try:
        with open(path, "rb") as f:
            meta = from_json(f.read().decode())
        name, history = meta["state"], meta["history"]
        if not isinstance(name, str) or os.path.basename(name) != name:
            raise TypeError(f"bad state file name {name!r}")
        if not isinstance(history, list):
            raise TypeError("`history` is not a list")
        if meta.get("epoch", len(history)) != len(history):  # e.g. a history emptied by hand
            raise ValueError(
                f"epoch {meta.get('epoch')!r} does not match the {len(history)} epochs of its "
                "history"
            )
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise CheckpointError(
            f"checkpoint file {path!r} is corrupt ({type(err).__name__}: {err}); {hint}"
        ) from err
    state_path = os.path.join(folder, name)
    if not os.path.exists(state_path):
        raise CheckpointError(
            f"checkpoint file {path!r} is corrupt: its state file {name!r} is missing; {hint}"
        )
    saved_fp = meta.get("fingerprint")
    if saved_fp is None:
        warnings.warn(
            f"checkpoint in {folder!r} has no fingerprint (written by an older ceemx): it is "
            "resumed without checking that it belongs to this fit (data, system, method).",
            stacklevel=4,
        )
    elif fingerprint is not None:
        diffs = _describe_mismatch(saved_fp, fingerprint)
        if diffs:
            raise CheckpointError(
                f"checkpoint in {folder!r} was written for a different fit — "
                + "; ".join(diffs)
                + f". Resume it with the same data, system and method, or {hint}"
            )
    digest = meta.get("state_sha256")
    if digest is not None and _sha256_file(state_path) != digest:
        raise CheckpointError(
            f"checkpoint state file {state_path!r} is corrupt: its sha256 does not match the one "
            f"recorded in {path!r}; {hint}"
        )
    try:
        with open(state_path, "rb") as f:
            tree = eqx.tree_deserialise_leaves(f, template, filter_spec=_load_leaf)
    except Exception as err:
        raise CheckpointError(
            f"checkpoint state file {state_path!r} does not fit this fit's state "
            f"({type(err).__name__}: {err}); {hint}"
        ) from err
    bad = _non_finite(tree)
    if bad:
        raise CheckpointError(
            f"checkpoint state file {state_path!r} holds non-finite values (NaN or inf) in "
            f"{', '.join(bad)}; it cannot be resumed; {hint}"
        )
    return tree, history
