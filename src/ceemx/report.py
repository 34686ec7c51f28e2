"""Reporting: Markdown tables, JSON and text files, figures.

- :func:`format_estimate`, :func:`markdown_table`, :func:`parameter_table` — mean (standard error)
  cells and GitHub-flavoured Markdown tables, flagged like the paper's Table 1 when the mean is not
  within two standard errors of the truth.
- :func:`output_dir`, :func:`save_json`, :func:`save_text` — result files.
- :func:`plt`, :func:`save_figure` — Matplotlib with a non-interactive backend.

The numbers themselves (ε(θ), simulation RMSE, :class:`~ceemx.evaluate.Estimate`) come from
:mod:`ceemx.evaluate`.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .evaluate import Estimate, mean_se

__all__ = [
    "format_estimate",
    "markdown_table",
    "output_dir",
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


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def output_dir(out: str | os.PathLike | None, default: str | os.PathLike) -> Path:
    """The folder ``out`` (``default`` when ``None``), created if missing."""
    path = Path(default if out is None else out)
    path.mkdir(parents=True, exist_ok=True)
    return path


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


def save_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (arrays become lists; non-finite floats become strings)."""
    path = Path(path)
    path.write_text(json.dumps(_jsonable(obj), indent=2) + "\n")
    return path


def save_text(path: str | os.PathLike, text: str) -> Path:
    """Write a text file (e.g. a Markdown table)."""
    path = Path(path)
    path.write_text(text)
    return path


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
    """Save a figure (tight bounding box) and close it."""
    path = Path(path)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt().close(fig)
    return path
