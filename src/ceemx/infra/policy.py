"""How ceemx compiles and runs its programs on this machine: the one place that decides.

Call sites state facts — how often a fit runs a program (:class:`Runs`), how its run time grows
with the problem (:class:`Work`) — and ask; this module turns them, with the machine's state, into
the way the program is compiled and run:

- **Which program.** XLA:CPU can compile a program *one-shot* (LLVM -O0, one code-generation
  module: a fraction of the compile time, a few times the run time) or optimised. A program a fit
  runs once or a few times whatever its number of epochs (its start, its checks, a score)
  compiles one-shot while its extra run time stays below the compile time saved; every other
  program compiles optimised. :func:`program` is the decorator, :func:`compiles_one_shot` the
  rule, :data:`ONE_SHOT_MAX_WORK` its bounds. ``CEEMX_ONE_SHOT=0`` compiles every program
  optimised (long batch runs that fit the same small shapes many times).
- **Compiling ahead.** :func:`ceemx.fit` compiles its epoch programs in a background thread
  while it computes the start states only where a core is idle (:func:`compiles_ahead`): on a
  busy machine a second compiling thread only competes with the first.
- **BLAS threads.** Public entry points run with the BLAS libraries at one thread for the call
  (:func:`entry_point`): XLA's CPU LAPACK calls run in OpenBLAS, whose own spinning threads
  otherwise take the cores XLA's threads need.

The mechanisms live beside it: per-program XLA options, the persistent cache and the compile
thread in :mod:`ceemx.infra.compilation`, the scoped BLAS limit in :mod:`ceemx.infra.runtime`.
Programs that run every epoch and need no choice use :func:`ceemx.infra.compilation.jit`
directly. (The LAPACK rule — no two batched LAPACK calls of one program independent of each
other, docs/known_issues.md — is kept in the programs themselves, :func:`ceemx.lib.dense.after`,
and checked in CI by ``.ci/check_lapack_concurrency.py``.)
"""

from __future__ import annotations

import enum
import functools
import os
import time
from collections.abc import Callable, Mapping
from typing import Any, Generic, NamedTuple, ParamSpec, TypeVar, overload

from ceemx.infra.compilation import jit, one_shot_jit, program_options
from ceemx.infra.runtime import blas_threads

_P = ParamSpec("_P")
_T = TypeVar("_T")

__all__ = [
    "ONE_SHOT_MAX_WORK",
    "Program",
    "Runs",
    "Work",
    "compiles_ahead",
    "compiles_one_shot",
    "entry_point",
    "joint_iteration_work",
    "program",
    "schur_work",
    "smoothing_work",
]


class Runs(enum.Enum):
    """How often a fit runs a program at one shape."""

    #: a start, a check, a score, data generation: a few calls whatever the number of epochs
    ONCE = "once"
    #: every epoch (or every call of a loop the user runs)
    EVERY_EPOCH = "every epoch"


class Work(NamedTuple):
    """A program's run time per call in its own unit: ``kind`` names the unit, ``amount`` counts."""

    kind: str
    amount: int


def smoothing_work(B: int, T: int, n: int) -> Work:
    """An LM smoothing pass of B trajectories of T steps and n states: B·T·n²."""
    return Work("smoothing", B * T * n**2)


def schur_work(B: int, T: int, n: int, P: int) -> Work:
    """The Schur complement Σ_b E_bᵀ A_b⁻¹ E_b over P parameters: B·T·n·P² multiply–adds."""
    return Work("schur", B * T * n * P**2)


def joint_iteration_work(B: int, T: int, n: int, P: int) -> Work:
    """The joint (x, θ) Gauss–Newton build over P parameters: B·T·n·(n + P)²."""
    return Work("joint iteration", B * T * n * (n + P) ** 2)


#: Up to which work a program compiles one-shot, by unit and how often it runs (a pair not listed:
#: optimised). Each bound keeps the one-shot program's extra run time below the compile time saved.
ONE_SHOT_MAX_WORK: Mapping[tuple[str, Runs], int] = {
    # an LM iteration costs ≈ 0.5–2 µs per unit: ≈ 0.3 s more at the bound, 1.4–2.5 s compile saved
    ("smoothing", Runs.ONCE): 5 * 10**5,
    # 1.4× the optimised run time at the Figure-3 size, still below the 2.2 s compile saved
    ("schur", Runs.ONCE): 2 * 10**9,
    # every epoch, yet one-shot on tiny problems: it breaks even only after hundreds of epochs
    ("joint iteration", Runs.EVERY_EPOCH): 10**5,
    # not listed: smoothing every epoch (Algorithm 1's E-step), whose extra run time per epoch
    # outweighs the compile time saved once, even on the smallest problems
}


