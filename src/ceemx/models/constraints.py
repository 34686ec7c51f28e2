"""Parameter constraints: a model holds θ in natural units, fits learn it in unconstrained ones.

A field of a system declares its constraint in its dataclass metadata with :func:`param`::

    class Tank(ceemx.AbstractContinuousSystem):
        k1: Array = ceemx.param(positive=True)           # k1 > 0
        a: Array = ceemx.param(lower=0.0, upper=1.0)     # 0 < a < 1
        g: Array = ceemx.param(fixed=True)               # never learned

The system always holds natural values (what the equations use). A constraint is a bijection
x = forward(z) from R onto the allowed set, applied elementwise; :class:`ceemx.FitProblem` learns
z = inverse(x) and builds the system with forward(z), so every solver, learner and checkpoint works
in unconstrained coordinates and every system it returns is in natural units (the dynamax
``ParameterProperties`` idea, with the constraint on the field instead of in a parallel tree).

========================= ============================ ============================================
constraint                x = forward(z)               allowed set
========================= ============================ ============================================
:class:`Unconstrained`    z                            R
:class:`Positive`         softplus(z)                  (0, ∞)
:class:`GreaterThan`      lower + softplus(z)          (lower, ∞)
:class:`LessThan`         upper − softplus(−z)         (−∞, upper)
:class:`Interval`         lower + (upper − lower)·σ(z) (lower, upper)
:class:`Fixed`            z (never trainable)          its value
========================= ============================ ============================================

Softplus, not exp: far from the bound softplus(z) ≈ z, so a parameter of size 10 is learned on
nearly its own scale (Gauss–Newton and Levenberg–Marquardt see almost the unconstrained problem and
exp's overflow for z ≳ 700 cannot happen), while near the bound softplus(z) ≈ eᶻ gives the
log-scale behaviour that keeps iterates strictly inside. For a strictly positive floor (e.g. a
scale that is used in a logarithm) declare ``param(lower=eps)``.

A constraint on a field applies to every array leaf below it, so a field holding a sub-module can be
fixed or bounded as a whole; the outermost declaration wins. Constraints inside nested modules are
found by walking the module tree and reading each Equinox module's dataclass field metadata. Values
are checked against them by :mod:`ceemx.models.constraint_checks`.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Float

from ceemx.lib.tree import as_jax

__all__ = [
    "CONSTRAINT_KEY",
    "DESCRIPTION_KEY",
    "UNIT_KEY",
    "child_of",
    "AbstractConstraint",
    "Fixed",
    "GreaterThan",
    "Interval",
    "LessThan",
    "Positive",
    "Unconstrained",
    "constraint_at",
    "field_constraint",
    "leaf_constraints",
    "param",
]

CONSTRAINT_KEY = "ceemx.constraint"
"""The dataclass-metadata key under which :func:`param` stores a field's constraint."""
UNIT_KEY = "ceemx.unit"
"""The key of a :func:`param`'s unit (the summary's unit column)."""
DESCRIPTION_KEY = "ceemx.description"
"""The key of a :func:`param`'s description (named under the summary's table)."""


def _softplus(z):
    return jax.nn.softplus(z)


def _softplus_inverse(y):
    # log(eʸ − 1) = y + log(1 − e⁻ʸ), stable for large and small y > 0.
    return y + jnp.log(-jnp.expm1(-y))


