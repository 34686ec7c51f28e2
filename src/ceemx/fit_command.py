r"""``ceemx fit``: fit a model to your records from the command line.

::

    ceemx fit tank_model.py:Tank run1.csv run2.csv --inputs pump --outputs level --dt 4 \\
        --start k=0.5 --test run3.csv --out tank-fit

1. Records (:mod:`ceemx.fit_records`): CSV files with a header row of column names (empty
   cells and ``nan``: missing samples) or NPZ files with one array per name; ``--inputs`` and
   ``--outputs`` name the columns; several files are several records (padded and masked:
   :meth:`ceemx.Trajectories.from_arrays`); the sample time from ``--dt`` or a ``--time``
   column (checked to be uniform).
2. The model (:func:`load_model`): ``FILE.py[:NAME]`` or ``module:NAME``; ``NAME`` a system
   instance, a system class or a function returning a system, called with the ``--start``
   values as keyword arguments. Without ``NAME``: the file's ``model``, else its one system
   class. A file is imported as a module from its folder, so the saved model loads again in
   another process with that folder on the path (``ceemx.load``).
3. :func:`ceemx.fit` (``--solver``, ``--noise``, ``--max-epochs``), with progress on stderr.
4. Written to ``--out``: ``summary.txt``, ``scores.txt`` (free-run scores of the records and of
   the ``--test`` records, :func:`ceemx.benchmark_score`), ``results.json``, the figures
   ``fit.png`` / ``test.png`` (measured and simulated outputs) and ``residuals.png`` (the
   residual diagnostics), and ``model.ceemx`` (:func:`ceemx.save`).

Every refusal — a file or column that is not there, a value out of range, a model file that
does not import, a model or a fit that refuses its arguments — is one line on stderr and exit
status 2 (``--traceback`` shows the traceback of an error raised by the model's own code).
Everything up to the model's import reads files with NumPy only: JAX starts after the checks.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import math
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ceemx.experiment_command import positive_int
from ceemx.fit_records import Records, Refused, read_records

__all__ = ["Records", "Refused", "add_parser", "load_model", "read_records", "run"]

SOLVERS = ("auto", "joint", "alternate", "laplace")
NOISE = ("auto", "learn", "fixed")
# ----------------------------------------------------------------------------------------------
# The command's options (argparse types answer without importing JAX)
# ----------------------------------------------------------------------------------------------


def _columns(text: str) -> tuple[str, ...]:
    names = tuple(s.strip() for s in text.split(","))
    if not all(names) or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"expected distinct comma-separated names; got {text!r}")
    return names


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (0 < value < math.inf):
        raise argparse.ArgumentTypeError(f"must be a positive number; got {text!r}")
    return value


def _start_value(text: str) -> tuple[str, Any]:
    name, sep, value = text.partition("=")
    name = name.strip()
    if not sep or not name.isidentifier():
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE; got {text!r}")
    try:
        parsed = json.loads(value)
    except json.JSONDecodeError:
        parsed = value  # a string, e.g. hold=foh
    return name, parsed


def add_parser(sub) -> argparse.ArgumentParser:
    """The ``fit`` command and its options (on the subparsers ``sub``)."""
    p = sub.add_parser(
        "fit",
        help="fit a model (a Python file or module:Class) to CSV or NPZ records",
        description="Fit a model to your records; writes the summary, scores, figures and the "
        "saved model to --out. Example: ceemx fit tank.py:Tank run1.csv --inputs u "
        "--outputs y --dt 4 --start k=0.5",
    )
    p.add_argument(
        "model",
        metavar="MODEL",
        help="FILE.py[:NAME] or module:NAME: a system instance, class, or function returning "
        "one (without NAME: the file's `model`, else its one system class)",
    )
    p.add_argument("records", nargs="+", metavar="RECORD", help="CSV or NPZ files, one record each")
    p.add_argument(
        "--outputs", type=_columns, required=True, metavar="Y1,...", help="output columns"
    )
    p.add_argument(
        "--inputs",
        type=_columns,
        default=(),
        metavar="U1,...",
        help="input columns (default: none, an autonomous model)",
    )
    p.add_argument("--dt", type=_positive, default=None, help="sample time (default: --time)")
    p.add_argument("--time", metavar="COLUMN", help="a time column: the sample time from it")
    p.add_argument("--time-unit", default="s", help="unit of the sample time (default: s)")
    p.add_argument("--output-units", type=_columns, default=None, metavar="UNIT,...")
    p.add_argument("--input-units", type=_columns, default=None, metavar="UNIT,...")
    p.add_argument(
        "--start",
        type=_start_value,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a keyword argument of the model class or function, as JSON (k=0.5, "
        "k=[0.1,0.2], process_noise=0.05); repeatable",
    )
    p.add_argument(
        "--test",
        action="append",
        default=[],
        metavar="RECORD",
        help="a held-out record scored beside the fitted ones (same columns); repeatable",
    )
    p.add_argument(
        "--solver",
        choices=SOLVERS,
        default="auto",
        help="auto: chosen from the problem (ceemx.fit without a solver); joint: JointLM; "
        "alternate: Algorithm 1; laplace: LaplaceEM",
    )
    p.add_argument(
        "--noise",
        choices=NOISE,
        default="auto",
        help="learn the noise scales or keep the model's (auto: fit's default)",
    )
    p.add_argument(
        "--max-epochs", type=positive_int, default=100, help="bound on epochs (default 100)"
    )
    p.add_argument(
        "--n-init",
        type=positive_int,
        default=None,
        metavar="N",
        help="samples that set the initial state before scoring (default: a tenth of the "
        "shortest record, at most 50)",
    )
    p.add_argument("--out", default="ceemx-fit", help="output folder (default: ./ceemx-fit)")
    p.add_argument("--no-figures", action="store_true", help="write no figures")
    p.add_argument("--no-progress", action="store_true", help="no progress display on stderr")
    p.add_argument(
        "--traceback",
        action="store_true",
        help="show the traceback of an error in the model's code instead of one line",
    )
    p.set_defaults(command_parser=p)  # refusals after parsing name this command's help
    return p


# ----------------------------------------------------------------------------------------------
# The model
# ----------------------------------------------------------------------------------------------


def _split_spec(spec: str) -> tuple[str, str | None]:
    """``FILE.py[:NAME]`` or ``module:NAME`` → (file or module, name or None)."""
    target, sep, name = spec.rpartition(":")
    if not sep or not target or os.path.exists(spec):
        return spec, None
    return target, name


def is_file_spec(target: str) -> bool:
    return target.endswith(".py") or os.sep in target or os.path.exists(target)


def check_model_spec(spec: str) -> None:
    """Refuse a model file that is not there (before JAX starts)."""
    target, name = _split_spec(spec)
    if is_file_spec(target):
        if not Path(target).is_file():
            raise Refused(f"{spec}: no such model file")
    elif name is None:
        raise Refused(f"{spec}: expected FILE.py[:NAME] or module:NAME")
    if name is not None and not name.replace(".", "_").isidentifier():
        raise Refused(f"{spec}: {name!r} is not a Python name")


def _import(target: str, traceback: bool):
    """The module of a model file (imported from its folder, by its name) or a module name."""
    if is_file_spec(target):
        path = Path(target).resolve()
        module_name = path.stem
        if not module_name.isidentifier():
            raise Refused(f"{target}: a model file's name must be a Python name (it is imported)")
        folder = str(path.parent)
        if folder not in sys.path:
            sys.path.insert(0, folder)
        loaded = sys.modules.get(module_name)
        if loaded is not None and Path(getattr(loaded, "__file__", "") or "").resolve() != path:
            raise Refused(
                f"{target}: a module named {module_name!r} is already imported from "
                f"{getattr(loaded, '__file__', None) or 'elsewhere'}; rename the file"
            )
    else:
        module_name = target
    try:
        return importlib.import_module(module_name)
    except Exception as e:  # noqa: BLE001 — the user's file: any error is one line
        if traceback:
            raise
        raise Refused(f"{target}: the model does not import: {_one_line(e)}") from None


def _systems_in(module) -> list[tuple[str, Any]]:
    from ceemx.models.system import AbstractSystem

    found = []
    for name, obj in vars(module).items():
        if (
            inspect.isclass(obj)
            and issubclass(obj, AbstractSystem)
            and obj.__module__ == module.__name__
            and not inspect.isabstract(obj)
        ):
            found.append((name, obj))
    return found


def _pick(module, spec: str, name: str | None):
    if name is not None:
        obj = module
        for part in name.split("."):
            if not hasattr(obj, part):
                raise Refused(f"{spec}: {module.__name__} has no {name!r}")
            obj = getattr(obj, part)
        return obj
    if hasattr(module, "model"):
        return module.model
    found = _systems_in(module)
    if len(found) == 1:
        return found[0][1]
    what = ", ".join(n for n, _ in found) or "none"
    raise Refused(
        f"{spec}: name the model as FILE.py:NAME (no `model` in the file; system classes: {what})"
    )


def _start_array(value):
    """A JSON value as a model argument: lists as float arrays, the rest as given."""
    if isinstance(value, list):
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            return value
        import jax.numpy as jnp

        return jnp.asarray(arr)
    return value


def load_model(spec: str, start: Sequence[tuple[str, Any]] = (), *, traceback: bool = False):
    """The system of ``spec`` at its start values (see the module notes).

    Raises:
        Refused: the file or name is not there, it does not import, it is not a system, or its
            class refuses the start values (one line each).
    """
    import equinox as eqx

    from ceemx.models.system import AbstractSystem

    target, name = _split_spec(spec)
    module = _import(target, traceback)
    obj = _pick(module, spec, name)
    kwargs = {k: _start_array(v) for k, v in start}
    if isinstance(obj, AbstractSystem):
        system = obj
        for field, value in kwargs.items():
            if not hasattr(system, field):
                raise Refused(f"--start {field}: {type(system).__name__} has no field {field!r}")
            old = getattr(system, field)
            new = np.asarray(value, old.dtype) if hasattr(old, "dtype") else value
            if hasattr(old, "shape") and np.shape(new) != np.shape(old):
                raise Refused(
                    f"--start {field}: shape {np.shape(new)}, the model's is {np.shape(old)}"
                )
            system = eqx.tree_at(lambda s, f=field: getattr(s, f), system, _start_array(new))
        return system
    if not callable(obj):
        raise Refused(f"{spec}: {type(obj).__name__} is not a system, a class or a function")
    try:
        system = obj(**kwargs)
    except (TypeError, ValueError) as e:
        if traceback:
            raise
        given = ", ".join(kwargs) or "no arguments"
        raise Refused(f"{spec}: building the model with {given}: {_one_line(e)}") from None
    if not isinstance(system, AbstractSystem):
        raise Refused(f"{spec}: returned a {type(system).__name__}, not a ceemx system")
    return system


# ----------------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------------


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    plain = isinstance(e, (ValueError, TypeError, Refused))
    return text if plain else f"{type(e).__name__}: {text}"


def n_init_of(args: argparse.Namespace, records: Records, tests: Records | None) -> int:
    """``--n-init``, or a tenth of the shortest record (at most 50); refused past a record."""
    shortest = min(records.shortest, tests.shortest if tests else records.shortest)
    n = args.n_init if args.n_init is not None else max(1, min(50, shortest // 10))
    if n >= shortest:
        raise Refused(f"--n-init {n}: must be below the shortest record's {shortest} samples")
    return n


def _solver(name: str):
    import ceemx

    return {
        "auto": None,
        "joint": ceemx.JointLM,
        "alternate": ceemx.Alternating,
        "laplace": ceemx.LaplaceEM,
    }[name]


def _data(records: Records, args: argparse.Namespace):
    from ceemx.data.trajectories import Trajectories

    try:
        return Trajectories.from_arrays(
            list(records.ys),
            None if records.us is None else list(records.us),
            dt=records.dt,
            output_names=args.outputs,
            output_units=args.output_units,
            input_names=args.inputs or None,
            input_units=args.input_units,
            time_unit=args.time_unit,
        )
    except (ValueError, TypeError) as e:
        raise Refused(_one_line(e)) from None


@dataclass
class Outcome:
    """What a run produced: the texts and data the command writes."""

    summary: str
    scores: str
    results: dict
    figures: dict[str, Any]
    save: Callable[[Path], Path]


def run(args: argparse.Namespace, records: Records, tests: Records | None) -> Outcome:
    """Load the model, fit it, score it and draw the figures (nothing written yet).

    Raises:
        Refused: the model, the data or the fit refuse a value (one line).
    """
    import ceemx
    from ceemx.evaluation import plots

    n_init = n_init_of(args, records, tests)
    system = load_model(args.model, args.start, traceback=args.traceback)
    data = _data(records, args)
    test = None if tests is None else _data(tests, args)
    solver = _solver(args.solver)
    try:
        result = ceemx.fit(
            system,
            data,
            solver=None if solver is None else solver(),
            max_epochs=args.max_epochs,
            noise=None if args.noise == "auto" else args.noise,
            progress=False if args.no_progress else True,
        )
    except (ValueError, TypeError) as e:
        if args.traceback:
            raise
        raise Refused(f"the fit refused: {_one_line(e)}") from None
    fitted = result.system
    summary = result.summary()
    scores = {"fitted records": ceemx.benchmark_score(fitted, data, n_init)}
    if test is not None:
        scores["test records"] = ceemx.benchmark_score(fitted, test, n_init)
    score_text = "\n\n".join(
        f"{what} ({', '.join(files)}):\n{score.table()}"
        for (what, score), files in zip(
            scores.items(), (records.files, *(() if tests is None else (tests.files,))), strict=True
        )
    )
    figures: dict[str, Any] = {}
    if not args.no_figures:
        drawn = [("fit.png", "fitted records", data)]
        drawn += [] if test is None else [("test.png", "test records", test)]
        for name, what, d in drawn:
            score = scores[what]
            figures[name] = plots.plot_benchmark(
                np.asarray(d.y[0]),
                np.asarray(score.y_sim[0]),
                n_init=n_init,
                output_names=score.outputs,
                dt=records.dt,
                title=f"{args.model}: {what}, record 1",
            )
        figures["residuals.png"] = plots.plot_residual_diagnostics(result.diagnostics())
    results = {
        "model": args.model,
        "records": list(records.files),
        "test_records": [] if tests is None else list(tests.files),
        "solver": args.solver,
        "noise": args.noise,
        "max_epochs": args.max_epochs,
        "epochs": result.epochs,
        "converged": bool(result.converged),
        "J": float(result.history[-1]["J"]) if result.history else None,
        "n_init": n_init,
        "parameters": {k: {"estimate": v[0], "se": v[1]} for k, v in _estimates(result).items()},
        "scores": {
            what: {
                "rmse": np.asarray(s.rmse).tolist(),
                "fit_percent": np.asarray(s.fit_percent).tolist(),
                "outputs": list(s.outputs) if s.outputs else None,
            }
            for what, s in scores.items()
        },
    }
    return Outcome(
        summary, score_text, results, figures, lambda path: ceemx.save(path, result, data=data)
    )


def _estimates(result) -> dict[str, tuple[float, float]]:
    try:
        return {k: (float(v[0]), float(v[1])) for k, v in result.parameter_estimates().items()}
    except (ValueError, np.linalg.LinAlgError):  # no covariance (e.g. a singular curvature)
        return {}
