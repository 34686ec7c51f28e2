"""The ``ceemx`` command: ``ceemx fit``, ``ceemx demo``, ``ceemx experiment NAME``, ``--version``.

Examples::

    ceemx fit tank.py:Tank run1.csv run2.csv --inputs u --outputs y --dt 4 --start k=0.5
                                               # your model on your records (ceemx.fit_command)

    ceemx demo                                 # six coupled Lorenz attractors, < 2 min on a laptop
    ceemx experiment table1                    # paper Table 1, both weightings, 10 seeds
    ceemx experiment figure3 --method alternate --max-epochs 50
    ceemx experiment figure3 --seeds 2         # the first two seeds of figure3's: 42, 43
    ceemx experiment table1 --seeds 3,7        # exactly seeds 3 and 7
    ceemx experiment table1 --smoke            # seconds; what the tests run
    ceemx experiment figure2                   # CE-EM vs Particle EM, 10 seeds
    ceemx experiment calibration               # learned noise + 95 % coverage, 100 seeds
    ceemx experiment figure3 --method particle # Particle EM on six coupled Lorenz
    ceemx experiment figure4                   # helicopter-like study: naive, LSTM, H25, SID, NL
    ceemx experiment figure4 --dataset silverbox  # the same five models on a real record
    ceemx experiment real_data --dataset silverbox  # gray-box, hybrid, linear on a real dataset

``--threads N`` (or ``CEEMX_THREADS=N``) runs JAX's CPU runtime on N CPUs: on a machine whose
cores are busy with other work, ``--threads 1`` can be several times faster than the default of
all cores (:mod:`ceemx.infra.runtime`).

Compilation: the command compiles with XLA:CPU's classic emitters
(:func:`ceemx.infra.compilation.use_fast_compilation`; ``CEEMX_XLA_DEFAULTS=1`` keeps XLA's
defaults) and keeps compiled programs in the persistent cache (``CEEMX_COMPILATION_CACHE=0``
turns it off).

``--seeds N`` runs the first N seeds of the experiment's seed sequence (table1: 0, 1, 2, …;
figure2: 43, 44, …; figure3: 42, 43, …); a comma list (``--seeds 42,44``, or ``--seeds 42,``
for one seed) runs exactly those seeds.

Interrupts and errors: Ctrl-C (SIGINT) at any point after the command starts prints the one line
``ceemx: interrupted`` on stderr and exits with status 130, without a traceback and without
writing any result file (results are held in memory and written, atomically and ``results.json``
last, only when the run has finished); SIGTERM (``kill``, a batch scheduler's stop) the same, with
``ceemx: terminated`` and status 143. Either removes the ``--out`` folder if this run created it
and nothing was written to it. A usage error (unknown option, ``--seeds 0``, an ``--out``
folder that cannot be written, ``--max-epochs -3``, a ``--data`` folder that is not there, an
option the experiment does not take) prints one line and exits with status 2 before any compute.
Each command and each experiment has its own parser: ``ceemx experiment table1 --help`` lists
the options table1 takes, and an option it does not take is refused by name. ``ceemx fit``
refuses the same way a record or column that is not there, a model file that does not import
and a model or fit that refuses its values (:mod:`ceemx.fit_command`).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NoReturn

from ceemx import fit_command
from ceemx.experiment_command import add_experiment, experiment_kwargs, positive_int
from ceemx.infra.interrupts import EXIT_INTERRUPTED, INTERRUPTED, Interrupts, missing_folders

__all__ = ["main"]


def _version() -> str:
    from ceemx import __version__

    return __version__


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr and exit status 2."""

    def error(self, message: str) -> NoReturn:  # type: ignore[override]
        message = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


# Parsing and checking the arguments imports neither JAX nor equinox: ``ceemx --help`` and every
# usage error answer at once (importing them takes seconds). What the checks need lives in light
# modules: ``METHODS`` and ``parse_seeds`` in :mod:`ceemx.experiments`, ``output_dir`` in
# :mod:`ceemx.infra.paths` (tests/test_cli_reliability.py checks that a usage error leaves JAX
# unimported).


