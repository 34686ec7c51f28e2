"""How ceemx programs are compiled: per-program XLA options, the persistent cache, a compile thread.

:func:`jit` is the decorator of ceemx's compiled entry points: ``eqx.filter_jit`` with the
library's XLA options per program (nothing global changes). Which programs compile *one-shot*
(:func:`one_shot_jit`) is decided by :mod:`ceemx.infra.policy`.

JAX's persistent compilation cache is opt-in for the library and on in the CLI: a first fit of a
small model is mostly compilation, and a new Python process compiles everything again. JAX keeps
compiled executables on disk and reloads them in later processes when the program, the shapes
and the XLA flags are the same. :func:`enable_compilation_cache` is called by the ``ceemx``
command and the examples, and by users who want it. The folder is, in order: the ``path``
argument, the ``CEEMX_COMPILATION_CACHE`` environment variable, or ``~/.cache/ceemx/jax``
(``$XDG_CACHE_HOME/ceemx/jax``). Setting the variable to ``0``, ``off`` or ``none`` turns the
cache off. Entries are keyed by JAX on the program and its compile options; a JAX or jaxlib
upgrade simply misses. The cache grows without bound: delete the folder to reclaim space.

:func:`compile_in_background` compiles programs in a worker thread (XLA releases the interpreter
lock while it compiles) and the caller's ``join()`` compiles the jobs the worker has not started.
XLA:CPU already spreads one large program's code generation over the cores, so the gain is the
main thread's idle time, not a second core.
"""

from __future__ import annotations

import collections
import functools
import os
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ParamSpec, TypeVar, cast, overload

import equinox as eqx
import jax
from jax.core import Tracer

from ceemx.infra.options import check_nonnegative, check_path

try:  # no public query of JAX's trace state; the arguments' tracers tell where it is absent
    from jax._src.core import trace_state_clean as _trace_state_clean
except ImportError:  # pragma: no cover
    _trace_state_clean = None

_P = ParamSpec("_P")
_T = TypeVar("_T")

__all__ = [
    "BackgroundCompile",
    "FAST_COMPILE_FLAGS",
    "ONE_SHOT_COMPILE_FLAGS",
    "OPTIMISED_COMPILE_FLAGS",
    "compile_in_background",
    "default_cache_dir",
    "enable_compilation_cache",
    "jit",
    "one_shot_jit",
    "program_options",
    "use_fast_compilation",
]

#: XLA:CPU options of every ceemx program (and :func:`use_fast_compilation`'s): the classic
#: (non-MLIR) fusion emitters, about half the compile time for the same HLO optimisations.
FAST_COMPILE_FLAGS = {"xla_cpu_use_fusion_emitters": "false"}

#: XLA:CPU options added to one-shot programs (:mod:`ceemx.infra.policy` says which): LLVM at -O0
#: and one code-generation module — the same HLO optimisations, unoptimised machine code, which
#: compiles several times faster and runs a few times slower.
ONE_SHOT_COMPILE_FLAGS = {
    "xla_backend_optimization_level": "0",
    "xla_cpu_parallel_codegen_split_count": "1",
}

#: XLA:CPU options of every other (optimised) program: LLVM at -O1 instead of XLA's -O2, which
#: compiles faster; the heavy arithmetic runs in library kernels the LLVM level does not touch,
#: so the programs run as fast with bitwise-equal outputs.
OPTIMISED_COMPILE_FLAGS = {"xla_backend_optimization_level": "1"}

_OFF = ("0", "off", "none", "false", "no")


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/ceemx/jax`` or ``~/.cache/ceemx/jax``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ceemx" / "jax"


