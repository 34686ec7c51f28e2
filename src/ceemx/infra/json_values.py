"""JSON that strict readers accept: NumPy/JAX values as Python ones, non-finite floats tagged.

JSON has no NaN or infinity: ``json.dumps`` writes them as ``NaN``/``-Infinity``, which strict
readers refuse, and a fit's records hold them (a failed trajectory's J is −inf or NaN, a standard
error NaN). :func:`to_json` writes each as ``{"nonfinite": "nan" | "inf" | "-inf"}`` and
:func:`from_json` reads it back as the float.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

__all__ = ["from_json", "jsonable", "to_json"]

#: the key of a non-finite float: ``{"nonfinite": "nan" | "inf" | "-inf"}``
NONFINITE = "nonfinite"


def jsonable(value: Any) -> Any:
    """``value`` in JSON's types: NumPy/JAX values as Python ones, a non-finite float tagged."""
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if value is None or isinstance(value, str | bool | int):
        return value
    if isinstance(value, float):
        return float(value) if np.isfinite(value) else {NONFINITE: repr(float(value))}
    arr = np.asarray(value)
    out = arr.item() if arr.ndim == 0 else arr.tolist()
    if isinstance(out, type(value)) and not isinstance(out, list):
        raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")
    return jsonable(out)


def to_json(value: Any, **options: Any) -> str:
    """``json.dumps`` of :func:`jsonable` ``(value)``; any NaN left is refused."""
    return json.dumps(jsonable(value), allow_nan=False, **options)


def _hook(obj: dict) -> Any:
    if set(obj) == {NONFINITE} and obj[NONFINITE] in ("nan", "inf", "-inf"):
        return float(obj[NONFINITE])
    return obj


def from_json(text: str | bytes) -> Any:
    """``json.loads`` with tagged non-finite floats read back as floats."""
    return json.loads(text, object_hook=_hook)
