"""Atomic checkpoints of a fit: arrays via Equinox serialisation, history as JSON.

Layout of a checkpoint folder: ``state-<epoch>.eqx`` (the leaves of the fit state) and
``latest.json`` (the epoch, the state file's name and the history). Each file is written to a
temporary name and moved into place with ``os.replace`` (atomic on POSIX); ``latest.json`` is
replaced last, so a run killed at any instant leaves either the previous or the new checkpoint,
never a torn one.
"""

from __future__ import annotations

import json
import os
import tempfile

import equinox as eqx

__all__ = ["load", "save"]

_LATEST = "latest.json"


def _atomic_write(path: str, write) -> None:
    folder = os.path.dirname(path) or "."
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def save(folder: str, tree, history: list[dict]) -> None:
    """Write the fit state ``tree`` (a pytree of arrays) and ``history`` to ``folder``."""
    os.makedirs(folder, exist_ok=True)
    epoch = len(history)
    name = f"state-{epoch}.eqx"
    _atomic_write(os.path.join(folder, name), lambda f: eqx.tree_serialise_leaves(f, tree))
    meta = {"epoch": epoch, "state": name, "history": history}
    text = json.dumps(meta, default=_to_builtin)
    _atomic_write(os.path.join(folder, _LATEST), lambda f: f.write(text.encode()))
    for other in os.listdir(folder):
        # Older states, and temporaries of a write that was killed half-way.
        if (other.startswith("state-") and other != name) or other.startswith(".tmp-"):
            os.remove(os.path.join(folder, other))


def _to_builtin(value):
    """JSON fallback for NumPy/JAX scalars and arrays that callbacks may put in the history."""
    import numpy as np

    arr = np.asarray(value)
    return arr.item() if arr.ndim == 0 else arr.tolist()


def load(folder: str, template):
    """(tree, history) from ``folder``'s latest checkpoint, or ``None`` when there is none.

    ``template`` is a pytree with the structure, shapes and dtypes of the saved state.
    """
    path = os.path.join(folder, _LATEST)
    if not os.path.exists(path):
        return None
    with open(path) as f:
        meta = json.load(f)
    with open(os.path.join(folder, meta["state"]), "rb") as f:
        tree = eqx.tree_deserialise_leaves(f, template)
    return tree, meta["history"]
