"""What a fit found, for a person: :meth:`ceemx.FitResult.summary` and ``repr(result)``.

:func:`fit_summary` writes, in plain text or Markdown (like statsmodels' ``summary()`` or MATLAB's
``present``):

1. one line: the solver (each stage's, for a path of several), whether it converged and in how
   many epochs;
2. the trainable parameters, named as written in the system (``M``, ``H[2,3]``,
   ``process_noise.scale``), in natural units: estimate, standard error, the 95 % interval and
   the constraint;
3. which solver ran and why (:attr:`FitResult.choice`: the library's rule when ``fit`` was given
   none — "chosen: …, because …" — or "named by the user"), what the intervals are (the
   method's :attr:`~ceemx.AbstractFitSolver.uncertainty`: certainty-equivalent or Laplace
   evidence), the noise models, J at the start and the end, the data, epochs and time, the
   trajectories' status;
4. the end-of-fit noise check (:attr:`FitResult.noise_check`) and the identifiability analysis
   (:attr:`FitResult.identifiability`) when the fit recorded them; with the noise check, the
   whiteness of the one-step prediction errors (an EKF pass,
   :func:`~ceemx.identification.analysis.diagnostics.prediction_error_check`: the intervals
   assume white errors, and errors that are not white flag a model that misses dynamics or a
   local optimum); on request (``diagnostics=True``), the residual diagnostics of
   :meth:`FitResult.diagnostics` instead (an EKF pass and a Laplace E-step);
5. the messages (per-trajectory statuses grouped, then the fit's own).

**The interval.** The Laplace covariance lives in the unconstrained coordinates z of θ
(:mod:`ceemx.identification.analysis.uncertainty`); the interval is ``forward(ẑ ± q·σ_z)``, the Wald
interval of z mapped to natural units, so it always lies inside the constraint (a positive
parameter's interval never reaches 0) and is ``estimate ± q·SE`` for unconstrained parameters
(q = 1.96 for 95 %). The standard error is the delta-method one, ``forward'(ẑ)·σ_z``. When the
data do not determine some parameters, those are held at their estimates and the others' errors
are conditional on them (``FitResult.covariance(hold_weak=True)``; a message says so), rather than
NaN for every parameter. Where a bound is near or the objective is skewed, the profile-likelihood
interval replaces the Wald one (``intervals="auto"``, the rule of
:mod:`ceemx.identification.analysis.profile_rule`); each interval says its kind.

Nothing here computes on the device except the covariance (one compiled Schur complement per
problem shape, as :meth:`FitResult.covariance`), the EKF pass of the one-step errors (one compiled
filter per system and record length) and, for the few parameters the rule picks, the profiles'
refits; ``uncertainty=False`` skips the covariance and the refits, ``intervals="wald"`` the
refits.
"""

from __future__ import annotations

import textwrap
import warnings
from collections import Counter
from collections.abc import Sequence
from statistics import NormalDist
from typing import Literal

import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from ceemx.identification.analysis.diagnostics import prediction_error_check
from ceemx.identification.analysis.profile_rule import summary_intervals
from ceemx.lib.results import RESULTS, codes
from ceemx.models.constraints import Unconstrained
from ceemx.models.noise import AbstractNoise
from ceemx.models.parameter_meta import entry_labels

__all__ = [
    "ParameterRow",
    "Summary",
    "fit_summary",
    "interval_kind",
    "noise_round_messages",
    "parameter_rows",
    "short_repr",
]

Format = Literal["text", "markdown"]
Intervals = Literal["auto", "wald", "profile"]


class Summary(str):
    """A summary: a ``str`` that shows itself as it reads (no quotes, real line breaks).

    ``print(result.summary())`` and ``result.summary()`` at the prompt show the same table;
    notebooks render the Markdown form (``format="markdown"``) as Markdown.
    """

    __slots__ = ()

    def __repr__(self) -> str:
        return str(self)

    def _repr_markdown_(self) -> str:
        return str(self) if self.lstrip().startswith(("**", "|", "#")) else f"```\n{self}\n```"