class AbstractConstraint(eqx.Module):
    """An elementwise bijection x = forward(z) from R onto the allowed set of a parameter.

    Subclasses implement :meth:`forward`, :meth:`inverse` (both traceable and differentiable),
    :meth:`contains` (host-side, NumPy) and :attr:`description` (used in error messages).
    ``trainable`` is ``False`` for a parameter that never learns (:class:`Fixed`).
    """

    trainable: ClassVar[bool] = True

    @abc.abstractmethod
    def forward(self, z: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """Natural value x from the unconstrained z."""

    @abc.abstractmethod
    def inverse(self, x: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """Unconstrained z from the natural value x (x must satisfy :meth:`contains`)."""

    @abc.abstractmethod
    def contains(self, x: np.ndarray) -> np.ndarray:
        """Elementwise: whether each entry of ``x`` (a NumPy array) is allowed."""

    @property
    @abc.abstractmethod
    def description(self) -> str:
        """The allowed set in words, e.g. ``"> 0 (positive)"``."""

    @property
    def bounds(self) -> tuple[float, float]:
        """(lower, upper) of the allowed set (±inf where unbounded; default: none)."""
        return (-math.inf, math.inf)


class _AbstractIdentity(AbstractConstraint):
    """x = z with every value allowed (what :class:`Unconstrained` and :class:`Fixed` share)."""

    def forward(self, z: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """Z."""
        return z

    def inverse(self, x: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """X."""
        return x

    def contains(self, x: np.ndarray) -> np.ndarray:
        """Every value is allowed."""
        return np.ones(np.shape(x), bool)


class Unconstrained(_AbstractIdentity):
    """No constraint: x = z."""

    @property
    def description(self) -> str:
        """``"unconstrained"``."""
        return "unconstrained"


class Fixed(_AbstractIdentity):
    """A parameter that never learns: dropped from θ whatever ``trainable`` says."""

    trainable: ClassVar[bool] = False

    @property
    def description(self) -> str:
        """``"fixed"``."""
        return "fixed"


class Positive(AbstractConstraint):
    """x > 0 through x = softplus(z) = log(1 + eᶻ)."""

    def forward(self, z: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """softplus(z)."""
        return _softplus(z)

    def inverse(self, x: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """log(eˣ − 1)."""
        return _softplus_inverse(x)

    def contains(self, x: np.ndarray) -> np.ndarray:
        """X > 0."""
        return np.asarray(np.asarray(x) > 0)

    @property
    def description(self) -> str:
        """``"> 0 (positive)"``."""
        return "> 0 (positive)"

    @property
    def bounds(self) -> tuple[float, float]:
        """(0, inf)."""
        return (0.0, math.inf)


class GreaterThan(AbstractConstraint):
    """x > lower through x = lower + softplus(z).

    Attributes:
        lower: the bound (a Python float).
    """

    lower: float = eqx.field(static=True)

    def __init__(self, lower: float | int):
        self.lower = _finite_float("lower", lower)

    def forward(self, z: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """Lower + softplus(z)."""
        return self.lower + _softplus(z)

    def inverse(self, x: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """log(e^(x − lower) − 1)."""
        return _softplus_inverse(x - self.lower)

    def contains(self, x: np.ndarray) -> np.ndarray:
        """X > lower."""
        return np.asarray(np.asarray(x) > self.lower)

    @property
    def description(self) -> str:
        """``"> lower"``."""
        return f"> {self.lower:g}"

    @property
    def bounds(self) -> tuple[float, float]:
        """(lower, inf)."""
        return (self.lower, math.inf)


class LessThan(AbstractConstraint):
    """x < upper through x = upper − softplus(−z) (increasing in z).

    Attributes:
        upper: the bound (a Python float).
    """

    upper: float = eqx.field(static=True)

    def __init__(self, upper: float | int):
        self.upper = _finite_float("upper", upper)

    def forward(self, z: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """Upper − softplus(−z)."""
        return self.upper - _softplus(-z)

    def inverse(self, x: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """−log(e^(upper − x) − 1)."""
        return -_softplus_inverse(self.upper - x)

    def contains(self, x: np.ndarray) -> np.ndarray:
        """X < upper."""
        return np.asarray(np.asarray(x) < self.upper)

    @property
    def description(self) -> str:
        """``"< upper"``."""
        return f"< {self.upper:g}"

    @property
    def bounds(self) -> tuple[float, float]:
        """(-inf, upper)."""
        return (-math.inf, self.upper)


class Interval(AbstractConstraint):
    """lower < x < upper through x = lower + (upper − lower)·sigmoid(z).

    Attributes:
        lower, upper: the bounds (Python floats, lower < upper).
    """

    lower: float = eqx.field(static=True)
    upper: float = eqx.field(static=True)

    def __init__(self, lower: float | int, upper: float | int):
        self.lower = _finite_float("lower", lower)
        self.upper = _finite_float("upper", upper)
        if not self.lower < self.upper:
            raise ValueError(f"`lower` must be < `upper`; got {self.lower} and {self.upper}.")

    def forward(self, z: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """Lower + (upper − lower)·sigmoid(z)."""
        return self.lower + (self.upper - self.lower) * jax.nn.sigmoid(z)

    def inverse(self, x: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
        """logit((x − lower)/(upper − lower))."""
        p = (x - self.lower) / (self.upper - self.lower)
        return jnp.log(p) - jnp.log1p(-p)

    def contains(self, x: np.ndarray) -> np.ndarray:
        """Lower < x < upper."""
        x = np.asarray(x)
        return np.asarray((x > self.lower) & (x < self.upper))

    @property
    def description(self) -> str:
        """``"in (lower, upper)"``."""
        return f"in ({self.lower:g}, {self.upper:g})"

    @property
    def bounds(self) -> tuple[float, float]:
        """(lower, upper)."""
        return (self.lower, self.upper)


def _finite_float(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(f"`{name}` must be a real number; got {value!r}.")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"`{name}` must be finite; got {value}.")
    return value


def _as_parameter(value: Any) -> Any:
    """A :func:`param` field's converter: numbers and arrays become floating JAX arrays.

    Python scalars stay weakly typed (they take the dtype of the arrays they meet); integer
    arrays become the default float dtype (an integer leaf would silently never learn); anything
    else (a sub-module, ``None``) is left as it is.
    """
    if isinstance(value, bool):
        raise TypeError(f"a parameter must be a number or an array; got {value!r}.")
    if isinstance(value, int | float):
        return jnp.asarray(float(value))
    if isinstance(value, np.ndarray | np.generic | jax.Array):
        host = not isinstance(value, jax.Array)  # host data: converted there, then a transfer
        a = np.asarray(value, jax.dtypes.canonicalize_dtype(value.dtype)) if host else value
        if not jnp.issubdtype(a.dtype, jnp.inexact):
            a = a.astype(jnp.result_type(float))
        return as_jax(a) if host else a
    return value


if TYPE_CHECKING:
    # Type checkers synthesise a dataclass's __init__ only from the field specifiers Equinox
    # declares (``eqx.field``); seen as ``eqx.field``, a ``param`` field without ``default`` is a
    # required argument for them too, as it is at run time.
    param = eqx.field
else:

    def param(
        *,
        positive: bool = False,
        lower: float | int | None = None,
        upper: float | int | None = None,
        fixed: bool = False,
        constraint: AbstractConstraint | None = None,
        converter: Callable[[Any], Any] | None = _as_parameter,
        unit: str | None = None,
        description: str | None = None,
        **field_kwargs: Any,
    ) -> Any:
        """A system field that is a parameter, with an optional constraint (an ``eqx.field``).

        Args:
            positive: x > 0 (:class:`Positive`).
            lower: x > lower (:class:`GreaterThan`), or with ``upper`` lower < x < upper
                (:class:`Interval`).
            upper: x < upper (:class:`LessThan`), or with ``lower`` an :class:`Interval`.
            fixed: never learned (:class:`Fixed`), whatever ``trainable`` selects.
            constraint: any :class:`AbstractConstraint` instead of the flags above.
            converter: applied to the value when the system is built (Equinox converter); the
                default turns numbers and integer or NumPy arrays into floating JAX arrays (Python
                scalars stay weakly typed) and leaves sub-modules alone. ``None``: no conversion.
            unit: the parameter's unit, e.g. ``"1/s"`` (the summary's unit column).
            description: what it is, in a few words (the summary's notes name it).
            **field_kwargs: passed to ``eqx.field`` (``default``, ``default_factory``, ``metadata``,
                ...).

        Returns:
            A dataclass field whose metadata holds the constraint under :data:`CONSTRAINT_KEY`.

        Raises:
            ValueError: for contradictory flags (e.g. ``positive`` with ``lower``, ``fixed`` with a
                bound, ``lower >= upper``) or ``static=True`` (a static field is not a parameter).

        Example:
            >>> class Decay(ceemx.AbstractContinuousSystem):  # doctest: +SKIP
            ...     a: Array = ceemx.param(positive=True)
        """
        if field_kwargs.get("static", False):
            raise ValueError("a `param` cannot be static: static fields are not leaves of θ.")
        chosen = [
            name
            for name, on in (
                ("positive", positive),
                ("lower/upper", lower is not None or upper is not None),
                ("fixed", fixed),
                ("constraint", constraint is not None),
            )
            if on
        ]
        if len(chosen) > 1:
            raise ValueError(f"`param` takes one kind of constraint; got {' and '.join(chosen)}.")
        if constraint is not None:
            if not isinstance(constraint, AbstractConstraint):
                raise TypeError(
                    "`constraint` must be a ceemx AbstractConstraint; got "
                    f"{type(constraint).__name__}."
                )
            c = constraint
        elif positive:
            c = Positive()
        elif fixed:
            c = Fixed()
        elif lower is not None and upper is not None:
            c = Interval(lower, upper)
        elif lower is not None:
            c = GreaterThan(lower)
        elif upper is not None:
            c = LessThan(upper)
        else:
            c = Unconstrained()
        metadata = dict(field_kwargs.pop("metadata", {}))
        metadata[CONSTRAINT_KEY] = c
        metadata.update(_labels(unit=unit, description=description))
        return eqx.field(converter=converter, metadata=metadata, **field_kwargs)


def _labels(**texts: str | None) -> dict[str, str]:
    """A :func:`param`'s ``unit`` and ``description`` as metadata (strings, or refused)."""
    out = {}
    for name, text in texts.items():
        if text is not None:
            if not isinstance(text, str):
                raise TypeError(f"`{name}` must be a string; got {text!r}.")
            out[UNIT_KEY if name == "unit" else DESCRIPTION_KEY] = text
    return out


_UNCONSTRAINED = Unconstrained()


def field_constraint(module: Any, name: str) -> AbstractConstraint | None:
    """The constraint declared on field ``name`` of a dataclass ``module``, or ``None``."""
    if not dataclasses.is_dataclass(module):
        return None
    for f in dataclasses.fields(module):
        if f.name == name:
            return f.metadata.get(CONSTRAINT_KEY)
    return None


def child_of(node: Any, key: Any) -> tuple[bool, Any]:
    """``(found, child)``: the child of ``node`` at one key of a pytree path."""
    if isinstance(key, jtu.GetAttrKey):
        return True, getattr(node, key.name)
    if isinstance(key, jtu.SequenceKey):
        return True, node[key.idx]
    if isinstance(key, jtu.DictKey):
        return True, node[key.key]
    return False, None  # a custom node without keys: nothing below it is declared


def constraint_at(tree: Any, path: tuple) -> AbstractConstraint:
    """The constraint of the leaf at key ``path`` of ``tree`` (see :func:`leaf_constraints`)."""
    node = tree
    for key in path:
        if isinstance(node, eqx.Module) and isinstance(key, jtu.GetAttrKey):
            c = field_constraint(node, key.name)
            if c is not None:
                return c
        ok, node = child_of(node, key)
        if not ok:
            break
    return _UNCONSTRAINED


def leaf_constraints(tree: Any) -> list[AbstractConstraint]:
    """The constraint of every leaf of ``tree``, in ``jax.tree_util.tree_leaves`` order.

    A leaf takes the constraint declared (by :func:`param`) on the outermost field above it in the
    module tree; :class:`Unconstrained` when there is none.
    """
    pairs, _ = jtu.tree_flatten_with_path(tree)
    return [constraint_at(tree, path) for path, _ in pairs]