def _add_demo(sub, methods: Sequence[str]) -> None:
    """The ``demo`` command and its options."""
    demo = sub.add_parser(
        "demo", help="identify six coupled Lorenz attractors; writes a figure and tables"
    )
    demo.add_argument("--smoke", action="store_true", help="tiny, fast version (for tests)")
    demo.add_argument("--out", default="ceemx-demo", help="output folder (default: ./ceemx-demo)")
    demo.add_argument("--method", choices=methods, default=None, help="default: joint")
    demo.add_argument(
        "--max-epochs", type=positive_int, default=None, metavar="N", help="bound on iterations"
    )
    demo.set_defaults(command_parser=demo)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for documentation and tests)."""
    from ceemx.experiments import EXPERIMENTS, METHODS  # a light module (no JAX)

    parser = _Parser(
        prog="ceemx",
        description="Certainty-equivalent EM system identification in JAX.",
    )
    parser.add_argument("--version", action="version", version=f"ceemx {_version()}")
    parser.add_argument(
        "--threads",
        type=positive_int,
        default=None,
        metavar="N",
        help="CPU threads for JAX (default: CEEMX_THREADS, else all cores); 1 is often faster "
        "on a machine busy with other work",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_demo(sub, METHODS)
    add_experiment(sub, EXPERIMENTS)
    fit_command.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None, *, handle_sigint: bool | None = None) -> int:
    """Entry point of the ``ceemx`` console script (and ``python -m ceemx``).

    Args:
        argv: the arguments (``None``: ``sys.argv[1:]``).
        handle_sigint: take over SIGINT and SIGTERM (one line on stderr, ``os._exit(130)`` or
            ``os._exit(143)``; see the module notes). ``None``: when ``argv`` is ``None`` (run
            as a program) in the main thread; a caller in the same process (tests, a notebook)
            gets ``KeyboardInterrupt`` caught instead: one line and the return value 130.

    Returns:
        The exit status: 0 done, 1 the results could not be written, 2 usage error, 130
        interrupted. Usage errors raise ``SystemExit(2)`` (argparse's convention). With the
        signals taken over, the process exits at once: 130 on SIGINT, 143 on SIGTERM.
    """
    if handle_sigint is None:
        handle_sigint = argv is None
    handle_sigint = handle_sigint and threading.current_thread() is threading.main_thread()
    interrupts = Interrupts()
    if handle_sigint:
        interrupts.install()
    try:
        return _main(argv, interrupts)
    except KeyboardInterrupt:
        interrupts.remove_created()
        sys.stderr.write(INTERRUPTED.decode())
        sys.stderr.flush()
        return EXIT_INTERRUPTED
    finally:
        if handle_sigint:
            interrupts.uninstall()


def _check_out(parser: argparse.ArgumentParser, out: str | None, default: str) -> None:
    from ceemx.infra.paths import output_dir

    try:
        output_dir(out, default)
    except OSError as e:
        where = out if out is not None else default
        parser.error(f"--out {where}: cannot write there ({e.strerror or e})")


def _default_out(args: argparse.Namespace) -> str:
    """The output folder a command writes to when ``--out`` is not given."""
    if args.command == "demo":
        return "ceemx-demo"
    if args.command == "fit":
        return "ceemx-fit"
    default = f"results/{args.name}"
    if args.name == "figure4" and args.dataset is not None:
        default += f"-{args.dataset}"
    return default


def _thread_count(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int | None:
    """``--threads``, else ``CEEMX_THREADS`` (a bad value is a usage error), else ``None``."""
    threads = args.threads
    if threads is None and os.environ.get("CEEMX_THREADS", "").strip():
        try:
            threads = positive_int(os.environ["CEEMX_THREADS"].strip())
        except argparse.ArgumentTypeError as e:
            parser.error(f"CEEMX_THREADS: {e}")
    return threads


def _limit_threads(threads: int | None) -> None:
    """Size JAX's CPU thread pool to ``threads`` CPUs (before JAX starts; ``None``: all)."""
    if threads is not None:
        from ceemx.infra.runtime import limit_cpu_threads  # imports JAX, does not start it

        limit_cpu_threads(threads)  # before JAX starts: XLA sizes its thread pool then


def _start_jax() -> None:
    """Faster XLA compilation, float64 and the persistent compilation cache."""
    from ceemx.infra.compilation import use_fast_compilation

    # Before JAX starts: the classic XLA:CPU emitters compile in about half the CPU time, same
    # steady state (CEEMX_XLA_DEFAULTS=1 or an XLA_FLAGS that sets the flag keeps XLA's choice).
    use_fast_compilation()
    import jax

    jax.config.update("jax_enable_x64", True)
    from ceemx.infra.compilation import enable_compilation_cache

    # Compiled programs persist across runs (CEEMX_COMPILATION_CACHE=0 turns this off).
    enable_compilation_cache()


def _main(argv: Sequence[str] | None, interrupts: Interrupts) -> int:
    """Parse and check the arguments, start JAX, run the command; returns the exit status.

    Everything up to the last usage error runs without importing JAX (the argument types of
    :mod:`ceemx.experiment_command`, the records of :mod:`ceemx.fit_records`); then the thread
    limit, then JAX's start (the limit must come before JAX's backend starts).
    """
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if args.command == "fit":  # records after the options: more records (argparse stops at -x)
        args.records += [a for a in extra if not a.startswith("-")]
        extra = [a for a in extra if a.startswith("-")]
    if extra:
        _unknown(parser, args, extra)
    if args.command is None:
        parser.print_help()
        return 2
    out = args.out if args.out is not None else _default_out(args)
    interrupts.created = missing_folders(out)  # removed again if interrupted before writing
    # A signal during the check waits for its end: the exit removing the folders the check is
    # creating made the check fail and exit 2 instead (seen once under load).
    with interrupts.critical():
        _check_out(parser, args.out, _default_out(args))
    threads = _thread_count(parser, args)
    if args.command == "fit":
        records = _fit_records(args)
        _limit_threads(threads)
        _start_jax()
        return _fit(args, records, interrupts)
    kwargs = experiment_kwargs(args) if args.command == "experiment" else None
    _limit_threads(threads)
    _start_jax()
    from ceemx.evaluation import report

    if kwargs is None:  # demo
        from ceemx.experiments import demo

        with report.deferred_writes() as held:
            demo.run(smoke=args.smoke, out=args.out, method=args.method, max_epochs=args.max_epochs)
        return _commit(held, interrupts)

    from ceemx.experiments import get

    module = get(args.name)
    with report.deferred_writes() as held, _noise_warnings_counted():
        module.run(**kwargs)
    return _commit(held, interrupts)


def _unknown(parser: argparse.ArgumentParser, args: argparse.Namespace, extra: list[str]) -> None:
    """Refuse arguments the command does not take, naming what it takes (exit 2)."""
    command = getattr(args, "command_parser", None) or parser
    flags = [a.split("=", 1)[0] for a in extra if a.startswith("-")]
    if command is parser or not flags:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    flags_of = (a.option_strings for a in command._actions)
    takes = [o for names in flags_of for o in names if o.startswith("--") and o != "--help"]
    what = f"experiment {args.name}" if args.command == "experiment" else args.command
    _refuse(
        command,
        f"{', '.join(flags)}: not an option of {what} (its options: {', '.join(takes)})",
    )


def _refuse(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    """Exit 2 with ``message`` as one line that names the command's help."""
    parser.error(message)
    raise AssertionError("unreachable")  # argparse's error exits


def _fit_records(args: argparse.Namespace):
    """The records of ``ceemx fit`` read and checked before JAX starts (refusals exit 2)."""
    parser = args.command_parser
    try:
        fit_command.check_model_spec(args.model)
        if args.dt is not None and args.time is not None:
            raise fit_command.Refused("give --dt or --time, not both")
        records = fit_command.read_records(
            args.records, args.outputs, args.inputs, dt=args.dt, time=args.time
        )
        tests = None
        if args.test:
            tests = fit_command.read_records(
                args.test, args.outputs, args.inputs, dt=records.dt, time=args.time
            )
        fit_command.n_init_of(args, records, tests)
    except fit_command.Refused as e:
        _refuse(parser, str(e))
    return records, tests


def _fit(args: argparse.Namespace, records, interrupts: Interrupts) -> int:
    """``ceemx fit``: fit, score and draw, then write everything to ``--out`` at once."""
    from ceemx.evaluation import report

    out = Path(args.out)
    report.plt()  # figures drawn off-screen
    try:
        done = fit_command.run(args, *records)
    except fit_command.Refused as e:
        _refuse(args.command_parser, str(e))
    print(done.summary)
    print(done.scores)
    with report.deferred_writes() as held:
        report.save_text(out / "summary.txt", done.summary + "\n")
        report.save_text(out / "scores.txt", done.scores + "\n")
        for name, fig in done.figures.items():
            report.save_figure(fig, out / name)
        report.save_json(out / "results.json", done.results)
    status = _commit(held, interrupts)
    if status == 0:
        with interrupts.critical():
            done.save(out / "model.ceemx")
        print(f"ceemx fit: wrote {', '.join(sorted(p.name for p in out.iterdir()))} to {out}")
    return status


@contextlib.contextmanager
def _noise_warnings_counted() -> Iterator[None]:
    """Count the experiment's noise-check warnings into one line at the end.

    An experiment's fits run at the paper's fixed noise settings, which the end-of-fit noise
    check often finds inconsistent (by design of the setting, not a fault of the run).
    """
    from ceemx.identification.analysis.noise_check import NoiseCheckWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", NoiseCheckWarning)
        yield
    flagged = [w for w in caught if issubclass(w.category, NoiseCheckWarning)]
    for w in caught:  # every other warning as it would have been shown
        if not issubclass(w.category, NoiseCheckWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if flagged:
        print(
            f"ceemx: the end-of-fit noise check flagged {len(flagged)} fit"
            f"{'s' if len(flagged) > 1 else ''} at the experiment's fixed noise settings "
            "(ceemx.identification.analysis.noise_check; fit(..., noise='learn') learns the "
            "scales).",
            file=sys.stderr,
        )


def _commit(held, interrupts: Interrupts) -> int:
    """Write the held result files (SIGINT waits until they are all written)."""
    try:
        with interrupts.critical():
            held.commit()
    except OSError as e:
        print(f"ceemx: error: cannot write the results: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
