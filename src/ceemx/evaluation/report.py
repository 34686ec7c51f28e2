"""Reporting: Markdown tables, JSON and text files, figures.

- :func:`format_estimate`, :func:`markdown_table`, :func:`parameter_table` — mean (standard error)
  cells and GitHub-flavoured Markdown tables, flagged like the paper's Table 1 when the mean is not
  within two standard errors of the truth.
- :func:`format_pm`, :func:`estimate_table` — one fit's estimates ± their standard errors (e.g.
  the Laplace standard errors of :meth:`ceemx.FitResult.parameter_estimates`);
  :meth:`ceemx.FitResult.summary` is the whole fit's table.
- :func:`score_table` — a benchmark score in a few lines (``repr`` of
  :class:`~ceemx.evaluation.metrics.BenchmarkScore`).
- :func:`output_dir`, :func:`save_json`, :func:`save_text` — result files, each written atomically
  (a temporary file in the same folder, then ``os.replace``): a reader never sees half a file.
- :func:`deferred_writes` — hold every result file in memory until :meth:`Deferred.commit`
  (the ``ceemx`` command commits after the run, ``results.json`` last, so an interrupted run
  leaves no result file at all).
- :func:`plt`, :func:`save_figure` — Matplotlib with a non-interactive backend; the figures
  themselves (benchmark traces, residual correlations, the residual diagnostics) are in
  :mod:`ceemx.evaluation.plots`.

The numbers themselves (ε(θ), simulation RMSE) come from :mod:`ceemx.evaluation.metrics`, their
summaries over seeds (:class:`~ceemx.evaluation.estimates.Estimate`) from
:mod:`ceemx.evaluation.estimates`.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ceemx.evaluation.estimates import Estimate, mean_se
from ceemx.infra.paths import output_dir

__all__ = [
    "Deferred",
    "deferred_writes",
    "format_estimate",
    "markdown_table",
    "output_dir",
    "estimate_table",
    "format_pm",
    "parameter_table",
    "plt",
    "save_figure",
    "save_json",
    "save_text",
]


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------


def format_estimate(
    est: Estimate,
    truth: float | None = None,
    *,
    flagged: bool | None = None,
    digits: int = 3,
    k: float = 2.0,
) -> str:
    """``"10.011 (0.012)"``, or ``"**10.011 (0.012)**†"`` when flagged.

    Args:
        est: mean and standard error.
        truth: flag the cell when the mean is not within ``k`` standard errors of it.
        flagged: flag (or not) regardless of ``truth``, e.g. for numbers reported elsewhere.
        digits: decimals.
        k: flagging threshold in standard errors (paper: 2).

    Returns:
        The cell's text.
    """
    if flagged is None:
        flagged = truth is not None and not est.within(truth, k)
    s = f"{est.mean:.{digits}f} ({est.se:.{digits}f})"
    return f"**{s}**†" if flagged else s


def markdown_table(header: Sequence[object], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-flavoured Markdown table (cells formatted with ``str``)."""
    lines = ["| " + " | ".join(str(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def parameter_table(
    rows: Mapping[str, Mapping[str, tuple[object, float]]],
    *,
    label: str = "setting",
    digits: int = 3,
    k: float = 2.0,
) -> str:
    """Markdown table of mean (SE) per row and parameter, flagging means not within k SE of truth.

    Args:
        rows: row label → {parameter name → (estimates over seeds, true value)}; every row must
            name the same parameters.
        label: header of the first column.
        digits: decimals.
        k: flagging threshold in standard errors (paper: 2).

    Returns:
        The table (a line "† not within k SE of the truth" is appended when any cell is flagged).
    """
    if not rows:
        return ""
    names = list(next(iter(rows.values())).keys())
    body, any_flagged = [], False
    for name, params in rows.items():
        cells = [name]
        for p in names:
            values, truth = params[p]
            est = mean_se(values)
            any_flagged |= not est.within(truth, k)
            cells.append(format_estimate(est, truth, digits=digits, k=k))
        body.append(cells)
    truths = ", ".join(f"{p} = {float(next(iter(rows.values()))[p][1]):.{digits}f}" for p in names)
    out = markdown_table([label, *names], body) + f"\nTruth: {truths}.\n"
    if any_flagged:
        out += f"† mean not within {k:g} standard errors of the truth.\n"
    return out


def format_pm(value: float, se: float, *, digits: int = 3) -> str:
    """``"10.011 ± 0.012"`` (``"10.011 ± nan"`` when the standard error is not available)."""
    return f"{float(value):.{digits}f} ± {float(se):.{digits}f}"


def estimate_table(
    estimates: Mapping[str, tuple[float, float]],
    truth: Mapping[str, float] | None = None,
    *,
    digits: int = 3,
    k: float = 2.0,
) -> str:
    """Markdown table of one fit's parameters as estimate ± standard error.

    Args:
        estimates: parameter name → (estimate, standard error), e.g.
            :meth:`ceemx.FitResult.parameter_estimates`.
        truth: optional parameter name → true value; adds a column and flags (†) the estimates
            not within ``k`` standard errors of it.
        digits: decimals.
        k: flagging threshold in standard errors.

    Returns:
        The table (a line "† not within k SE of the truth" is appended when any cell is flagged).
    """
    if not estimates:
        return ""
    if truth is not None:  # names as written; the key paths of earlier versions (".a") too
        truth = {str(k).removeprefix("."): v for k, v in truth.items()}
    header = ["parameter", "estimate ± SE"] + (["truth"] if truth is not None else [])
    body, any_flagged = [], False
    for name, (value, se) in estimates.items():
        cell = format_pm(value, se, digits=digits)
        row = [name, cell]
        if truth is not None and name.removeprefix(".") in truth:
            t = float(truth[name.removeprefix(".")])
            if not abs(float(value) - t) <= k * float(se):
                cell, any_flagged = f"**{cell}**†", True
            row = [name, cell, f"{t:.{digits}f}"]
        elif truth is not None:
            row.append("")
        body.append(row)
    out = markdown_table(header, body)
    if any_flagged:
        out += f"† estimate not within {k:g} standard errors of the truth.\n"
    return out


def score_table(
    score,
    *,
    output_names: Sequence[str] | None = None,
    unit: str = "",
    format: str = "text",
    arrays: bool = False,
) -> str:
    """A :class:`~ceemx.evaluation.metrics.BenchmarkScore` in a few lines; ``repr(score)``.

    One row per test record and output (RMSE, NRMSE, fit %), then each record's overall RMSE
    when there are several outputs; the simulated trajectories only with ``arrays=True``
    (NumPy's abbreviated print).

    Args:
        score: the score.
        output_names: one name per output (default: the score's ``outputs``, from the test
            data's names and units, else ``y1``, ``y2``, …).
        unit: the RMSE's unit, e.g. ``"mV"`` (in the RMSE column's heading).
        format: ``"text"`` (aligned columns) or ``"markdown"``.
        arrays: append ``x1``, ``y_sim`` and ``x_sim``.

    Returns:
        The table as a string.
    """
    if format not in ("text", "markdown"):
        raise ValueError(f"`format` must be 'text' or 'markdown'; got {format!r}.")
    rmse, nrmse, fit = (np.atleast_2d(np.asarray(a, np.float64)) for a in score[:3])
    B, m = rmse.shape
    output_names = getattr(score, "outputs", None) if output_names is None else output_names
    names = [f"y{j + 1}" for j in range(m)] if output_names is None else list(output_names)
    if len(names) != m:
        raise ValueError(f"`output_names` needs {m} names; got {len(names)}.")
    head = ["record", "output", f"RMSE [{unit}]" if unit else "RMSE", "NRMSE", "fit %"]
    body = [
        [str(b), names[j], f"{rmse[b, j]:.4g}", f"{nrmse[b, j]:.4g}", f"{fit[b, j]:.2f}"]
        for b in range(B)
        for j in range(m)
    ]
    if m > 1:
        overall = np.atleast_1d(np.asarray(score.rmse_overall, np.float64))
        nr, ft = (np.atleast_1d(np.asarray(a, np.float64)) for a in score[4:6])
        body += [
            [str(b), "all", f"{overall[b]:.4g}", f"{nr[b]:.4g}", f"{ft[b]:.2f}"] for b in range(B)
        ]
    title = (
        f"BenchmarkScore: free-run simulation of {B} record{'s' if B != 1 else ''}, scored from "
        "sample "
        f"n_init = {int(score.n_init)}"
    )
    if format == "markdown":
        lines = [f"**{title}**", "", markdown_table(head, body).rstrip("\n")]
    else:
        widths = [max(len(r[i]) for r in [head, *body]) for i in range(len(head))]
        lines = [title] + [
            "  ".join(
                c.rjust(w) if i >= 2 else c.ljust(w)
                for i, (c, w) in enumerate(zip(r, widths, strict=True))
            )
            for r in [head, *body]
        ]
    if arrays:
        for name in ("x1", "y_sim", "x_sim"):
            a = np.asarray(getattr(score, name))
            lines.append(f"{name} {a.shape}:\n{np.array2string(a, threshold=50, edgeitems=2)}")
    else:
        lines.append("(x1, y_sim, x_sim: attributes; score.table(arrays=True) prints them)")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def _jsonable(obj: Any):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray | jax.Array):
        return _jsonable(np.asarray(obj).tolist())
    if isinstance(obj, np.floating | float):
        f = float(obj)
        return f if math.isfinite(f) else str(f)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path``, then rename it over ``path``."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            umask = os.umask(0o022)
            os.umask(umask)
            os.fchmod(f.fileno(), 0o666 & ~umask)  # mkstemp's 0600 → an ordinary write's mode
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


class Deferred:
    """Result files held in memory by :func:`deferred_writes` until :meth:`commit`."""

    def __init__(self) -> None:
        self.files: dict[Path, bytes] = {}

    def commit(self) -> list[Path]:
        """Write the held files atomically, ``results.json`` files last; returns their paths."""
        order = sorted(self.files, key=lambda p: p.name == "results.json")
        for path in order:
            _write_atomic(path, self.files[path])
        self.files.clear()
        return order


_deferred: Deferred | None = None


@contextlib.contextmanager
def deferred_writes() -> Iterator[Deferred]:
    """Hold result files in memory within the block, to write them later or never.

    Within the block, :func:`save_json`, :func:`save_text` and :func:`save_figure` only hold
    their files; :meth:`Deferred.commit` writes them. Files not committed are dropped.

    Example::

        with report.deferred_writes() as held:
            table1.run(smoke=True)
        held.commit()
    """
    global _deferred
    previous, _deferred = _deferred, Deferred()
    try:
        yield _deferred
    finally:
        _deferred = previous


def _save(path: Path, data: bytes) -> Path:
    if _deferred is not None:
        _deferred.files[path] = data
    else:
        _write_atomic(path, data)
    return path


def save_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (arrays become lists; non-finite floats become strings).

    The file is replaced atomically (held until commit under :func:`deferred_writes`).
    """
    text = json.dumps(_jsonable(obj), indent=2) + "\n"
    return _save(Path(path), text.encode())


def save_text(path: str | os.PathLike, text: str) -> Path:
    """Write a text file (e.g. a Markdown table), atomically (see :func:`save_json`)."""
    return _save(Path(path), text.encode())


# --------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------


def plt():
    """``matplotlib.pyplot`` with the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as pyplot

    return pyplot


def save_figure(fig, path: str | os.PathLike, dpi: int = 120) -> Path:
    """Save a figure (tight bounding box), atomically (see :func:`save_json`), and close it."""
    path = Path(path)
    buf = io.BytesIO()
    try:
        fig.savefig(
            buf, format=path.suffix.lstrip(".").lower() or "png", dpi=dpi, bbox_inches="tight"
        )
    finally:
        plt().close(fig)
    return _save(path, buf.getvalue())
