"""Output folders, checked before any compute.

A light module (no JAX): the command line checks its ``--out`` with it at once.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["output_dir"]


def output_dir(out: str | os.PathLike | None, default: str | os.PathLike) -> Path:
    """The folder ``out`` (``default`` when ``None``), created if missing and checked writable.

    Raises:
        OSError: the folder cannot be created, or a file cannot be created in it (checked with a
            probe file that is removed at once, so that a run fails before any compute).
    """
    path = Path(default if out is None else out)
    path.mkdir(parents=True, exist_ok=True)
    fd, probe = tempfile.mkstemp(dir=path, prefix=".ceemx-probe.", suffix=".tmp")
    os.close(fd)
    os.unlink(probe)
    return path