class ParameterRow(tuple):
    """One trainable scalar: ``(name, estimate, se, lower, upper, constraint, interval)``.

    Natural units; ``interval`` is the interval's kind: ``"Wald"``, ``"profile"`` (profile
    likelihood, :mod:`ceemx.identification.analysis.profile`; ``"profile, to bound"`` when it
    reaches the constraint's bound, ``"profile, open"`` when it does not close within the
    search) or ``""`` (none computed).
    """

    __slots__ = ()

    def __new__(cls, name: str, estimate, se, lower, upper, constraint: str, interval: str = ""):
        """One row; the numbers as Python floats (NaN where not available)."""
        return super().__new__(
            cls,
            (name, float(estimate), float(se), float(lower), float(upper), constraint, interval),
        )

    name = property(lambda self: self[0], doc="The parameter's name as written, e.g. ``H[2,3]``.")
    estimate = property(lambda self: self[1], doc="The estimate in natural units.")
    se = property(lambda self: self[2], doc="The delta-method standard error (NaN: none).")
    lower = property(lambda self: self[3], doc="The interval's lower end.")
    upper = property(lambda self: self[4], doc="The interval's upper end.")
    constraint = property(lambda self: self[5], doc="The constraint in words.")
    interval = property(lambda self: self[6], doc="The interval's kind (``Wald``, ``profile``).")


def _constraint_words(problem) -> list[str]:
    """One description per entry of θ: each leaf's constraint, repeated over its entries."""
    leaves = jtu.tree_leaves(problem.template)
    constraints = problem.constraints or [Unconstrained()] * len(leaves)
    out: list[str] = []
    for c, leaf in zip(constraints, leaves, strict=True):
        out += [c.description] * int(np.size(leaf))
    return out


