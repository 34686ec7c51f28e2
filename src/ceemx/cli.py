"""The ``ceemx`` command: ``ceemx demo``, ``ceemx experiment NAME``, ``ceemx --version``.

Examples::

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
folder that cannot be written) prints one line and exits with status 2 before any compute.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import warnings
from collections.abc import Iterator, Sequence

from ceemx.infra.interrupts import EXIT_INTERRUPTED, INTERRUPTED, Interrupts, missing_folders

__all__ = ["main"]


def _version() -> str:
    from ceemx import __version__

    return __version__


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr and exit status 2."""

    def error(self, message: str):  # type: ignore[override]
        message = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


# Parsing and checking the arguments imports neither JAX nor equinox: ``ceemx --help`` and every
# usage error answer at once (importing them takes seconds). What the checks need lives in light
# modules: ``METHODS`` and ``parse_seeds`` in :mod:`ceemx.experiments`, ``output_dir`` in
# :mod:`ceemx.infra.paths` (tests/test_cli_reliability.py checks that a usage error leaves JAX
# unimported).


def _seeds(text: str):
    from ceemx.experiments import parse_seeds

    try:
        return parse_seeds(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _threads(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1; got {text!r}")
    return n


def _add_demo(sub, methods: Sequence[str]) -> None:
    """The ``demo`` command and its options."""
    demo = sub.add_parser(
        "demo", help="identify six coupled Lorenz attractors; writes a figure and tables"
    )
    demo.add_argument("--smoke", action="store_true", help="tiny, fast version (for tests)")
    demo.add_argument("--out", default="ceemx-demo", help="output folder (default: ./ceemx-demo)")
    demo.add_argument("--method", choices=methods, default=None, help="default: joint")
    demo.add_argument("--max-epochs", type=int, default=None, help="bound on iterations")


def _add_experiment(sub, experiments: Sequence[str], methods: Sequence[str]):
    """The ``experiment`` command with the options every experiment takes; returns its parser."""
    exp = sub.add_parser(
        "experiment",
        help="run an experiment (table1, figure2, figure3, figure4, real_data, calibration)",
    )
    exp.add_argument("name", choices=experiments, help="which experiment")
    exp.add_argument("--smoke", action="store_true", help="tiny, fast version (for tests)")
    exp.add_argument(
        "--seeds",
        type=_seeds,
        default=None,
        metavar="N|S1,S2,...",
        help="N: the first N seeds of the experiment's sequence (table1: 0, 1, …; figure2: "
        "43, 44, …; figure3: 42, 43, …); a comma list: exactly those seeds (default: the "
        "paper's)",
    )
    exp.add_argument("--out", default=None, help="output folder (default: ./results/NAME)")
    exp.add_argument(
        "--method",
        choices=methods,
        default=None,
        help="joint (x, θ) LM, Algorithm 1, Particle EM (figure3), or Laplace EM (table1: EM "
        "with a Gaussian E-step, likelihood weighting; figure2 runs CE-EM and "
        "Particle EM; figure4: the NL model's CE-EM solver, alternate or joint) (default: "
        "table1 alternate, figure3 joint, figure4 alternate)",
    )
    return exp


def _add_experiment_options(exp) -> None:
    """The ``experiment`` options that only some experiments take."""
    exp.add_argument(
        "--protocol",
        choices=("ours", "authors"),
        default=None,
        help="table1: 'authors' runs the authors' protocol (explicit midpoint, x1 spread 5, zero "
        "start states, paper weighting, rho_x 0.001, Nelder-Mead with rho_theta 0.01)",
    )
    exp.add_argument(
        "--weighting",
        choices=("likelihood", "paper", "both"),
        default=None,
        help="noise weights of the fitted system (default: table1 both, figure3 paper)",
    )
    exp.add_argument(
        "--max-epochs", type=int, default=None, help="epochs (or joint iterations) per fit"
    )
    exp.add_argument(
        "--learner",
        choices=("lm", "lbfgs"),
        default="lm",
        help="figure3, alternate: θ-step optimiser",
    )
    exp.add_argument(
        "--data", default=None, metavar="DIR", help="figure4: the paper's helicopter dataset folder"
    )
    exp.add_argument(
        "--dataset",
        default=None,
        choices=("cascaded_tanks", "silverbox", "coupled_electric_drives"),
        help="figure4: run the five models on windows of a real dataset's records; "
        "real_data: only this dataset (default: all three)",
    )


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
        type=_threads,
        default=None,
        metavar="N",
        help="CPU threads for JAX (default: CEEMX_THREADS, else all cores); 1 is often faster "
        "on a machine busy with other work",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_demo(sub, METHODS)
    _add_experiment_options(_add_experiment(sub, EXPERIMENTS, METHODS))
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
    default = f"results/{args.name}"
    if args.name == "figure4" and args.dataset is not None:
        default += f"-{args.dataset}"
    return default


def _thread_count(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int | None:
    """``--threads``, else ``CEEMX_THREADS`` (a bad value is a usage error), else ``None``."""
    threads = args.threads
    if threads is None and os.environ.get("CEEMX_THREADS", "").strip():
        try:
            threads = _threads(os.environ["CEEMX_THREADS"].strip())
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


def _experiment_kwargs(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict:
    """The keyword arguments of ``run`` for ``ceemx experiment NAME`` (usage errors exit 2)."""
    kwargs = dict(
        smoke=args.smoke,
        seeds=args.seeds,
        out=args.out,
        method=args.method,
        max_epochs=args.max_epochs,
    )
    if args.weighting is not None:
        kwargs["weighting"] = args.weighting
    if args.protocol is not None:
        if args.name != "table1":
            parser.error("--protocol applies to table1 only")
        kwargs["protocol"] = args.protocol
    if args.name == "figure3":
        kwargs["learner"] = args.learner
    if args.name == "figure4":
        kwargs["data"] = args.data
        kwargs["dataset"] = args.dataset
    elif args.name == "real_data":
        if args.data is not None:
            parser.error("--data applies to figure4 only (real_data reads CEEMX_DATA)")
        if args.method not in (None, "joint", "alternate"):
            parser.error("real_data: --method must be joint or alternate")
        kwargs["dataset"] = args.dataset
    elif args.data is not None or args.dataset is not None:
        parser.error("--data applies to figure4 only, --dataset to figure4 and real_data")
    return kwargs


def _main(argv: Sequence[str] | None, interrupts: Interrupts) -> int:
    """Parse and check the arguments, start JAX, run the command; returns the exit status.

    Everything up to the last usage error runs without importing JAX (see ``_seeds``); then the
    thread limit, then JAX's start (the limit must come before JAX's backend starts).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
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
    kwargs = _experiment_kwargs(parser, args) if args.command == "experiment" else None
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
