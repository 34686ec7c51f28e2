"""The ``ceemx`` command: ``ceemx demo``, ``ceemx experiment NAME``, ``ceemx --version``.

Examples::

    ceemx demo                                 # six coupled Lorenz attractors, < 2 min on a laptop
    ceemx experiment table1                    # paper Table 1, both weightings, 10 seeds
    ceemx experiment figure3 --method alternate --max-epochs 50
    ceemx experiment figure3 --seeds 2         # the first two seeds of figure3's: 42, 43
    ceemx experiment table1 --seeds 3,7        # exactly seeds 3 and 7
    ceemx experiment table1 --smoke            # seconds; what the tests run
    ceemx experiment figure2                   # CE-EM vs Particle EM, 10 seeds
    ceemx experiment figure3 --method particle # Particle EM on six coupled Lorenz
    ceemx experiment figure4                   # helicopter-like study: naive, LSTM, H25, SID, NL
    ceemx experiment figure4 --dataset silverbox  # the same five models on a real record

``--seeds N`` runs the first N seeds of the experiment's seed sequence (table1: 0, 1, 2, …;
figure2: 43, 44, …; figure3: 42, 43, …); a comma list (``--seeds 42,44``, or ``--seeds 42,``
for one seed) runs exactly those seeds.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

__all__ = ["main"]


def _version() -> str:
    from . import __version__

    return __version__


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for documentation and tests)."""
    from .experiments import EXPERIMENTS
    from .experiments.common import METHODS, parse_seeds

    parser = argparse.ArgumentParser(
        prog="ceemx",
        description="Certainty-equivalent EM system identification in JAX.",
    )
    parser.add_argument("--version", action="version", version=f"ceemx {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    demo = sub.add_parser(
        "demo", help="identify six coupled Lorenz attractors; writes a figure and tables"
    )
    demo.add_argument("--smoke", action="store_true", help="tiny, fast version (for tests)")
    demo.add_argument("--out", default="ceemx-demo", help="output folder (default: ./ceemx-demo)")
    demo.add_argument("--method", choices=METHODS, default=None, help="default: joint")
    demo.add_argument("--max-epochs", type=int, default=None, help="bound on iterations")

    exp = sub.add_parser(
        "experiment", help="run a paper experiment (table1, figure2, figure3, figure4)"
    )
    exp.add_argument("name", choices=EXPERIMENTS, help="which experiment")
    exp.add_argument("--smoke", action="store_true", help="tiny, fast version (for tests)")
    exp.add_argument(
        "--seeds",
        type=parse_seeds,
        default=None,
        metavar="N|S1,S2,...",
        help="N: the first N seeds of the experiment's sequence (table1: 0, 1, …; figure2: "
        "43, 44, …; figure3: 42, 43, …); a comma list: exactly those seeds (default: the "
        "paper's)",
    )
    exp.add_argument("--out", default=None, help="output folder (default: ./results/NAME)")
    exp.add_argument(
        "--method",
        choices=METHODS,
        default=None,
        help="joint (x, θ) LM, Algorithm 1, or Particle EM (figure3; figure2 runs CE-EM and "
        "Particle EM; figure4: the NL model's CE-EM solver, alternate or joint) (default: "
        "table1 alternate, figure3 joint, figure4 alternate)",
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
        help="figure4: run the five models on windows of a real benchmark record; "
        "benchmarks: only this dataset (default: all three)",
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``ceemx`` console script (and ``python -m ceemx``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2

    import jax

    jax.config.update("jax_enable_x64", True)
    from .compilation import enable_compilation_cache

    # Compiled programs persist across runs (CEEMX_COMPILATION_CACHE=0 turns this off).
    enable_compilation_cache()

    if args.command == "demo":
        from .experiments import demo

        demo.run(smoke=args.smoke, out=args.out, method=args.method, max_epochs=args.max_epochs)
        return 0

    from .experiments import get

    module = get(args.name)
    kwargs = dict(
        smoke=args.smoke,
        seeds=args.seeds,
        out=args.out,
        method=args.method,
        max_epochs=args.max_epochs,
    )
    if args.weighting is not None:
        kwargs["weighting"] = args.weighting
    if args.name == "figure3":
        kwargs["learner"] = args.learner
    if args.name == "figure4":
        kwargs["data"] = args.data
        kwargs["dataset"] = args.dataset
    elif args.name == "benchmarks":
        if args.data is not None:
            parser.error("--data applies to figure4 only (benchmarks read CEEMX_DATA)")
        if args.method not in (None, "joint", "alternate"):
            parser.error("benchmarks: --method must be joint or alternate")
        kwargs["dataset"] = args.dataset
    elif args.data is not None or args.dataset is not None:
        parser.error("--data applies to figure4 only, --dataset to figure4 and benchmarks")
    module.run(**kwargs)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
