"""Real write faults under checkpoints: a file-size limit and a full file system.

Run as ``python tests/checkpoint_faults.py FOLDER [SMALL_FS]`` (by tests/test_checkpoint_safety.py,
in a subprocess: the limit is the process's own). Prints one JSON object: per scenario the
error message, the files left in the folder and the epochs the folder then resumes.

- ``RLIMIT_FSIZE`` (SIGXFSZ ignored, so a write past the limit returns what fit and the next
  fails with EFBIG): the state file cut at the second save (``second``) and at the first
  (``first``), ``latest.json`` cut after its state file was written (``latest``), and the
  start-of-fit probe of the folder (``probe``).
- ``SMALL_FS``: a small file system (a 64 kB tmpfs) holding one checkpoint, then filled to
  within 4 kB by another file, so the next save's state file is written in part and the disk
  is full (``disk``).
"""

from __future__ import annotations

import json
import os
import resource
import signal
import sys
from contextlib import contextmanager

signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

from ceemx.identification.solvers import FitState  # noqa: E402
from ceemx.infra import checkpoint as ckpt  # noqa: E402
from ceemx.lib.results import RESULTS, select  # noqa: E402

FINGERPRINT = {"method": "a fault test's fit state"}


def state(T: int = 400) -> FitState:
    """A fit state whose file is about 16·T bytes (6.9 kB at T = 400)."""
    return FitState(
        theta=jnp.zeros(3),
        states=jnp.zeros((2, T, 1)),
        J=jnp.zeros(2),
        weights=jnp.ones(2),
        status=select(jnp.zeros(2, bool), RESULTS.nonfinite, RESULTS.successful),
        solver_state=jnp.asarray(1e-3),
    )


@contextmanager
def file_size_limit(nbytes: int):
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


def outcome(folder: str, save, T: int = 400) -> dict:
    try:
        save()
        error = None
    except Exception as err:  # noqa: BLE001 - reported
        error = f"{type(err).__name__}: {err}"
    files = sorted(os.listdir(folder))
    loaded = ckpt.load(folder, state(T), fingerprint=FINGERPRINT)
    return {"error": error, "files": files, "epochs": None if loaded is None else len(loaded[1])}


def limited(base: str) -> dict:
    out = {}
    one, two = [{"epoch": 1}], [{"epoch": 1}, {"epoch": 2}]
    long = [{"epoch": i, "note": "x" * 100} for i in range(1, 201)]  # latest.json ≈ 22 kB
    for name, limit, first, history in [
        ("second", 3000, one, two),
        ("first", 3000, None, one),
        ("latest", 8000, one, long),
    ]:
        folder = os.path.join(base, name)
        os.makedirs(folder)
        if first is not None:
            ckpt.save(folder, state(), first, FINGERPRINT)

        def save(folder=folder, limit=limit, history=history):
            with file_size_limit(limit):
                ckpt.save(folder, state(), history, FINGERPRINT)

        out[name] = outcome(folder, save)
    folder = os.path.join(base, "probe")
    with file_size_limit(2):
        try:
            ckpt.check_folder(folder)
            error = None
        except Exception as err:  # noqa: BLE001 - reported
            error = f"{type(err).__name__}: {err}"
    out["probe"] = {"error": error, "files": sorted(os.listdir(folder)), "epochs": None}
    return out


def full_disk(disk: str) -> dict:
    folder = os.path.join(disk, "ckpt")
    T = 1500  # a 24 kB state file
    ckpt.save(folder, state(T), [{"epoch": 1}], FINGERPRINT)
    fs = os.statvfs(disk)
    filler = os.path.join(disk, "filler")
    with open(filler, "wb") as f:
        f.write(b"\0" * max(0, fs.f_bavail * fs.f_frsize - 4096))
    try:
        ckpt.save(folder, state(T), [{"epoch": 1}, {"epoch": 2}], FINGERPRINT)
        error = None
    except Exception as err:  # noqa: BLE001 - reported
        error = f"{type(err).__name__}: {err}"
    files = sorted(os.listdir(folder))
    os.remove(filler)  # space again: the folder resumes, and takes the next save
    loaded = ckpt.load(folder, state(T), fingerprint=FINGERPRINT)
    ckpt.save(folder, state(T), [{"epoch": 1}, {"epoch": 2}], FINGERPRINT)
    after = ckpt.load(folder, state(T), fingerprint=FINGERPRINT)
    return {
        "error": error,
        "files": files,
        "epochs": None if loaded is None else len(loaded[1]),
        "epochs_after": None if after is None else len(after[1]),
    }


if __name__ == "__main__":
    result = limited(sys.argv[1])
    if len(sys.argv) > 2:
        result["disk"] = full_disk(sys.argv[2])
    print(json.dumps(result))