def compiles_one_shot(runs: Runs, work: Work | None = None) -> bool:
    """Whether a program run ``runs`` with ``work`` per call compiles one-shot.

    Without a work measure, a program's run time is negligible beside its compile time: one-shot
    when it runs :attr:`Runs.ONCE`, optimised when it runs every epoch. With one, one-shot up to
    :data:`ONE_SHOT_MAX_WORK` of its unit and ``runs``, optimised above (or when none is listed).
    """
    if work is None:
        return runs is Runs.ONCE
    bound = ONE_SHOT_MAX_WORK.get((work.kind, runs))
    return bound is not None and work.amount <= bound


class Program(Generic[_P, _T]):
    """A ceemx program compiled as :func:`compiles_one_shot` decides for each call's shapes.

    Made by :func:`program`. Both variants exist lazily: only the ones called are traced and
    compiled; they are one object where the two would compile alike (``XLA_FLAGS`` names the
    one-shot options already, as the test suite's does, ``CEEMX_XLA_DEFAULTS=1`` or
    ``CEEMX_ONE_SHOT=0``). ``.lower`` follows the same choice.
    """

    def __init__(
        self,
        fun: Callable[_P, _T],
        runs: Runs,
        work: Callable[..., Work] | None,
        variants: tuple[Any, Any],
    ):
        functools.update_wrapper(self, fun)
        self._fun = fun
        self.runs = runs
        self._work = work
        self._optimised, self._one_shot = variants

    def with_runs(self, runs: Runs) -> Program[_P, _T]:
        """The same program (its compiled variants shared) called ``runs``."""
        return Program(self._fun, runs, self._work, (self._optimised, self._one_shot))

    def compiles_one_shot(self, *args: Any, **kwargs: Any) -> bool:
        """Whether a call with these arguments runs the one-shot variant (shapes only are read)."""
        work = None if self._work is None else self._work(*args, **kwargs)
        return compiles_one_shot(self.runs, work)

    def _pick(self, args: Any, kwargs: Any) -> Any:
        return self._one_shot if self.compiles_one_shot(*args, **kwargs) else self._optimised

    def __call__(self, *args: _P.args, **kwargs: _P.kwargs) -> _T:
        """The program run on these arguments, in the variant the policy picks."""
        return self._pick(args, kwargs)(*args, **kwargs)

    def lower(self, *args: Any, **kwargs: Any) -> Any:
        """Ahead-of-time lowering of the variant a call with these arguments runs."""
        return self._pick(args, kwargs).lower(*args, **kwargs)


@overload
def program(
    fun: Callable[_P, _T],
    /,
    *,
    runs: Runs = ...,
    work: Callable[..., Work] | None = ...,
    **kwargs: Any,
) -> Program[_P, _T]: ...


@overload
def program(
    fun: None = None,
    /,
    *,
    runs: Runs = ...,
    work: Callable[..., Work] | None = ...,
    **kwargs: Any,
) -> Callable[[Callable[_P, _T]], Program[_P, _T]]: ...


def program(
    fun: Callable | None = None,
    /,
    *,
    runs: Runs = Runs.EVERY_EPOCH,
    work: Callable[..., Work] | None = None,
    **kwargs: Any,
) -> Any:
    """A ceemx program that runs ``runs`` at cost ``work`` (a :class:`Program`).

    ``work`` maps the call's arguments to the program's :class:`Work` (shapes only: it must not
    read array values); ``None`` for programs whose run time is small beside their compile time
    at any size. The other keywords are :func:`ceemx.infra.compilation.jit`'s. Usable bare or
    as ``@program(runs=Runs.ONCE)``.
    """
    if fun is None:
        return functools.partial(program, runs=runs, work=work, **kwargs)
    optimised = jit(fun, **kwargs)
    if program_options(one_shot=True) == program_options():
        return Program(fun, runs, work, (optimised, optimised))
    return Program(fun, runs, work, (optimised, one_shot_jit(fun, **kwargs)))


def compiles_ahead() -> bool:
    """Whether a fit compiles its epoch programs in a background thread: an idle core exists.

    True when the process may run on ≥ 2 CPUs and fewer tasks than those CPUs are runnable now,
    this one included — Linux's instantaneous count of runnable tasks (``/proc/loadavg``, the
    median of five readings 2 ms apart); elsewhere, when the 1-minute load average leaves one CPU
    idle (load ≤ CPUs − 1.5). The load average lags by a minute, so it is the fallback only.
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


def entry_point(fun: Callable[_P, _T]) -> Callable[_P, _T]:
    """``fun`` (a public entry point) run with the BLAS libraries at one thread, results ready.

    :func:`ceemx.infra.runtime.blas_threads` for the call (``CEEMX_BLAS_THREADS=N`` chooses
    another N, ``0`` leaves the libraries alone); its array results are waited for inside.
    """

    @functools.wraps(fun)
    def wrapped(*args: _P.args, **kwargs: _P.kwargs) -> _T:
        import jax

        with blas_threads():
            return jax.block_until_ready(fun(*args, **kwargs))

    return wrapped
