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

:func:`compile_in_background` compiles programs in a worker thread: :func:`ceemx.fit` compiles
the solver's epoch programs there while the main thread computes the start states (XLA releases
the interpreter lock while it compiles), and the main thread's ``join()`` compiles the jobs the
worker has not started. XLA:CPU already spreads one large program's code generation over the
cores (the demo's joint iteration: 6.1 s of CPU in 3.5 s,
``benchmarks/probes/joint_iteration_parts.py``), so the gain is the main thread's idle time,
not a second core.
"""

from __future__ import annotations

import collections
import functools
import os
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ParamSpec, TypeVar, cast, overload

import equinox as eqx
import jax
from jax.core import Tracer

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
    "has_idle_core",
    "enable_compilation_cache",
    "jit",
    "jit_variants",
    "one_shot_when",
    "program_options",
    "use_fast_compilation",
]

#: XLA:CPU options that :func:`use_fast_compilation` adds: the classic (non-MLIR) fusion emitters,
#: which compile ceemx's programs in about half the CPU time (benchmarks/README.md, "First-fit
#: latency"); the same HLO optimisations and LLVM -O2 run either way.
FAST_COMPILE_FLAGS = {"xla_cpu_use_fusion_emitters": "false"}

#: XLA:CPU options added to the programs a fit runs once or a few times — its setup and its checks
#: (``jit(..., one_shot=True)``): LLVM at -O0 and one code-generation module. The same HLO
#: optimisations run; the machine code is not optimised, which compiled ceemx's programs 1.7–10×
#: faster and ran them 1.2–3.3× slower (benchmarks/README.md, "One-shot programs") — a gain
#: wherever the program's run time is small beside its compile time.
ONE_SHOT_COMPILE_FLAGS = {
    "xla_backend_optimization_level": "0",
    "xla_cpu_parallel_codegen_split_count": "1",
}

#: XLA:CPU options of every other (optimised) program: LLVM at -O1 instead of XLA's -O2. The
#: heavy arithmetic runs in library kernels (dot, Cholesky), which the LLVM level does not touch;
#: the fused loops ran as fast: the Figure-3 joint iteration compiled in 5.7–5.8 instead of
#: 8.0–8.1 s and ran 0.98–0.99× the time, the single-Lorenz smoother 2.6 against 3.1 s and
#: 1.03–1.05× the time, Algorithm 1's Figure-3 epoch 0.62 against 0.64 s; outputs bitwise
#: equal (benchmarks/README.md, "LLVM -O1").
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


def has_idle_core() -> bool:
    """Whether this process may use a core nobody else is using (for compiling in background).

    True when the process may run on ≥ 2 CPUs and fewer tasks than those CPUs are runnable now,
    this one included — Linux's instantaneous count of runnable tasks (``/proc/loadavg``, the
    median of five readings 2 ms apart); elsewhere, when the 1-minute load average leaves one CPU
    idle (load ≤ CPUs − 1.5). The load average lags by a minute: right after another process
    finished (back-to-back runs, a test or benchmark just before) it still reads ≈ 1.5 on an idle
    2-core machine, and the background compile was never used there (it takes the first JointLM
    fit 10.9–11.2 → 9.7–9.9 s; benchmarks/README.md "One program per configuration"). On a
    busy machine a second compiling thread only competes with the main thread (measured: the
    suite's JointLM test files 4–5 % more CPU, single core 1.07× slower wall), so
    :func:`ceemx.fit` compiles in the foreground there.
    """
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    if cpus < 2:
        return False
    running = _runnable_tasks()
    if running is not None:
        return running < cpus
    try:
        load = os.getloadavg()[0]
    except OSError:
        return False
    return load <= cpus - 1.5


def _runnable_tasks(samples: int = 5) -> int | None:
    """The median number of runnable tasks on the machine now (``None`` where unknown)."""
    counts = []
    for i in range(samples):
        try:
            with open("/proc/loadavg") as f:
                counts.append(int(f.read().split()[3].split("/")[0]))
        except (OSError, ValueError, IndexError):
            return None
        if i + 1 < samples:
            time.sleep(0.002)
    return sorted(counts)[len(counts) // 2]


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
    :data:`ONE_SHOT_COMPILE_FLAGS` too (unless ``CEEMX_ONE_SHOT=0``: every program optimised, for
    long batch runs that fit the same small shapes many times). None that ``XLA_FLAGS`` sets
    already (the user's choice wins), none at all with ``CEEMX_XLA_DEFAULTS=1``. Read when a
    ceemx module is imported.
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


def jit(fun: Callable | None = None, /, *, one_shot: bool = False, **kwargs: Any) -> Any:
    """``eqx.filter_jit`` with :func:`program_options` as the program's XLA ``compiler_options``.

    The decorator of ceemx's compiled entry points. The options are per program (JAX's
    ``jit(compiler_options=...)``): nothing global changes, and programs a user compiles
    themselves keep XLA's defaults. A ceemx function called inside a user's own ``jax.jit`` is
    inlined into it and compiles with the user's options (JAX refuses compiler options on a
    nested jit). Usable bare (``@jit``) or with ``eqx.filter_jit``'s keywords
    (``@jit(donate="all")``); ``.lower(...)`` compiles ahead of time with the options.
    ``one_shot=True`` marks a program a fit runs once or a few times whatever the number of
    epochs (setup, checks): it compiles with :data:`ONE_SHOT_COMPILE_FLAGS` too.
    """
    if fun is None:
        return functools.partial(jit, one_shot=one_shot, **kwargs)
    plain = eqx.filter_jit(fun, **kwargs)
    options = program_options(one_shot)
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


def jit_variants(fun: Callable, **kwargs: Any) -> tuple[Any, Any]:
    """``(optimised, one-shot)``: ``fun`` compiled by :func:`jit` without and with ``one_shot``.

    One and the same object when the two would compile alike (``XLA_FLAGS`` names the one-shot
    options already, as the test suite's does, or ``CEEMX_XLA_DEFAULTS=1``): a program is then
    traced and compiled once for both uses.
    """
    optimised = jit(fun, **kwargs)
    if program_options(True) == program_options(False):
        return optimised, optimised
    return optimised, jit(fun, one_shot=True, **kwargs)


def one_shot_when(small: Callable[..., bool], **kwargs: Any) -> Callable[[Callable], Any]:
    """:func:`jit` as a one-shot program when ``small(*args, **kw)``, optimised otherwise.

    For programs that run once or twice per fit but whose run time grows with the problem (the
    Schur complement of the identifiability check, say): on small problems the unoptimised
    machine code's extra run time is far below the compile time it saves, on large ones not.
    ``small`` sees the call's arguments (shapes only: it must not read array values). Both
    programs exist lazily: only the variants called are compiled; ``.lower`` follows the same
    choice.
    """

    def wrap(fun: Callable) -> Any:
        optimised, one_shot = jit_variants(fun, **kwargs)

        def pick(args: Any, kw: Any) -> Any:
            return one_shot if small(*args, **kw) else optimised

        @functools.wraps(fun)
        def call(*args: Any, **kw: Any) -> Any:
            return pick(args, kw)(*args, **kw)

        call.lower = lambda *args, **kw: pick(args, kw).lower(*args, **kw)  # type: ignore[attr-defined]
        return call

    return wrap


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
