"""Validation of options: one helper per kind of option, for every class and public function.

Each check runs on the host when an options object is built (Equinox ``__check_init__``) or a
public function is entered (its keyword options: ``fit``, ``smooth``, ``hybrid``, …), before any
compute, and raises ``TypeError`` (wrong kind) or ``ValueError`` (bad value) with a message
that names the option and says what it must be: "`rtol` must be finite and >= 0; got nan.".
Traced values pass unchecked (an options object rebuilt inside ``jit`` was checked when made).

Construction is not the only way an options object is made: ``eqx.tree_at`` (the usual Equinox
way to change one field) and ``dataclasses.replace`` bypass ``__check_init__``. The entry points
that run a solver (:func:`ceemx.fit`, :func:`ceemx.smooth`) therefore check it again with
:func:`recheck`, once, before any compute.

What the numbers may be, beyond their kind:

- relative tolerances (``rtol``, :func:`check_rtol`): finite, ≥ 0 and < 1. A stopping rule
  "improvement ≤ rtol·|objective|" with rtol ≥ 1 declares convergence while an iteration still
  removes as much misfit as it leaves;
- Marquardt damping (``damping``, :func:`check_damping`): finite, > 0, and with
  ``damping·rtol < 1``. λ = 0 never grows after a rejected step (λ·ν = 0), so a rejected
  Gauss–Newton step is tried again unchanged until the trials run out; a λ with λ·rtol ≥ 1
  shortens the first step (Marquardt's scaling: by 1/(1 + λ) along each variable) until its
  predicted decrease is below ``rtol·|objective|`` whatever the start — "converged" at once;
- integers (:func:`check_int`): at most 2³¹ − 1, since JAX carries them as int32 (a larger
  ``max_steps`` would wrap, silently, to a negative or small bound).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Collection
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

__all__ = [
    "INT32_MAX",
    "check_bool",
    "check_callable",
    "check_choice",
    "check_damping",
    "check_int",
    "check_key",
    "check_nonnegative",
    "check_path",
    "check_positive",
    "check_real",
    "check_rtol",
    "recheck",
]

#: The largest integer option: counts (steps, epochs, particles, widths) become int32 loop bounds
#: and shapes in JAX, where a larger Python int fails late (``OverflowError`` naming no option)
#: or wraps to a negative or small bound.
INT32_MAX = 2**31 - 1


def check_real(name: str, value: Any) -> np.ndarray | None:
    """``value`` as a 0-d float64 NumPy array (``None`` if traced); ``TypeError`` otherwise.

    Real numbers and 0-d real arrays are accepted; booleans, strings, ``None``, complex values and
    sequences or arrays of several numbers are not (every option checked here is one number).
    """
    if isinstance(value, Tracer):
        return None
    if isinstance(value, bool | np.bool_ | str | bytes) or value is None:
        raise TypeError(f"`{name}` must be a real number; got {value!r}.")
    try:
        a = np.asarray(value)
    except Exception:  # noqa: BLE001 — any object NumPy cannot read is the wrong kind
        raise TypeError(f"`{name}` must be a real number; got {value!r}.") from None
    if a.dtype == bool or not (
        np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)
    ):
        raise TypeError(f"`{name}` must be a real number; got {value!r}.")
    if a.ndim:
        raise TypeError(f"`{name}` must be one real number; got shape {a.shape}: {value!r}.")
    return a.astype(np.float64)


def check_nonnegative(name: str, value: Any) -> None:
    """Raise unless ``value`` is real, finite and >= 0 (tolerances, trust regions, damping)."""
    a = check_real(name, value)
    if a is not None and not (np.all(np.isfinite(a)) and np.all(a >= 0)):
        raise ValueError(f"`{name}` must be finite and >= 0; got {value!r}.")


def check_positive(name: str, value: Any, *, allow_inf: bool = False) -> None:
    """Raise unless ``value`` is real and > 0 (and finite unless ``allow_inf``)."""
    a = check_real(name, value)
    if a is None:
        return
    finite = np.all(~np.isnan(a)) if allow_inf else np.all(np.isfinite(a))
    if not (finite and np.all(a > 0)):
        what = "> 0 (inf allowed)" if allow_inf else "finite and > 0"
        raise ValueError(f"`{name}` must be {what}; got {value!r}.")


def check_level(name: str, value: Any) -> float:
    """``value`` as a float, or raise unless it is a real number in (0, 1) (a confidence level)."""
    ok = isinstance(value, (int, float, np.floating)) and not isinstance(value, bool)
    if not ok or not 0.0 < float(value) < 1.0:
        raise ValueError(f"`{name}` must be a number in (0, 1); got {value!r}.")
    return float(value)


def check_int(
    name: str, value: Any, minimum: int, *, none: bool = False, maximum: int = INT32_MAX
) -> int | None:
    """``value`` as an integer in [``minimum``, ``maximum``] (``None`` passes if ``none``).

    A bool is not an int here (``max_steps=True`` is a mistake, not 1). The upper bound defaults
    to :data:`INT32_MAX`: JAX counts in int32, where ``2**31`` steps would wrap.
    """
    if value is None and none:
        return None
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        kind = "an integer or None" if none else "an integer"
        raise TypeError(f"`{name}` must be {kind}; got {value!r}.")
    if value < minimum:
        raise ValueError(f"`{name}` must be an integer >= {minimum}; got {value}.")
    if value > maximum:
        why = " (2**31 - 1: counts are int32 in JAX)" if maximum == INT32_MAX else ""
        raise ValueError(f"`{name}` must be an integer <= {maximum}{why}; got {value}.")
    return int(value)


def check_rtol(name: str, value: Any) -> None:
    """Raise unless ``value`` is real, finite, >= 0 and < 1 (a relative tolerance)."""
    check_nonnegative(name, value)
    a = check_real(name, value)
    if a is not None and not np.all(a < 1):
        raise ValueError(
            f"`{name}` must be < 1 (a relative tolerance: at 1 or more an iteration that still "
            f"removes as much misfit as it leaves counts as converged); got {value!r}."
        )


def check_damping(name: str, value: Any, rtol: Any) -> None:
    """Raise unless ``value`` is a usable initial Marquardt damping for relative tolerance ``rtol``.

    Finite and > 0 (λ = 0 never grows after a rejection), and ``value·rtol < 1`` (a larger λ
    makes the first step's predicted decrease smaller than ``rtol·|objective|`` at any start:
    the iteration would stop at once, "converged"). See the module notes.
    """
    a = check_real(name, value)
    if a is None:
        return
    if not (np.all(np.isfinite(a)) and np.all(a > 0)):
        raise ValueError(
            f"`{name}` must be finite and > 0 (a damping of 0 never grows after a rejected "
            f"step, so the step is retried unchanged); got {value!r}."
        )
    try:
        r = check_real("rtol", rtol)
    except TypeError:  # the tolerance's own check names it
        return
    if r is not None and 0 <= float(r) < 1 and float(a) * float(r) >= 1.0:
        raise ValueError(
            f"`{name}` = {value!r} with rtol = {rtol!r}: the initial damping must be below "
            f"1/rtol = {1.0 / float(r):.3g}. Marquardt's damping shortens the first step by "
            "about 1/(1 + damping), so its predicted decrease falls below the tolerance "
            "rtol·|objective| at any start and the iteration stops at once, 'converged'."
        )


def recheck(options: Any) -> None:
    """Run again every check made when ``options`` and the modules it holds were constructed.

    ``eqx.tree_at`` and ``dataclasses.replace`` build Equinox modules without calling their
    ``__check_init__``: a solver whose ``rho_x`` was set to −1 that way would run. Entry points
    call this once, before any compute; each module's checks run as Equinox runs them (every
    ``__check_init__`` of its classes), the modules it holds (a solver's smoother and learner)
    first.

    Raises:
        TypeError, ValueError: as the module's own checks, naming the option.
    """
    seen: set[int] = set()

    def visit(node: Any) -> None:
        if not isinstance(node, eqx.Module) or id(node) in seen:
            return
        seen.add(id(node))
        for field in dataclasses.fields(node):
            value = getattr(node, field.name, None)
            for item in value if isinstance(value, list | tuple) else (value,):
                visit(item)
        for kls in type(node).__mro__:
            check = kls.__dict__.get("__check_init__")
            if check is not None:
                check(node)

    visit(options)


def check_bool(name: str, value: Any, *, none: bool = False) -> None:
    """Raise ``TypeError`` unless ``value`` is ``True`` or ``False`` (or ``None`` if ``none``).

    Truthy stand-ins are refused: ``covariance="False"`` would otherwise mean True.
    """
    if value is None and none:
        return
    if not isinstance(value, bool | np.bool_):
        kind = "True, False or None" if none else "True or False"
        raise TypeError(f"`{name}` must be {kind}; got {_short(value)}.")


def check_callable(name: str, value: Any, *, none: bool = False) -> None:
    """Raise ``TypeError`` unless ``value`` is callable (or ``None`` if ``none``)."""
    if (value is None and none) or callable(value):
        return
    kind = "a callable or None" if none else "a callable"
    raise TypeError(f"`{name}` must be {kind}; got {_short(value)}.")


def check_path(name: str, value: Any, *, none: bool = False) -> str | None:
    """``value`` as a ``str`` path: a ``str`` or ``os.PathLike`` of one (``None`` if ``none``)."""
    if value is None and none:
        return None
    path = os.fspath(value) if isinstance(value, str | os.PathLike) else None
    if not isinstance(path, str):
        kind = "a path (str or os.PathLike)" + (" or None" if none else "")
        raise TypeError(f"`{name}` must be {kind}; got {_short(value)}.")
    return path


def check_choice(name: str, value: Any, choices: Collection[Any]) -> None:
    """Raise ``ValueError`` unless ``value`` is one of ``choices`` (listed in the message)."""
    if not any(value is c or (type(value) is type(c) and value == c) for c in choices):
        listed = ", ".join(repr(c) for c in choices)
        raise ValueError(f"`{name}` must be one of {listed}; got {value!r}.")


def check_key(value: Any, name: str = "key") -> None:
    """Raise unless ``value`` is a JAX PRNG key: typed (``jax.random.key``) or raw uint32.

    A raw key is what ``jax.random.PRNGKey(seed)`` returns: a 1-D ``uint32`` array (two words for
    the default threefry implementation). Batches of keys are refused (one fit, one key).
    """
    if isinstance(value, Tracer):
        return
    if isinstance(value, jax.Array | np.ndarray):
        if jnp.issubdtype(value.dtype, jax.dtypes.prng_key):
            if value.shape == ():
                return
            raise ValueError(f"`{name}` must be a single PRNG key; got shape {value.shape}.")
        if value.dtype == np.uint32 and value.ndim == 1 and value.shape[0] >= 2:
            return
    raise TypeError(
        f"`{name}` must be a JAX PRNG key such as jax.random.key(0) or jax.random.PRNGKey(0); "
        f"got {_short(value)}."
    )


def _short(value: Any) -> str:
    if isinstance(value, jax.Array | np.ndarray):
        return f"an array of dtype {value.dtype} and shape {value.shape}"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