def parameter_rows(
    result,
    *,
    level: float = 0.95,
    uncertainty: bool = True,
    intervals: Intervals = "auto",
    max_profiles: int = 3,
) -> tuple[list[ParameterRow], list[str]]:
    """The parameter table of a fit and the notes that go with it.

    Args:
        result: a :class:`ceemx.FitResult` with its ``problem`` (any fit's).
        level: the interval's coverage, in (0, 1).
        uncertainty: compute the Laplace covariance (``False``: estimates only, NaN elsewhere).
        intervals: ``"wald"``, ``"profile"`` (every parameter's profile-likelihood interval: a
            few refits each) or ``"auto"`` (the profile interval for the parameters the rule of
            :func:`~ceemx.identification.analysis.profile.summary_intervals` flags — near a
            bound, or a skewed objective — at most ``max_profiles``; Wald for the others).
        max_profiles: with ``"auto"``, the most parameters profiled.

    Returns:
        ``(rows, notes)``: one :class:`ParameterRow` per entry of θ, in θ order; ``notes`` holds
        the covariance's warnings (e.g. which entries are weakly determined), not re-raised.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"`level` must be in (0, 1); got {level}.")
    if intervals not in ("auto", "wald", "profile"):
        raise ValueError(f"`intervals` must be 'auto', 'wald' or 'profile'; got {intervals!r}.")
    problem, theta = result.problem, result.theta
    names = problem.parameter_names()
    estimate = np.asarray(problem.natural(theta), np.float64)
    nan = np.full(estimate.shape, np.nan)
    se, lower, upper, notes = nan, nan, nan, []
    if uncertainty and estimate.size:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cov = np.asarray(result.covariance(hold_weak=True), np.float64)
        notes = list(dict.fromkeys(str(w.message) for w in caught))
        sd = np.sqrt(np.maximum(np.diagonal(cov), 0.0))
        sd = np.where(np.isfinite(np.diagonal(cov)), sd, np.nan)
        se = np.abs(np.asarray(problem.natural_jacobian(theta), np.float64)) * sd
        q = NormalDist().inv_cdf(0.5 + level / 2.0)
        th = np.asarray(theta, np.float64)
        step = np.where(np.isfinite(sd), q * sd, 0.0)
        ends = [
            np.asarray(problem.natural(jnp.asarray(th + s * step, theta.dtype)), np.float64)
            for s in (-1.0, 1.0)
        ]
        lower = np.where(np.isfinite(sd), np.minimum(*ends), np.nan)
        upper = np.where(np.isfinite(sd), np.maximum(*ends), np.nan)
        kinds = ["Wald" if np.isfinite(v) else "" for v in sd]
        if intervals != "wald":
            lower, upper, more = _profiled(
                result, cov, level, intervals, max_profiles, (lower, upper, kinds)
            )
            notes += more
    else:
        kinds = [""] * len(names)
    words = _constraint_words(problem)
    rows = [
        ParameterRow(*fields)
        for fields in zip(names, estimate, se, lower, upper, words, kinds, strict=True)
    ]
    return rows, notes


def _profiled(result, cov, level, mode, max_profiles, wald):
    """``(lower, upper, notes)``: the Wald ``(lower, upper, kinds)``, the rule's profiles put in.

    ``kinds`` is updated in place.
    """
    lower, upper, kinds = np.array(wald[0], np.float64), np.array(wald[1], np.float64), wald[2]
    profiles, notes = summary_intervals(
        result, cov, level=level, mode=mode, max_profiles=max_profiles
    )
    for j, p in profiles.items():
        if not (np.isfinite(p.lower) and np.isfinite(p.upper)):
            notes.append(f"The profile of {p.name} failed on one side: its Wald interval is shown.")
            continue
        lower[j], upper[j] = p.lower, p.upper
        ends = {p.lower_end, p.upper_end}
        kinds[j] = "profile" + (
            ", to bound" if "bound" in ends else ", open" if "limit" in ends else ""
        )
    return lower, upper, notes


# --------------------------------------------------------------------------------------------
# Pieces
# --------------------------------------------------------------------------------------------


def _num(x: float, digits: int = 5) -> str:
    return "nan" if not np.isfinite(x) else f"{x:.{digits}g}"


def _values(a) -> str:
    a = np.atleast_1d(np.asarray(a, np.float64)).reshape(-1)
    if a.size > 1 and np.allclose(a, a[0], rtol=0, atol=0):
        return f"{_num(float(a[0]), 4)} (each of {a.size})"
    shown = ", ".join(_num(float(v), 4) for v in a[:6])
    return shown + (f", … ({a.size} in all)" if a.size > 6 else "")


def describe_noise(noise: AbstractNoise | None) -> str:
    """A noise model in a few words with its scales, e.g. ``"DiagonalGaussian, std 0.1"``."""
    if noise is None:
        return "none"
    values = noise.describe()
    return ", ".join([type(noise).__name__] + [f"{k} {_values(v)}" for k, v in values.items()])


def _count(n: int, one: str, many: str | None = None) -> str:
    return f"{n} {one if n == 1 else (many or one + 's')}"


def _names_list(names: Sequence[str], most: int = 8) -> str:
    more = f", … ({len(names)} in all)" if len(names) > most else ""
    return ", ".join(names[:most]) + more


def _learned(result, field: str) -> bool:
    problem = result.problem
    if result.noise_rounds:  # noise="learn": unless no estimate but a degenerate one came
        return bool(result.noise_rounds[-1].get("learned", True))
    return bool(problem is not None and problem.trains(field))


def _trajectory_lines(result) -> tuple[str, list[str]]:
    """``(status in a few words, the rest of messages())``: statuses grouped with counts."""
    B = int(np.size(codes(result.status)))
    every = result.messages()
    per, rest = every[:B], every[B:]
    counts = Counter(per)
    if len(counts) == 1:
        text = f"all {B} trajectories: {per[0]}" if B > 1 else per[0]
    else:
        text = "; ".join(f"{n} × {m}" for m, n in counts.most_common())
    return text, rest


def _timing(result) -> str:
    times = [float(h.get("time", np.nan)) for h in result.history]
    if not times:
        return "no epoch run"
    total = float(np.nansum(times))
    if result.noise_rounds:  # every round's fit and noise estimate, not the last fit's alone
        rounds = [float(r.get("time", np.nan)) for r in result.noise_rounds]
        return f"{float(np.nansum(rounds)):.3g} s in all ({len(rounds) - 1} noise rounds)"
    text = f"{total:.3g} s in all"
    if len(times) > 1:
        rest = float(np.median(times[1:]))
        text += f" (first epoch {times[0]:.3g} s, compilation included; then {rest:.3g} s each)"
    return text


def _choice_facts(result) -> list[tuple[str, str]]:
    """The solver (chosen, and why; or named) and the stages run, from ``result.choice``."""
    choice = getattr(result, "choice", None)
    if choice is None:
        return []
    if choice.by == "user":
        facts = [("solver", f"{choice.describe()}, named by the user")]
    else:
        facts = [("solver chosen", f"{choice.describe()}, because {choice.reason}")]
    if len(choice.stages) > 1:
        parts = [
            f"{type(s.solver).__name__} skipped"
            if getattr(s, "skipped", None)
            else f"{type(s.solver).__name__} {_count(s.epochs or 0, 'epoch')}, "
            + ("converged" if s.converged else "NOT converged")
            + (f", {s.seconds:.3g} s" if s.seconds is not None else "")
            + (", discarded" if getattr(s, "discarded", None) else "")
            for s in choice.stages
        ]
        facts.append(("stages", "; ".join(parts)))
    return facts


def _ran(choice) -> list:
    """The stages of a path that ran and stand (not skipped, not discarded)."""
    return [
        s
        for s in choice.stages
        if not getattr(s, "skipped", None) and not getattr(s, "discarded", None)
    ]


def _epochs_fact(result) -> str:
    """Epochs, convergence and time: of every stage of a path (its stages' records)."""
    conv = "converged" if result.converged else "NOT converged"
    choice = getattr(result, "choice", None)
    if choice is not None and len(choice.stages) > 1:
        ran = _ran(choice)
        epochs = sum(s.epochs or 0 for s in ran)
        text = f"{epochs} in {_count(len(ran), 'stage')}, {conv}"
        return text + (f"; {choice.seconds:.3g} s in all" if choice.seconds is not None else "")
    return f"{result.epochs}, {conv}; {_timing(result)}"


def interval_kind(result) -> str:
    """What the parameter table's intervals are, from the solver that made the estimate.

    ``AbstractFitSolver.uncertainty``: ``"evidence"`` (Laplace EM) — the inverse observed
    information of the Laplace log-evidence, the states integrated out (the noise held at its
    value unless it is learned in θ); else certainty-equivalent — the Laplace approximation of
    the joint posterior p(x, θ | y) at the end point.
    """
    if getattr(result.solver, "uncertainty", None) == "evidence":
        problem = result.problem
        in_theta = problem is not None and any(problem.trains(f) for f in _NOISE)
        held = "" if in_theta else ", the noise held at its value"
        return f"Laplace evidence (the states integrated out{held})"
    return "certainty-equivalent (Laplace approximation of p(x, θ | y) at the end point)"


_NOISE = ("process_noise", "obs_noise")


def _noise_origin(result, field: str) -> str:
    """The noise's origin: learned (in θ, or by noise rounds) or given."""
    return " (learned)" if _learned(result, field) else " (given)"


def _facts(result, report=None) -> list[tuple[str, str]]:
    """Label → value, after the parameter table (``report``: the diagnostics, when run)."""
    system = result.system
    data = None if result.problem is None else result.problem.data
    J = result.history[-1]["J"] if result.history else result.initial_J
    facts = [
        *_choice_facts(result),
        ("intervals", interval_kind(result)),
        (
            "process noise",
            describe_noise(system.process_noise) + _noise_origin(result, "process_noise"),
        ),
        (
            "observation noise",
            describe_noise(system.obs_noise) + _noise_origin(result, "obs_noise"),
        ),
        ("J (log-likelihood, Eq. 9)", f"{_num(float(J), 8)} (start {_num(result.initial_J, 8)})"),
    ]
    if data is not None:
        B, T = int(data.y.shape[0]), int(data.y.shape[1])
        m = int(data.y.shape[2])
        text = f"{_count(B, 'trajectory', 'trajectories')} × {T} steps, {_count(m, 'output')}"
        if result.excluded:
            text += f"; excluded by the health test: {', '.join(map(str, result.excluded))}"
        facts.append(("data", text))
    facts.append(("epochs", _epochs_fact(result)))
    status, _ = _trajectory_lines(result)
    facts.append(("status", status))
    if result.noise_rounds:
        facts.append(("noise rounds", _rounds_line(result.noise_rounds)))
    check = result.noise_check
    if check is not None:
        # One verdict per noise question: with the diagnostics, their per-component ratios too.
        verdict = check.verdict if report is None else report.noise_verdict
        facts.append(
            (
                "noise check",
                f"rho = {check.ratio:.3g} (realised / assumed variance; band "
                f"[{check.band[0]:.3g}, {check.band[1]:.3g}]): {verdict}",
            )
        )
    if report is None and check is not None:  # with the diagnostics, their report says it
        errors = prediction_error_check(result)
        if errors is not None:
            facts.append(("one-step errors", str(errors)))
    ident = result.identifiability
    if ident is not None:
        text = (
            "determined: " + _names_list(ident.determined)
            if ident.determined
            else "not determined: " + _names_list(ident.undetermined)
        )
        facts.append(
            ("identifiability", text + (" (the fit stopped on it)" if ident.stopped else ""))
        )
    return facts


def _rounds_line(rounds) -> str:
    """``noise="learn"`` in a line: the rounds, the last change, whether a floor held."""
    last, n = rounds[-1], len(rounds) - 1
    change = last.get("change")
    text = f"noise learned in {_count(n, 'round')}"
    if change is not None:
        if last.get("settled"):
            verdict = ")"
        elif last.get("noise_settled"):  # the noise held, the round's own fit did not converge
            verdict = "; the noise held, its fit did not converge)"
        else:
            verdict = ", not settled)"
        text += f" (last change {100 * float(change):.3g} %" + verdict
    if last.get("floored"):
        text += f"; held at a floor from the data: {', '.join(last['floored'])} (messages)"
    return text


def noise_round_messages(rounds) -> list[str]:
    """The messages of ``fit(..., noise="learn")``.

    The floors the last estimate was held at, and why the rounds stopped when they did not settle.
    """
    last = rounds[-1]
    out = [f"the last noise estimate: {note}" for note in last.get("notes") or ()]
    if last.get("learned") is False:
        out.append(
            "the noise was not learned: every estimate lay at the degenerate boundary σ_v → 0, "
            "so the fit is at the noise given"
        )
    if last.get("round", 0) and not last.get("settled", True):
        out.append(
            f"the noise did not settle in {_count(len(rounds) - 1, 'round')} (last change "
            f"{100 * float(last.get('change', np.nan)):.3g} %): the fit is at the last round's "
            "noise and not converged"
        )
    return out


# --------------------------------------------------------------------------------------------
# Layout
# --------------------------------------------------------------------------------------------

_WIDTH = 78  # text lines wrap here (the parameter table may be wider)
_HEAD = ("parameter", "estimate", "std. error", "{pct} interval", "constraint")


def _cells(rows: Sequence[ParameterRow]) -> list[list[str]]:
    return [
        [
            r.name,
            _num(r.estimate),
            _num(r.se, 3),
            "—"
            if not np.isfinite(r.lower)
            else f"[{_num(r.lower)}, {_num(r.upper)}] {r.interval}".rstrip(),
            r.constraint,
        ]
        for r in rows
    ]


def _parameter_table(result, head: list[str], rows: Sequence[ParameterRow], md: bool) -> list[str]:
    """The parameter table's lines, with units and descriptions where the fields declare them.

    A unit column after the estimate when any parameter has a unit (:func:`ceemx.param`); the
    fields' descriptions on a line under the table.
    """
    labels = entry_labels(result.problem.template, result.system)
    cells = _cells(rows)
    if any(unit for unit, _ in labels):
        head.insert(2, "unit")
        for row, (unit, _) in zip(cells, labels, strict=False):
            row.insert(2, unit)
    right = {1, 3} if len(head) > 5 else {1, 2}
    out = [""] if md else []
    out += (_md_table if md else _text_table)(head, cells, right)
    meanings = _meanings(rows, labels)
    return out + (["", meanings] if md else [meanings]) if meanings else out


def _meanings(rows: Sequence[ParameterRow], labels: Sequence[tuple[str, str]]) -> str:
    """``"k: stiffness; c: damping"``: the fields' descriptions, each once, in table order."""
    seen: dict[str, str] = {}
    for row, (_, text) in zip(rows, labels, strict=False):
        field = row.name.split("[")[0]
        if text and field not in seen:
            seen[field] = text
    return "; ".join(f"{k}: {v}" for k, v in seen.items())


def _text_table(head: Sequence[str], body: Sequence[Sequence[str]], right: set[int]) -> list[str]:
    widths = [max(len(str(c)) for c in col) for col in zip(head, *body, strict=True)]

    def line(cells):
        return "  ".join(
            (c.rjust(w) if i in right else c.ljust(w))
            for i, (c, w) in enumerate(zip(cells, widths, strict=True))
        ).rstrip()

    return [line(head), "  ".join("-" * w for w in widths), *(line(r) for r in body)]


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _md_table(head: Sequence[str], body: Sequence[Sequence[str]], right: set[int]) -> list[str]:
    rule = ["---:" if i in right else "---" for i in range(len(head))]
    return [
        "| " + " | ".join(_md_escape(h) for h in head) + " |",
        "|" + "|".join(rule) + "|",
        *("| " + " | ".join(_md_escape(c) for c in r) + " |" for r in body),
    ]


def _title(result) -> str:
    name, epochs = type(result.solver).__name__, result.epochs
    choice = getattr(result, "choice", None)
    if choice is not None and len(choice.stages) > 1:  # a path: every stage run, every epoch
        name = " → ".join(type(s.solver).__name__ for s in _ran(choice))
        epochs = sum(s.epochs or 0 for s in _ran(choice))
    conv = "converged" if result.converged else "not converged"
    return f"Fit summary: {name}, {conv} after {_count(epochs, 'epoch')}"


def fit_summary(
    result,
    format: Format = "text",
    *,
    level: float = 0.95,
    diagnostics: bool = False,
    uncertainty: bool = True,
    max_rows: int | None = 40,
    intervals: Intervals = "auto",
) -> Summary:
    """The summary of a fit (module notes); :meth:`ceemx.FitResult.summary` calls it.

    Args:
        result: a :class:`ceemx.FitResult`.
        format: ``"text"`` (aligned columns) or ``"markdown"`` (GitHub tables).
        level: the intervals' coverage.
        diagnostics: also run :meth:`FitResult.diagnostics` (an EKF pass and a Laplace E-step;
            compiled on first use) and append its report.
        uncertainty: compute standard errors and intervals (one Schur complement).
        max_rows: show at most this many parameters (the first ones; ``None``: all).
        intervals: ``"auto"``, ``"wald"`` or ``"profile"``, as :func:`parameter_rows`.

    Returns:
        A :class:`Summary` (a ``str``).
    """
    if format not in ("text", "markdown"):
        raise ValueError(f"`format` must be 'text' or 'markdown'; got {format!r}.")
    md, options = format == "markdown", {"level": level, "intervals": intervals}
    notes: list[str] = []
    out = [f"**{_title(result)}**" if md else _title(result)]
    rule = "=" * _WIDTH
    if not md:
        out.append(rule)
    if result.problem is None:
        out.append("(no fit problem held: the parameter table needs a result of `fit`)")
    else:
        rows, notes = parameter_rows(result, **options, uncertainty=uncertainty)
        shown = rows if max_rows is None else rows[:max_rows]
        head = [h.format(pct=f"{100 * level:g} %") for h in _HEAD]
        out += _parameter_table(result, head, shown, md)
        if len(shown) < len(rows):
            out.append(
                f"… {len(rows) - len(shown)} more parameters (summary(max_rows=None) shows all)"
            )
        if not rows:
            out.append("(no trainable parameters)")
    report = result.diagnostics() if diagnostics else None
    facts = _facts(result, report)
    if md:
        out += ["", *_md_table(["", ""], [[k, v] for k, v in facts], set())]
    else:
        width = max(len(k) for k, _ in facts)
        out.append("-" * _WIDTH)
        for k, v in facts:
            out += textwrap.wrap(
                v,
                _WIDTH,
                initial_indent=f"{k.ljust(width)}  ",
                subsequent_indent=" " * (width + 2),
            )
    _, extra = _trajectory_lines(result)
    said = list(dict.fromkeys([*extra, *notes]))
    if said:
        out += ["", "**Messages**" if md else "Messages:"]
        out += (
            [f"- {m}" for m in said]
            if md
            else [
                textwrap.fill(m, _WIDTH, initial_indent="- ", subsequent_indent="  ") for m in said
            ]
        )
    if report is not None:
        text = report.summary()
        out += ["", "```", text, "```"] if md else ["", text]
    if not md:
        out.append(rule)
    return Summary("\n".join(out))


def short_repr(result) -> str:
    """One or two lines: solver, convergence, J, the first parameters; nothing computed."""
    J = result.history[-1]["J"] if result.history else result.initial_J
    title = _title(result).removeprefix("Fit summary: ")
    head = f"FitResult({title}, J = {_num(float(J), 6)}"
    if result.problem is not None and result.theta is not None:
        names = result.problem.parameter_names()
        values = np.asarray(result.problem.natural(result.theta), np.float64)
        shown = ", ".join(
            f"{n} = {_num(float(v), 4)}" for n, v in zip(names[:6], values[:6], strict=False)
        )
        more = f", … ({len(names)} in all)" if len(names) > 6 else ""
        head += f";\n  {shown}{more}"
    status = np.atleast_1d(codes(result.status)).reshape(-1)
    failed = int(np.sum(status != int(codes(RESULTS.successful))))
    head += f"; {_count(status.size, 'trajectory', 'trajectories')}"
    head += f", {failed} not successful" if failed else ""
    return head + ")  — .summary() for standard errors and diagnostics"
