"""JAX's persistent compilation cache for ceemx programs (opt-in for the library, on in the CLI).

Compilation is most of what a user waits for on small problems: a first fit of a two-state
gray-box model compiles the smoother, the learner and the initial-state estimation (seconds each),
and a new Python process compiles them all again. JAX can keep compiled executables on disk and
reload them in later processes when the program, the shapes and the XLA flags are the same.

The library never changes global JAX configuration on import; :func:`enable_compilation_cache` is
called by the ``ceemx`` command and the examples, and by users who want it. The folder is, in
order: the ``path`` argument, the ``CEEMX_COMPILATION_CACHE`` environment variable, or
``~/.cache/ceemx/jax`` (``$XDG_CACHE_HOME/ceemx/jax``). Setting the variable to ``0``, ``off`` or
``none`` turns the cache off. Entries are keyed by JAX on the program and its compile options; a
JAX or jaxlib upgrade simply misses. The cache grows without bound: delete the folder to reclaim
space.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = ["default_cache_dir", "enable_compilation_cache"]

_OFF = ("0", "off", "none", "false", "no")


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/ceemx/jax`` or ``~/.cache/ceemx/jax``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ceemx" / "jax"


def enable_compilation_cache(
    path: str | os.PathLike | None = None, *, min_compile_time_s: float = 0.2
) -> Path | None:
    """Turn on JAX's persistent compilation cache (see the module notes for the folder).

    Args:
        path: the cache folder (``None``: ``CEEMX_COMPILATION_CACHE`` or :func:`default_cache_dir`).
        min_compile_time_s: programs that compiled faster than this are not written (JAX's
            ``jax_persistent_cache_min_compile_time_secs``).

    Returns:
        The folder in use, or ``None`` when the environment turned the cache off.

    Raises:
        ValueError: a negative or non-finite ``min_compile_time_s``.
    """
    if not (min_compile_time_s >= 0 and min_compile_time_s != float("inf")):
        raise ValueError(f"`min_compile_time_s` must be finite and >= 0; got {min_compile_time_s}.")
    if path is None:
        env = os.environ.get("CEEMX_COMPILATION_CACHE")
        if env is not None and env.strip().lower() in _OFF:
            return None
        path = env if env else default_cache_dir()
    folder = Path(path).expanduser()
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder
