"""Near-null directions of a curvature matrix, and names for what they leave determined.

Host-side NumPy (a P × P eigen-analysis, P the number of parameters): no JAX program, so no
LAPACK call runs beside another one in a compiled program.

A curvature matrix S of a log-likelihood (in nats) is analysed in *relative* coordinates
r = θ / c (``scale`` c per variable): a direction u (unit in r) with eigenvalue λ of C S C changes
the log-likelihood by ½ λ for a unit move, so its standard deviation is λ^(-1/2) in units of c.
With c chosen so that a unit of r is a change by a factor e of a positive parameter (log
coordinates), λ < 1 means the data do not determine the direction to within a factor e:
:func:`near_null_space` returns those directions, and those that are zero to rounding
(λ ≤ ``rcond``·λ_max).

:func:`describe_null_space` names what such a null space leaves determined: in log coordinates an
integer null vector k (e.g. (1, −1, −1) over a, b, c) is a symmetry θ_i → θ_i·s^(k_i), and what the
data determine are the monomials Π θ_i^(m_i) with integer m orthogonal to every null vector (a·b,
a·c). It looks for a small-integer basis of that orthogonal complement (entries in −2…2, fewest
nonzero entries first, then fewest negative ones); a null direction carried by one variable names
that variable; anything else (no such basis, or variables that can be zero or change sign) is named
by its involved variables and its coefficients in natural units.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence

import numpy as np

__all__ = [
    "NullSpaceNames",
    "describe_null_space",
    "integer_complement",
    "monomial",
    "near_null_space",
    "share_in",
]

#: a variable takes part in a null direction when its squared loading is at least this (1 %)
INVOLVED = 1e-4
#: an integer vector is (close to) orthogonal to the null space when its projection on it is
#: at most this fraction of its length (exact symmetries give rounding-level projections)
INTEGER_TOL = 1e-2
#: entries of the integer vectors searched: −MAX_EXPONENT…MAX_EXPONENT
MAX_EXPONENT = 2
#: the integer search runs over (2·MAX_EXPONENT + 1)^m vectors: at most this many variables m
MAX_INTEGER_SIZE = 8
#: a null direction is "carried by one variable" when its largest entry is this many times the next
DOMINANT = 10.0
#: a sentence names at most this many variables (the most involved), and counts the rest
MAX_NAMED = 8
#: the text has at most this many sentences (groups); the others are counted
MAX_SENTENCES = 6

_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")


def near_null_space(
    S: np.ndarray, scale: np.ndarray, *, floor: float = 1.0, rcond: float = 1e-10
) -> tuple[np.ndarray, np.ndarray]:
    """The directions of ``C S C`` (``C = diag(scale)``) with eigenvalue below the threshold.

    Args:
        S: (P, P) symmetric curvature (a Gauss–Newton matrix or Schur complement).
        scale: (P,) nonzero scale of each variable (the relative coordinates r = θ / scale;
            negative for a log coordinate of a negative parameter).
        floor: absolute eigenvalue threshold in relative coordinates (1: a unit move of r changes
            the log-likelihood by less than ½ nat).
        rcond: relative threshold: eigenvalues ≤ ``rcond``·λ_max are zero to rounding.

    Returns:
        ``(eigenvalues, basis)``: the k eigenvalues below max(``floor``, ``rcond``·λ_max) in
        ascending order and a (P, k) orthonormal basis of their eigenvectors in relative
        coordinates. k = 0 when ``S`` is not finite.
    """
    S = np.asarray(S, dtype=np.float64)
    c = np.asarray(scale, dtype=np.float64)
    P = S.shape[0]
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(c))):
        return np.zeros((0,)), np.zeros((P, 0))
    M = c[:, None] * S * c[None, :]
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    null = w < max(floor, rcond * max(float(w[-1]), 0.0))
    return w[null], V[:, null]


def share_in(basis: np.ndarray, step: np.ndarray) -> float:
    """‖projection of ``step`` on span(``basis``)‖² / ‖step‖² (0 for a zero step)."""
    step = np.asarray(step, dtype=np.float64)
    total = float(step @ step)
    if not total > 0.0:
        return 0.0
    along = basis.T @ step
    return float(along @ along) / total


def monomial(exponents: Sequence[int] | np.ndarray, names: Sequence[str]) -> str:
    """``(1, 1, 0), (a, b, c)`` → ``"a·b"``; ``(1, -2)`` → ``"a/b²"``; ``(0, -1)`` → ``"1/b"``."""

    def power(name: str, k: int) -> str:
        return name if k == 1 else f"{name}{str(k).translate(_SUPERSCRIPT)}"

    up = [power(n, int(k)) for n, k in zip(names, exponents, strict=True) if k > 0]
    down = [power(n, -int(k)) for n, k in zip(names, exponents, strict=True) if k < 0]
    text = "·".join(up) if up else "1"
    if down:
        text += "/" + (down[0] if len(down) == 1 else "(" + "·".join(down) + ")")
    return text


def integer_complement(
    basis: np.ndarray, *, max_abs: int = MAX_EXPONENT, tol: float = INTEGER_TOL
) -> np.ndarray | None:
    """A small-integer basis of the orthogonal complement of span(``basis``), or ``None``.

    Args:
        basis: (m, k) orthonormal columns (k < m, m ≤ :data:`MAX_INTEGER_SIZE`).
        max_abs: entries of the candidate vectors range over −max_abs…max_abs.
        tol: a candidate v is orthogonal when ‖basisᵀ v‖ ≤ tol·‖v‖.

    Returns:
        (m − k, m) integer rows, each with its first nonzero entry positive and no common
        factor, chosen greedily (linearly independent) in the order: fewest nonzero entries,
        fewest negative entries, smallest largest entry, earliest variables; ``None`` when the
        candidates do not span the complement (the null space is not spanned by small-integer
        vectors) or m is too large.
    """
    m, k = basis.shape
    need = m - k
    if need == 0:
        return np.zeros((0, m), int)
    if m > MAX_INTEGER_SIZE:
        return None
    grid = np.array(list(itertools.product(range(-max_abs, max_abs + 1), repeat=m)), int)
    nonzero = grid != 0
    first = np.argmax(nonzero, axis=1)
    keep = nonzero.any(axis=1) & (grid[np.arange(len(grid)), first] > 0)
    grid = grid[keep]
    grid = grid[np.gcd.reduce(np.abs(grid), axis=1) == 1]
    length = np.linalg.norm(grid, axis=1)
    off = np.linalg.norm(grid @ basis, axis=1) / length
    cand = grid[off <= tol]
    if len(cand) < need:
        return None

    def order(v: np.ndarray):
        nz = np.flatnonzero(v)
        return (len(nz), int(np.sum(v < 0)), int(np.max(np.abs(v))), tuple(nz), tuple(-v))

    chosen: list[np.ndarray] = []
    for v in sorted(cand, key=order):
        trial = np.array([*chosen, v], float)
        if np.linalg.matrix_rank(trial, tol=1e-8) == len(trial):
            chosen.append(v)
            if len(chosen) == need:
                return np.array(chosen, int)
    return None


@dataclasses.dataclass(frozen=True)
class NullSpaceNames:
    """What a null space leaves determined, in words (:func:`describe_null_space`).

    Attributes:
        text: one sentence per group of variables that share null directions, joined by "; ".
        determined: the determined monomials, e.g. ``("a·b", "a·c")``.
        exponents: for each determined monomial, its ``(name, exponent)`` pairs.
        undetermined: the variables taking part in a null direction, in order.
    """

    text: str
    determined: tuple[str, ...]
    exponents: tuple[tuple[tuple[str, int], ...], ...]
    undetermined: tuple[str, ...]


def _groups(basis: np.ndarray) -> list[list[int]]:
    """Variables that share null directions: connected components of |(V Vᵀ)_ij| ≥ INVOLVED."""
    proj = basis @ basis.T
    involved = np.flatnonzero(np.diagonal(proj) >= INVOLVED)
    left = set(involved.tolist())
    groups = []
    while left:
        todo, group = [min(left)], []
        left.discard(todo[0])
        while todo:
            i = todo.pop()
            group.append(i)
            near = [j for j in left if abs(proj[i, j]) >= INVOLVED]
            left.difference_update(near)
            todo += near
        groups.append(sorted(group))
    return groups


def _listing(items: Sequence[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _most_involved(U: np.ndarray, names: Sequence[str]) -> str:
    """The :data:`MAX_NAMED` variables most involved in the directions U; the rest counted."""
    order = np.argsort(-np.sum(U**2, axis=1), kind="stable")[:MAX_NAMED]
    rest = len(names) - len(order)
    return ", ".join(names[int(i)] for i in order) + f" and {rest} more"


def _number(v: float) -> str:
    return f"{v:.2g}"


def describe_null_space(
    basis: np.ndarray,
    names: Sequence[str],
    loggable: np.ndarray,
    natural: np.ndarray,
) -> NullSpaceNames:
    """Name the null space of a curvature matrix by what it leaves determined (module notes).

    Args:
        basis: (P, k) orthonormal null directions in relative coordinates
            (:func:`near_null_space`).
        names: (P,) the variables' names.
        loggable: (P,) whether each variable's relative coordinate is its log (a positive or
            nonzero parameter): only groups of such variables are named by monomials.
        natural: (P,) the change of each variable in natural units per unit of its relative
            coordinate (for the coefficients of the fallback description).

    Returns:
        A :class:`NullSpaceNames`; its ``text`` reads, per group, "only a·b and a·c are
        determined by the data (a, b, c individually are not)", "parameter `x` is not
        determined by the data", or "the data do not determine a and b along
        Δa : Δb = 1 : −0.5 (natural units)"; a group of more than :data:`MAX_NAMED` variables
        (a learned term's weights) names its most involved few and counts the rest, and beyond
        :data:`MAX_SENTENCES` groups the others are counted: the text stays a few lines
        whatever the number of parameters (``undetermined`` lists them all).
    """
    sentences: list[str] = []
    determined: list[str] = []
    exponents: list[tuple[tuple[str, int], ...]] = []
    undetermined: list[str] = []
    for group in _groups(basis):
        sub = basis[group]
        # The null directions restricted to the group: eigenvectors of its block of V Vᵀ.
        w, U = np.linalg.eigh(sub @ sub.T)
        U = U[:, w > 0.5]
        gnames = [names[i] for i in group]
        if U.shape[1] == 1:
            mag = np.sort(np.abs(U[:, 0]))[::-1]
            if len(group) == 1 or mag[0] >= DOMINANT * mag[1]:
                top = gnames[int(np.argmax(np.abs(U[:, 0])))]
                undetermined.append(top)
                sentences.append(f"parameter `{top}` is not determined by the data")
                continue
        undetermined += gnames
        if len(group) > MAX_NAMED:  # a learned term's weights: name the few, count the rest
            k = U.shape[1]
            sentences.append(
                f"{k} direction{'s' if k > 1 else ''} among {len(group)} parameters "
                f"({_most_involved(U, gnames)}) {'are' if k > 1 else 'is'} not determined by "
                "the data"
            )
            continue
        if U.shape[1] == len(group):
            sentences.append(f"{_listing(gnames)} are not determined by the data")
            continue
        rows = integer_complement(U) if np.all(loggable[group]) else None
        if rows is not None:
            words = [monomial(r, gnames) for r in rows]
            determined += words
            exponents += [
                tuple((n, int(k)) for n, k in zip(gnames, r, strict=True) if k) for r in rows
            ]
            sentences.append(
                f"only {_listing(words)} {'is' if len(words) == 1 else 'are'} determined by the "
                f"data ({', '.join(gnames)} individually are not)"
            )
            continue
        sentences += _direction_sentences(U, gnames, natural[group])
    return NullSpaceNames(
        "; ".join(_bounded(sentences)), tuple(determined), tuple(exponents), tuple(undetermined)
    )


def _direction_sentences(U: np.ndarray, names: Sequence[str], natural: np.ndarray) -> list[str]:
    """One sentence per null direction ``U[:, j]`` of a group, as a ratio in natural units."""
    sentences = []
    deltas = " : ".join(f"Δ{n}" for n in names)
    for u in U.T:
        d = u * natural
        d = d / d[np.argmax(np.abs(d))]
        ratio = " : ".join(_number(v) for v in d)
        sentences.append(
            f"the data do not determine {_listing(names)} along {deltas} = {ratio} (natural units)"
        )
    return sentences


def _bounded(sentences: list[str]) -> list[str]:
    """At most :data:`MAX_SENTENCES` sentences, the rest counted in the last."""
    if len(sentences) <= MAX_SENTENCES:
        return sentences
    rest = len(sentences) - MAX_SENTENCES + 1
    return sentences[: MAX_SENTENCES - 1] + [
        f"{rest} more groups of parameters are not determined by the data (the analysis's "
        "`undetermined` lists every parameter)"
    ]