def enable_compilation_cache(
    path: str | os.PathLike | None = None, *, min_compile_time_s: float = 0.0
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
        TypeError: a ``min_compile_time_s`` that is not a number, a ``path`` that is not one.
    """
    check_nonnegative("min_compile_time_s", min_compile_time_s)
    path = check_path("path", path, none=True)
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


class BackgroundCompile:
    """Compile jobs run by a daemon thread; :meth:`join` runs what it has not started yet.

    Returned by :func:`compile_in_background`. The worker takes the jobs in order; a thread
    that calls :meth:`join` takes the jobs still waiting and runs them itself, then waits for
    the worker's current one — so a caller whose own work ended before the worker's does not
    sit idle while a second program waits for its turn (the demo: JointLM's identifiability
    program compiled beside the joint iteration instead of after it).
    """

    def __init__(self, jobs: Sequence[Callable[[], object]], name: str = "ceemx-compile"):
        self._jobs = collections.deque(jobs)
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._drain, name=name, daemon=True)
        self._thread.start()

    def _next(self) -> Callable[[], object] | None:
        with self._lock:
            return self._jobs.popleft() if self._jobs else None

    def _drain(self) -> None:
        while (job := self._next()) is not None:
            try:
                job()
            except Exception:  # noqa: BLE001 — the real call compiles and raises it
                pass

    def join(self, timeout: float | None = None) -> None:
        """Run the jobs not yet started in this thread, then wait for the worker."""
        self._drain()
        self._thread.join(timeout)

    def is_alive(self) -> bool:
        """Whether the worker is still compiling."""
        return self._thread.is_alive()


def compile_in_background(
    work: Callable[[], object] | Sequence[Callable[[], object]], name: str = "ceemx-compile"
) -> BackgroundCompile:
    """Run compile jobs (ahead-of-time ``lower(...).compile()`` calls) in a daemon thread; started.

    ``work`` is one job or a sequence of them, taken in order (largest first: a caller that
    ``join()``s early takes the later ones; :class:`BackgroundCompile`). A compiled program
    lands in JAX's in-memory caches, so the later call with arguments of the same shapes,
    dtypes (weak types included) and static parts runs it without compiling again; a call with
    other arguments compiles as usual. A job must only lower and compile, never execute:
    programs running concurrently can contend for the LAPACK thread pool. Any exception in a
    job is dropped (the later call compiles and reports it). ``join()`` before the calls it
    prepares: two threads compiling the same program both pay for it.
    """
    jobs = [work] if callable(work) else list(work)
    return BackgroundCompile(jobs, name)


def use_fast_compilation() -> bool:
    """Add :data:`FAST_COMPILE_FLAGS` to this process's ``XLA_FLAGS`` (before JAX starts).

    Process-local: it edits the environment variable XLA reads when its CPU backend starts, so it
    works only before JAX's first computation (the ``ceemx`` command calls it first thing) and
    is inherited by subprocesses. A flag ``XLA_FLAGS`` already names is left as it is;
    ``CEEMX_XLA_DEFAULTS=1`` keeps XLA's defaults.

    Returns:
        Whether the flags are in effect: ``False`` when JAX had already started (nothing is
        changed then) or ``CEEMX_XLA_DEFAULTS=1``.
    """
    add = _flags_to_add(FAST_COMPILE_FLAGS)
    if add is None or _backend_started():
        return False
    extra = [f"--{k}={v}" for k, v in add.items()]
    os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *extra]).strip()
    return True


def _flags_to_add(flags: dict[str, str]) -> dict[str, str] | None:
    """``flags`` that ``XLA_FLAGS`` does not name (``None``: ``CEEMX_XLA_DEFAULTS=1``, none)."""
    if os.environ.get("CEEMX_XLA_DEFAULTS", "").strip() == "1":
        return None
    named = os.environ.get("XLA_FLAGS", "")
    return {k: v for k, v in flags.items() if f"--{k}=" not in named}


def program_options(one_shot: bool = False) -> dict[str, Any]:
    """The XLA options every ceemx entry point compiles with (:func:`jit`), from the environment.

    :data:`FAST_COMPILE_FLAGS` as per-program options, so that a library user's programs compile
    as fast as the ``ceemx`` command's without any process-wide setting; with ``one_shot``,
    :data:`ONE_SHOT_COMPILE_FLAGS` (unless ``CEEMX_ONE_SHOT=0``: every program optimised), else
    :data:`OPTIMISED_COMPILE_FLAGS`. None that ``XLA_FLAGS`` sets already (the user's choice
    wins), none at all with ``CEEMX_XLA_DEFAULTS=1``. Read when a ceemx module is imported.
    """
    one_shot = one_shot and os.environ.get("CEEMX_ONE_SHOT", "").strip().lower() not in _OFF
    tier = ONE_SHOT_COMPILE_FLAGS if one_shot else OPTIMISED_COMPILE_FLAGS
    add = _flags_to_add({**FAST_COMPILE_FLAGS, **tier})
    return {} if add is None else {k: _option_value(v) for k, v in add.items()}


def _option_value(text: str) -> bool | int | str:
    """An ``XLA_FLAGS`` value as the compiler option's Python value."""
    if text in ("true", "false"):
        return text == "true"
    return int(text) if text.isdigit() else text


@overload
def jit(fun: Callable[_P, _T], /, **kwargs: Any) -> Callable[_P, _T]: ...


@overload
def jit(fun: None = None, /, **kwargs: Any) -> Callable[[Callable[_P, _T]], Callable[_P, _T]]: ...


def jit(fun: Callable | None = None, /, **kwargs: Any) -> Any:
    """``eqx.filter_jit`` with :func:`program_options` as the program's XLA ``compiler_options``.

    The decorator of ceemx's compiled entry points (optimised programs). The options are per
    program (JAX's ``jit(compiler_options=...)``): nothing global changes, and programs a user
    compiles themselves keep XLA's defaults. A ceemx function called inside a user's own
    ``jax.jit`` is inlined into it and compiles with the user's options (JAX refuses compiler
    options on a nested jit). Usable bare (``@jit``) or with ``eqx.filter_jit``'s keywords
    (``@jit(donate="all")``); ``.lower(...)`` compiles ahead of time with the options.
    """
    if fun is None:
        return functools.partial(jit, **kwargs)
    return _with_options(fun, program_options(), kwargs)


def one_shot_jit(fun: Callable[_P, _T], /, **kwargs: Any) -> Callable[_P, _T]:
    """:func:`jit` with :data:`ONE_SHOT_COMPILE_FLAGS` too (:func:`ceemx.infra.policy.program`)."""
    return _with_options(fun, program_options(one_shot=True), kwargs)


def _with_options(fun: Callable, options: dict[str, Any], kwargs: dict[str, Any]) -> Any:
    plain = eqx.filter_jit(fun, **kwargs)
    if not options:
        return plain
    top = cast(Any, eqx.filter_jit)(fun, compiler_options=options, **kwargs)  # a jax.jit keyword

    # JAX accepts compiler options on top-level programs only: called inside another trace (a
    # ceemx program calling another, or a user's jit), the function is the plain one, inlined.
    @functools.wraps(fun)
    def call(*args: Any, **kw: Any) -> Any:
        return (plain if _tracing(args, kw) else top)(*args, **kw)

    call.lower = top.lower  # type: ignore[attr-defined]  # ahead-of-time compilation (precompile)
    return call


def _tracing(args: Any, kwargs: Any) -> bool:
    """Whether a call happens inside a JAX transformation (jit, vmap, grad, ...)."""
    if _trace_state_clean is not None:
        return not _trace_state_clean()
    return any(isinstance(leaf, Tracer) for leaf in jax.tree.leaves((args, kwargs)))


def _backend_started() -> bool:
    """Whether JAX's backends exist already (no public query; False when unknown)."""
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return False
