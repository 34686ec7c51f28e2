"""``ceemx experiment NAME``: one parser per experiment, with only the options it takes.

:data:`EXPERIMENT_OPTIONS` says what each experiment takes besides ``--smoke`` and ``--out``;
``ceemx experiment NAME --help`` lists exactly those, and :mod:`ceemx.cli` refuses any other by
name. The argument types answer without importing JAX (a usage error exits at once).
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence

__all__ = ["EXPERIMENT_OPTIONS", "add_experiment", "experiment_kwargs", "positive_int", "seeds"]


def seeds(text: str):
    """``--seeds``: a count N or a comma list of seeds (:func:`ceemx.experiments.parse_seeds`)."""
    from ceemx.experiments import parse_seeds

    try:
        return parse_seeds(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def positive_int(text: str) -> int:
    """An integer >= 1 (``--threads``, ``--max-epochs``)."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1; got {text!r}")
    return n


#: what each experiment takes besides --smoke and --out, and the choices it accepts (``None``:
#: any value of the option's type). An option not listed is not offered: argparse refuses it.
EXPERIMENT_OPTIONS: dict[str, dict[str, tuple[str, ...] | None]] = {
    "table1": {
        "seeds": None,
        "method": ("joint", "alternate", "particle", "laplace"),
        "weighting": ("likelihood", "paper", "both"),
        "protocol": ("ours", "authors"),
        "max_epochs": None,
    },
    "figure2": {"seeds": None, "max_epochs": None},
    "figure3": {
        "seeds": None,
        "method": ("joint", "alternate", "particle", "laplace"),
        "weighting": ("likelihood", "paper"),
        "learner": ("lm", "lbfgs"),
        "max_epochs": None,
    },
    "figure4": {
        "seeds": None,
        "method": ("alternate", "joint"),
        "max_epochs": None,
        "data": None,
        "dataset": ("cascaded_tanks", "silverbox", "coupled_electric_drives"),
    },
    "real_data": {
        "seeds": None,
        "method": ("joint", "alternate"),
        "max_epochs": None,
        "dataset": ("cascaded_tanks", "silverbox", "coupled_electric_drives"),
    },
    "calibration": {"seeds": None, "max_epochs": None},
}

_EXPERIMENT_HELP = {
    "table1": "paper Table 1: bias on a single Lorenz system, both weightings",
    "figure2": "paper Figure 2: CE-EM against Particle EM",
    "figure3": "paper Figure 3: convergence on six coupled Lorenz systems",
    "figure4": "paper Figure 4: five models' one-step prediction (helicopter-like or a dataset)",
    "real_data": "gray-box, hybrid and linear models on the real datasets",
    "calibration": "learned noise and the coverage of 95 % intervals",
}

_OPTION_HELP = {
    "method": "the identification method: joint (x, θ) LM, alternate (Algorithm 1), particle "
    "(Particle EM), laplace (Laplace EM)",
    "weighting": "noise weights of the fitted system",
    "protocol": "'authors' runs the authors' protocol (explicit midpoint, x1 spread 5, zero "
    "start states, paper weighting, rho_x 0.001, Nelder-Mead with rho_theta 0.01)",
    "learner": "the θ-step optimiser of Algorithm 1",
    "max_epochs": "epochs (or joint iterations) per fit",
    "dataset": "a real dataset's records",
}


def _data_folder(text: str) -> str:
    if not os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"no such folder: {text!r}")
    return text


def add_experiment(sub, experiments: Sequence[str]) -> None:
    """``ceemx experiment NAME``: one parser per experiment, with only the options it takes."""
    exp = sub.add_parser("experiment", help=f"run an experiment ({', '.join(experiments)})")
    names = exp.add_subparsers(dest="name", metavar="NAME", required=True)
    for name in experiments:
        what = _EXPERIMENT_HELP[name]
        one = names.add_parser(name, help=what, description=what, allow_abbrev=False)
        one.add_argument("--smoke", action="store_true", help="tiny, fast version (for tests)")
        one.add_argument("--out", default=None, help=f"output folder (default: ./results/{name})")
        for option, choices in EXPERIMENT_OPTIONS[name].items():
            _add_experiment_option(one, option, choices)
        others = {o: None for o in _ALL_OPTIONS if o not in EXPERIMENT_OPTIONS[name]}
        one.set_defaults(command_parser=one, **others)


_ALL_OPTIONS = (
    *("seeds", "method", "weighting", "protocol", "learner", "max_epochs", "data", "dataset"),
)


def _add_experiment_option(parser, option: str, choices: tuple[str, ...] | None) -> None:
    flag = "--" + option.replace("_", "-")
    if option == "seeds":
        parser.add_argument(
            flag,
            type=seeds,
            default=None,
            metavar="N|S1,S2,...",
            help="N: the first N seeds of the experiment's sequence; a comma list: exactly those "
            "seeds (default: the paper's)",
        )
    elif option == "max_epochs":
        what = _OPTION_HELP[option]
        parser.add_argument(flag, type=positive_int, default=None, metavar="N", help=what)
    elif option == "data":
        parser.add_argument(
            flag,
            type=_data_folder,
            default=None,
            metavar="DIR",
            help="the paper's helicopter dataset folder",
        )
    else:
        parser.add_argument(flag, choices=choices, default=None, help=_OPTION_HELP[option])


def experiment_kwargs(args: argparse.Namespace) -> dict:
    """The keyword arguments of ``run`` for ``ceemx experiment NAME``: the options it takes."""
    kwargs = dict(smoke=args.smoke, out=args.out)
    for option in EXPERIMENT_OPTIONS[args.name]:
        value = getattr(args, option)
        if value is not None or option in ("seeds", "method", "max_epochs"):
            kwargs[option] = value
    return kwargs
