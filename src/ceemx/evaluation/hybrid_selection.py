"""A hybrid model from a physics model and a training record, its settings chosen from that record.

:func:`fit_hybrid` is the one procedure behind ``ceemx experiment real_data``: it has no setting
that depends on the record, and it chooses the two that decide a hybrid's free-run score by that
score, measured on the held-out tail of the *training* record (never a test record):

1. **The noise weighting, judged by the hybrid.** A CE fit maximises J (Eq. 9), where the
   process and observation noise weigh the dynamics' residuals against the outputs'; only their
   ratio moves the point estimate, so the observation noise is kept and the process noise is
   scaled. A loose weighting lets the smoothed states absorb the model's errors (a good one-step
   fit that free-runs badly, and a term that has nothing to learn from: the states already carry
   what the physics lacks); a tight one makes the fit an output-error (simulation) fit, whose
   landscape is rougher. The physics is fitted on the fit part at every factor of
   ``noise_factors`` × its process noise, loose to tight, each fit started from the previous
   one's parameters and states (a continuation), and each scored by a free run over the
   validation tail. The physics' own score does not decide: where the physics lacks a force, its
   error is that force at every weighting, and the weighting where it scores best can be one
   where the term cannot learn. So the term is trained (step 2) at the physics' best factor and
   at every whole decade from it, nearest first (tighter before looser), until
   ``noise_patience`` of them in a row did not improve the best hybrid score. The physics' best
   weighting is kept unless the best other weighting's hybrid (or physics, iteration 0) is
   *clearly better* on the validation tail: the lower bound at ``level`` (95 %) of its
   relative RMSE improvement is above zero, by a paired moving-block bootstrap of the two
   models' free-run errors there (:func:`ceemx.evaluation.paired_bootstrap.clearly_better`;
   the block length from the errors' own autocorrelation). A few per cent on a short
   validation tail whose errors drift together for hundreds of samples are no evidence that a
   weighting carries over to new data; the test says how many per cent are, on this tail,
   with no constant to choose. The best of several weightings scores well partly by luck (the
   winner's curse), so its test is held to the Bonferroni level over the weightings it was
   picked from (:func:`~ceemx.evaluation.paired_bootstrap.adjusted_level`). The noise the
   likelihood
   learns (``fit(noise="learn")``) is not used: it maximises the evidence of the state-space
   model, not the free-run score, and on the real datasets it made that score worse.
2. **The learned term's training length.** At each candidate weighting the hybrid
   (:func:`ceemx.hybrid`: that weighting's physics fit plus a zero-initialised network) is
   trained on the fit part by :class:`ceemx.JointLM` with weight decay, every iteration scored
   on the validation tail (:class:`ceemx.EarlyStopping`, the physics scored as iteration 0).
   The term leaves its zero start slowly — its free run can sit at the physics' score for tens
   to hundreds of iterations while J climbs, then fall, and it does not fall monotonically — so
   the training stops only after ``patience`` iterations without a better score, counted from
   the last improvement of at least ``min_delta`` (relative) and only once the term has made
   one (``EarlyStopping(patience_from="improvement")``: a term still at its start has not
   stopped improving), or at ``term_epochs``. The best iteration
   of the chosen weighting is the training length; when no iteration beats the physics, the
   term is left out (length 0).
3. **Every sample in the final model** (``refit=True``): the physics is refitted on the whole
   record at the chosen weighting (from the fit part's parameters), and the term trained on the
   whole record from its zero start for the chosen length plus ``patience`` iterations, each
   scored by its free run over the whole record. The chosen length is kept unless the best
   iteration is a dip, clearly better (the same test, over the whole record) than both the
   chosen length and the last iteration: the best can be a transient a few iterations wide that
   the longer record reaches later, while a steady in-sample gain of training longer (the best
   at the end) is no evidence that it carries over (on a short record it is overfitting). The
   held-out model (the fit part's, early-stopped) is returned beside it, so the two can be
   compared on test data.

The result (:class:`HybridFit`) holds the selected model, both physics fits and the selection's
record: every candidate weighting with its validation score and its hybrid's, the chosen one,
the chosen term's validation score per iteration and the chosen length, and both tests
(improvement, lower bound, block length, samples) behind the two choices
(:meth:`HybridFit.record`, a JSON-able dict; :meth:`HybridFit.summary`, text).

Width, depth and the weight-decay σ of the term are fixed options (16 units, one hidden layer,
σ = 1): on the real datasets' validation tails no change of them helped by more than the
rounding-level spread of the early-stopped path (``docs/results.md``, "Hybrid variants").
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ceemx.data.trajectories import Trajectories
from ceemx.evaluation.early_stopping import SCORE_OPTIONS, EarlyStopping
from ceemx.evaluation.paired_bootstrap import adjusted_level, clearly_better
from ceemx.identification.fitting.result import FitResult
from ceemx.infra.options import check_int, check_level, check_positive
from ceemx.models.system import AbstractSystem, with_noise

__all__ = ["NOISE_FACTORS", "HybridFit", "NoiseCandidate", "fit_hybrid", "split_tail"]

#: The default candidate process-noise factors, loose to tight: half decades over three decades
#: from the model's own process noise.
NOISE_FACTORS: tuple[float, ...] = tuple(10.0 ** (-k / 2) for k in range(7))


@dataclass(frozen=True)
class NoiseCandidate:
    """One noise weighting the selection tried.

    Attributes:
        factor: the factor on the model's process noise.
        process_noise: the largest process-noise scale at that factor.
        validation_rmse: the physics fit's free-run RMSE on the validation tail.
        epochs: iterations of its fit.
        converged: whether its fit converged.
        wall_s: its fit's and score's wall time [s].
        hybrid_rmse: the best validation RMSE of the term trained at this weighting, the
            physics' (iteration 0) included (``None``: no term trained here).
        term_best_epoch: that best iteration (0: the physics).
        term_epochs: iterations the term's training ran here.
        term_wall_s: the term's training time here [s].
    """

    factor: float
    process_noise: float
    validation_rmse: float
    epochs: int
    converged: bool
    wall_s: float
    hybrid_rmse: float | None = None
    term_best_epoch: int = 0
    term_epochs: int = 0
    term_wall_s: float = 0.0


@dataclass
class HybridFit:
    """What :func:`fit_hybrid` selected and how (module notes).

    Attributes:
        system: the selected model: the hybrid trained on every sample for the chosen length
            (``refit=True``), else the held-out one; the physics (a hybrid with a zero term when
            bounds were asked for) when the term did not beat it on the validation tail.
        physics: the physics alone at its own best weighting (``physics_factor``), fitted on
            every sample (``refit=False``: on the fit part): what the physics-only user gets.
        held_out: the hybrid trained on the fit part, stopped at its best validation iteration.
        held_out_physics: the physics fit at the chosen weighting on the fit part (the held-out
            hybrid's start).
        candidates: every weighting tried, loose to tight (with the term's score where it was
            trained).
        factor: the chosen factor on the model's process noise (the hybrid's weighting).
        process_noise: the chosen process-noise scale (the largest component).
        physics_factor: the factor at which the physics alone scored best.
        term_scores: (iteration, validation RMSE) of the term's training on the fit part at
            the chosen weighting (iteration 0: the physics).
        best_epoch: the chosen training length (0: no term).
        term_epochs: iterations the held-out training at the chosen weighting ran.
        validation_rmse: the validation score of the physics alone at its best weighting
            (``physics``), of the physics at the chosen weighting (``physics_at_factor``) and
            of the held-out hybrid (``hybrid``).
        term_stop: why the held-out training ended (its last iteration's record: converged,
            stop, accepted, the LM's status, whether the term settled, failed trajectories;
            ``stopped_by``: ``"patience"`` (the validation stopped improving: converged in the
            selection's sense), ``"term_epochs"`` (the budget ran out) or ``"fit"``).
        refit: whether the final model was refitted on every sample.
        refit_epoch: the iteration of the term's training on every sample that was kept (the
            chosen length unless the best iteration's free run over the whole record was a dip,
            clearly better than both it and the last iteration's; 0: no term).
        refit_scores: (iteration, free-run RMSE over the whole record) of that training.
        samples: samples of the fit part, the validation tail and the whole record.
        wall_s: wall time per stage [s].
        term_result: the final term fit's :class:`ceemx.FitResult` (``None`` without a term).
        tests: the significance tests behind the two choices (module notes), each the
            :class:`~ceemx.evaluation.paired_bootstrap.PairedComparison` record (``better``,
            the relative RMSE ``improvement``, its ``lower_bound``, ``level``,
            ``block_length``, samples ``n``) or ``None`` where none was run: ``"weighting"``
            (the best other weighting's hybrid, ``other_factor``, against the first's,
            ``factor``, on the validation tail) and ``"refit"`` (the best refit iteration,
            ``best``, ``against_length`` — the chosen length — and ``against_last``, on the
            whole record).
    """

    system: AbstractSystem
    physics: FitResult
    held_out: AbstractSystem
    held_out_physics: AbstractSystem
    candidates: list[NoiseCandidate]
    factor: float
    process_noise: float
    physics_factor: float
    term_scores: list[tuple[int, float]]
    best_epoch: int
    term_epochs: int
    validation_rmse: dict[str, float]
    term_stop: dict[str, Any]
    refit: bool
    samples: dict[str, int]
    refit_epoch: int = 0
    refit_scores: list[tuple[int, float]] = field(default_factory=list)
    wall_s: dict[str, float] = field(default_factory=dict)
    term_result: FitResult | None = None
    tests: dict[str, dict[str, Any] | None] = field(default_factory=dict)

    def record(self) -> dict[str, Any]:
        """The selection's record as plain Python values (for JSON)."""
        return {
            "candidates": [c.__dict__ for c in self.candidates],
            "factor": self.factor,
            "process_noise": self.process_noise,
            "physics_factor": self.physics_factor,
            "term_scores": [[int(e), float(r)] for e, r in self.term_scores],
            "best_epoch": self.best_epoch,
            "term_epochs": self.term_epochs,
            "validation_rmse": dict(self.validation_rmse),
            "term_stop": dict(self.term_stop),
            "refit": self.refit,
            "refit_epoch": self.refit_epoch,
            "refit_scores": [[int(e), float(r)] for e, r in self.refit_scores],
            "samples": dict(self.samples),
            "wall_s": dict(self.wall_s),
            "tests": dict(self.tests),
        }

    def summary(self) -> str:
        """The selection in a few lines of text."""
        lines = [
            "noise weighting (process noise × factor, free-run RMSE on the validation tail: "
            "physics; hybrid at its best iteration where the term was trained):"
        ]
        for c in self.candidates:
            mark = "  ← chosen" if c.factor == self.factor else ""
            term = (
                ""
                if c.hybrid_rmse is None
                else f"; hybrid {c.hybrid_rmse:.4g} (iteration {c.term_best_epoch} of "
                f"{c.term_epochs}, {c.term_wall_s:.1f} s)"
            )
            lines.append(
                f"  × {c.factor:.3g} (σ_w {c.process_noise:.3g}): {c.validation_rmse:.4g}"
                f" ({c.epochs} iterations, {c.wall_s:.1f} s){term}{mark}"
            )
        v = self.validation_rmse
        lines.append(
            f"learned term at × {self.factor:.3g}: best iteration {self.best_epoch} of "
            f"{self.term_epochs}, validation {v['hybrid']:.4g} (physics alone {v['physics']:.4g}"
            f" at × {self.physics_factor:.3g}); "
            + _STOPPED.get(self.term_stop.get("stopped_by", ""), "not trained")
            + ("" if self.best_epoch else "; no iteration beat the physics, term left out")
        )
        lines.extend(_test_lines(self.tests))
        where = "every sample" if self.refit else "the fit part"
        kept = f", the term's iteration {self.refit_epoch} kept" if self.refit_scores else ""
        lines.append(
            f"final model: fitted on {where} ({self.samples['total' if self.refit else 'fit']}"
            f" samples{kept}); {sum(self.wall_s.values()):.1f} s in all"
        )
        return "\n".join(lines)


def _verdict(test: Mapping[str, Any]) -> str:
    """One paired comparison in words: the improvement, its bound, the blocks."""
    return (
        f"{100 * test['improvement']:.3g} % better, lower bound {100 * test['lower_bound']:.3g} %"
        f" at {100 * test['level']:.3g} % (blocks of {test['block_length']}, "
        f"{test['n']} samples): {'clearly better' if test['better'] else 'not clearly better'}"
    )


def _test_lines(tests: Mapping[str, Any]) -> list[str]:
    """The summary's lines on the two significance tests (:attr:`HybridFit.tests`)."""
    lines = []
    w = tests.get("weighting")
    if w:
        lines.append(
            f"weighting: the hybrid at × {w['other_factor']:.3g} against × {w['factor']:.3g} "
            f"on the validation tail: {_verdict(w)}"
        )
    r = tests.get("refit")
    if r:
        lines.append(
            f"refit: iteration {r['best']} against the chosen length {r['length']}: "
            f"{_verdict(r['against_length'])}; against the last, {r['last']}: "
            f"{_verdict(r['against_last'])}"
        )
    return lines


#: Why the chosen weighting's term training ended, in words (``term_stop["stopped_by"]``).
_STOPPED = {
    "patience": "converged: the validation stopped improving",
    "term_epochs": "not converged: the iteration budget ran out",
    "fit": "the fit stopped",
}

#: The history keys that say why the term's training ended.
_WHY = (
    "epoch",
    "converged",
    "stop",
    "accepted",
    "lm_status",
    "term_settled",
    "failed_trajectories",
)


def split_tail(
    data: Trajectories, n_init: int, fraction: float = 0.2
) -> tuple[Trajectories, Trajectories]:
    """(fit part, validation tail) of every record: the last ``fraction`` held out.

    The tail holds at least ``2 n_init`` samples and starts ``n_init`` samples before the cut
    (its first ``n_init`` outputs set the free run's initial state, as in a test record).
    """
    T = data.num_steps
    held = max(int(fraction * T), 2 * n_init)
    cut = T - held
    if cut < 2 * n_init:
        raise ValueError(
            f"a record of {T} samples is too short to hold out a validation tail of {held} "
            f"(n_init = {n_init}): lower `validation_fraction` or pass longer records."
        )
    return data[:, :cut], data[:, cut - n_init :]


def _windows(data: Trajectories, window: int | None) -> Trajectories:
    """``data`` cut into windows of ``window`` samples with half overlap (``None``: whole)."""
    if window is None or data.num_steps <= window:
        return data
    return data.windows(window, window // 2)


def _noise_scale(system: AbstractSystem) -> float:
    s = system.process_noise.scale_parameters()
    if s is None:
        raise TypeError(
            f"`physics.process_noise` ({type(system.process_noise).__name__}) has no scale to "
            "select: give the model a Gaussian process noise (a scale)."
        )
    return float(np.max(np.asarray(s)))


def _check_options(  # fmt: skip
    physics,
    data,
    n_init,
    noise_patience,
    level,
    patience,
    max_epochs,
    term_epochs,
    window,
    validation_fraction,
    noise_factors,
    score_options,
) -> tuple[list[float], dict[str, Any]]:
    """:func:`fit_hybrid`'s arguments checked before any compute: (the factors, score options)."""
    if not isinstance(physics, AbstractSystem):
        raise TypeError(f"`physics` must be a ceemx.AbstractSystem; got {type(physics).__name__}.")
    if not isinstance(data, Trajectories):
        raise TypeError(f"`data` must be ceemx.Trajectories; got {type(data).__name__}.")
    check_int("n_init", n_init, 1)
    for name, value in (("noise_patience", noise_patience), ("patience", patience)):
        check_int(name, value, 1)
    check_int("max_epochs", max_epochs, 1)
    check_int("term_epochs", term_epochs, 0)
    if window is not None:
        check_int("window", window, 2 * n_init)
    check_level("level", level)
    check_positive("validation_fraction", validation_fraction)
    if validation_fraction >= 1:
        raise ValueError(f"`validation_fraction` must be in (0, 1); got {validation_fraction!r}.")
    factors = [float(f) for f in noise_factors]
    if not factors or not all(math.isfinite(f) and f > 0 for f in factors):
        raise ValueError(f"`noise_factors` must be positive numbers; got {noise_factors!r}.")
    options = dict(score_options or {})
    unknown = sorted(set(options) - SCORE_OPTIONS)
    if unknown:
        raise ValueError(
            f"`score_options` has unknown keys {unknown}; allowed: {sorted(SCORE_OPTIONS)}."
        )
    return factors, options


def _physics_path(
    physics: AbstractSystem,
    fit_part: Trajectories,
    judge: EarlyStopping,
    factors: list[float],
    scale0: float,
    max_epochs: int,
    say: Callable[[str], Any],
) -> tuple[list[NoiseCandidate], list[FitResult]]:
    """The loose-to-tight continuation of physics fits: (every candidate, every fit).

    Each fit starts from the last one's parameters and states; where the fit refuses that start
    (a parameter the last fit pinned at its bound, a J not finite there), from the guess — a
    refused start is a fact about the last fit, not a reason to lose the selection.
    """
    from ceemx.identification.fitting.driver import fit
    from ceemx.identification.solvers.joint import JointLM

    candidates: list[NoiseCandidate] = []
    fits: list[FitResult] = []
    for f in factors:
        t = time.perf_counter()
        last = fits[-1] if fits else None
        start = physics if last is None else last.system
        model = with_noise(start, process_noise=physics.process_noise.scaled(f))
        x0 = None if last is None else last.states
        try:
            res = fit(model, fit_part, x0, solver=JointLM(), max_epochs=max_epochs, diagnose=False)
        except ValueError as err:
            if last is None:
                raise
            say(f"physics at noise × {f:.3g}: the last fit's end refused as a start ({err}); "
                "from the guess")  # fmt: skip
            model = with_noise(physics, process_noise=physics.process_noise.scaled(f))
            res = fit(model, fit_part, solver=JointLM(), max_epochs=max_epochs, diagnose=False)
        rmse = judge.score(res.system)
        candidates.append(
            NoiseCandidate(
                f, f * scale0, rmse, len(res.history), bool(res.converged), time.perf_counter() - t
            )
        )
        fits.append(res)
        say(f"physics at noise × {f:.3g}: validation {rmse:.4g} ({len(res.history)} iterations)")
    if not any(math.isfinite(c.validation_rmse) for c in candidates):
        raise RuntimeError(
            "every candidate noise weighting diverged on the validation tail (non-finite free "
            "run); check the physics model's guess and the data's units."
        )
    return candidates, fits


def _term_candidates(candidates: list[NoiseCandidate]) -> list[int]:
    """Where the term is trained: the physics' best factor and every whole decade from it.

    Nearest first (at equal distance the tighter first): the order the patience reads.
    """
    finite = [i for i, c in enumerate(candidates) if math.isfinite(c.validation_rmse)]
    best = min(finite, key=lambda i: candidates[i].validation_rmse)
    f0 = candidates[best].factor
    decades = {i: math.log10(f0 / candidates[i].factor) for i in finite}
    whole = [i for i, d in decades.items() if abs(d - round(d)) < 1e-6]
    return sorted(whole, key=lambda i: (abs(round(decades[i])), -decades[i]))


def _hybrid_model(training, candidate: NoiseCandidate, physics_fit: FitResult) -> AbstractSystem:
    """The model a candidate's hybrid score belongs to (:func:`_train_candidates`).

    The early-stopped term model, or the physics at that weighting where no term iteration
    beat it.
    """
    stopper, model = training[0], training[1]
    return model if stopper.best_rmse <= candidate.validation_rmse else physics_fit.system


def _choose(trained: dict, candidates: list, fits: list, judge: EarlyStopping, level: float):
    """The chosen candidate: the physics' best weighting (tried first) unless clearly beaten.

    The best-scoring other weighting is chosen when its hybrid's validation free run is
    clearly better than the first's (:func:`~ceemx.evaluation.paired_bootstrap.clearly_better`
    at ``level`` on the two models' errors over the validation tail).

    Returns:
        (the chosen candidate, the test's record or ``None`` where no other weighting scored).
    """
    first = next(iter(trained))
    others = [i for i in trained if i != first and math.isfinite(trained[i][0])]
    if not others:
        return first, None
    other = min(others, key=lambda i: trained[i][0])
    model = {i: _hybrid_model(trained[i][1], candidates[i], fits[i]) for i in (first, other)}
    errors_a, observed = judge.errors(model[first])
    errors_b, _ = judge.errors(model[other])
    level = adjusted_level(level, len(others))  # the best of the others: the winner's curse
    test = clearly_better(errors_a, errors_b, mask=observed, level=level)
    record = {"factor": candidates[first].factor, "other_factor": candidates[other].factor}
    return (other if test.better else first), record | test.record()


def _train_term(build, held_physics, fit_part, validation, n_init, patience, options, epochs):
    """The term on a physics fit, trained with every iteration scored on the tail.

    Returns (the early stopping, the best model, iterations run, why training ended).
    """
    model = build(held_physics.system, fit_part, states=held_physics.states)
    stopper = EarlyStopping(
        validation, n_init, patience=patience, start=model, score_options=options,
        patience_from="improvement",
    )  # fmt: skip
    if not epochs:
        return stopper, model, 0, {}
    res = _fit_term(model, fit_part, held_physics.states, epochs, callbacks=[stopper])
    end = res.history[-1] if res.history else {}
    why = {k: end[k] for k in _WHY if k in end}
    why["stopped_by"] = (
        "patience" if stopper.stopped else "term_epochs" if len(res.history) >= epochs else "fit"
    )
    return stopper, stopper.restore(res).system, len(res.history), why


def _refit_all(build, held_physics, whole, record, n_init, options, max_epochs, best_epoch,
               patience, level, bounds):  # fmt: skip
    """The physics, then the term, on every sample.

    The term is trained on every sample for ``best_epoch + patience`` iterations, each scored
    by its free run over the whole ``record`` (the data it is trained on: the simulation error,
    which J does not optimise). The iteration ``best_epoch`` is kept unless the best iteration
    is a dip: clearly better (:func:`_dip`) than both ``best_epoch`` and the last iteration.
    The term's best free run is often a transient a few iterations wide that the longer record
    reaches later, which such a dip shows; a steady in-sample gain of longer training (the best
    at the end) is no evidence that it carries over — on a short record it is overfitting.

    Returns (the physics fit, the final model, the term's fit or ``None``, the watcher or
    ``None``, the iteration kept, the dip tests' record or ``None``).
    """
    physics = _refit_physics(held_physics.system, whole, max_epochs)
    final: Any = physics.system
    if best_epoch or bounds:
        final = build(physics.system, whole, states=physics.states)
    if not best_epoch:
        return physics, final, None, None, 0, None
    epochs = best_epoch + patience
    watch = EarlyStopping(record, n_init, patience=epochs, start=final, score_options=options)
    kept: dict[str, Any] = {}

    def keep(info) -> dict:
        kept["last"] = info.epoch, info.system
        if info.epoch == best_epoch:
            kept["system"] = info.system
        return {}

    term = _fit_term(final, whole, physics.states, epochs, callbacks=[watch, keep])
    if "system" not in kept:  # the fit ended before the chosen length: its best
        return physics, watch.restore(term).system, term, watch, watch.best_epoch, None
    dip, tests = _dip(watch, best_epoch, kept["system"], kept["last"], level)
    if not dip:
        return physics, kept["system"], term, watch, best_epoch, tests
    return physics, watch.restore(term).system, term, watch, watch.best_epoch, tests


def _dip(watch: EarlyStopping, best_epoch: int, at_length, last, level: float):
    """Whether the watch's best iteration is clearly better than two others on its record.

    The two: ``best_epoch``'s model (``at_length``) and the last iteration's (``last``:
    (iteration, model)).

    Returns (dip, the two tests' record or ``None`` where the best is one of the two).

    At ``level`` itself, not the Bonferroni level over the iterations the best is picked from:
    consecutive iterations are nearly the same model, so they are not that many chances, and
    over a whole record the difference series' blocks are thousands of samples long (the
    friction case: 3–7 blocks to a replicate), where no bound at 1 − 0.05/80 is informative.
    """
    last_epoch, last_system = last
    best = watch.best_epoch
    if watch.best_system is None or best in (best_epoch, last_epoch):
        return False, None
    errors_best, observed = watch.errors(watch.best_system)
    tests: dict[str, Any] = {"best": best, "length": best_epoch, "last": last_epoch}
    for name, system in (("against_length", at_length), ("against_last", last_system)):
        errors, _ = watch.errors(system)
        tests[name] = clearly_better(errors, errors_best, mask=observed, level=level).record()
    return tests["against_length"]["better"] and tests["against_last"]["better"], tests


def _refit_physics(system: AbstractSystem, whole: Trajectories, max_epochs: int) -> FitResult:
    """The physics refitted on every sample from ``system`` (the fit part's parameters)."""
    from ceemx.identification.fitting.driver import fit
    from ceemx.identification.solvers.joint import JointLM

    return fit(system, whole, solver=JointLM(), max_epochs=max_epochs, diagnose=False)


def _fit_term(model, data: Trajectories, states, epochs: int, callbacks=()) -> FitResult:
    """JointLM on the physics and the term together, the weights under weight decay."""
    from ceemx.identification.fitting.driver import fit
    from ceemx.identification.solvers.joint import JointLM
    from ceemx.systems.learned_term import weight_decay

    return fit(
        model,
        data,
        jnp.asarray(states),
        solver=JointLM(),
        trainable=model.trainable("both"),
        log_prior=weight_decay,
        max_epochs=epochs,
        callbacks=callbacks,
        diagnose=False,
    )


def _train_candidates(train, candidates: list, fits: list, noise_patience: int, say) -> dict:
    """``{candidate: (validation RMSE, training)}``: the term trained at each weighting.

    In the order of :func:`_term_candidates`, until ``noise_patience`` in a row did not beat
    the best hybrid. ``candidates`` is updated in place with each trained candidate's hybrid
    score, best iteration, iterations run and time.
    """
    trained: dict[int, tuple[float, Any]] = {}
    best, since_best = math.inf, 0
    for i in _term_candidates(candidates):
        t = time.perf_counter()
        training = train(fits[i])
        stopper, epochs_run = training[0], training[2]
        rmse = min(stopper.best_rmse, candidates[i].validation_rmse)
        candidates[i] = dataclasses.replace(
            candidates[i], hybrid_rmse=rmse, term_best_epoch=stopper.best_epoch,
            term_epochs=epochs_run, term_wall_s=time.perf_counter() - t,
        )  # fmt: skip
        say(
            f"term at noise × {candidates[i].factor:.3g}: validation {rmse:.4g} (iteration "
            f"{stopper.best_epoch} of {epochs_run})"
        )
        trained[i] = (rmse, training)
        if rmse < best:
            best, since_best = rmse, 0
        else:
            since_best += 1
            if since_best >= noise_patience:
                break
    return trained


def _every_sample(build, fits, chosen, alone, whole, data, n_init, options, max_epochs,
                  best_epoch, patience, level, bounds):  # fmt: skip
    """``(hybrid, physics, term result, refit scores, refit iteration, dip tests)``, every sample.

    The hybrid refitted at the chosen weighting (:func:`_refit_all`); the physics alone at its
    own best weighting, that refit where the two weightings are the same.
    """
    hybrid_physics, final, term_result, watch, refit_epoch, dip = _refit_all(
        build, fits[chosen], whole, data, n_init, options, max_epochs, best_epoch, patience,
        level, bounds,
    )  # fmt: skip
    refit_scores = [] if watch is None else list(watch.scores)
    final_physics = (
        hybrid_physics if alone == chosen else _refit_physics(fits[alone].system, whole, max_epochs)
    )
    return final, final_physics, term_result, refit_scores, refit_epoch, dip


def _validation_scores(candidates: list, chosen: int, hybrid_rmse: float):
    """``(the physics' best weighting, the validation RMSE of each model that was judged)``."""
    alone = min(
        (i for i, c in enumerate(candidates) if math.isfinite(c.validation_rmse)),
        key=lambda i: candidates[i].validation_rmse,
    )
    return alone, {
        "physics": candidates[alone].validation_rmse,
        "physics_at_factor": candidates[chosen].validation_rmse,
        "hybrid": hybrid_rmse,
    }


def _sample_counts(fit_raw: Trajectories, validation: Trajectories, data: Trajectories, n_init):
    """Samples of the fit part, of the validation tail (scored) and of the whole record."""
    return {
        "fit": int(fit_raw.num_steps * fit_raw.batch_size),
        "validation": int((validation.num_steps - n_init) * validation.batch_size),
        "total": int(data.num_steps * data.batch_size),
    }


def fit_hybrid(
    physics: AbstractSystem,
    data: Trajectories,
    *,
    n_init: int,
    dynamics: bool | Sequence[int] = True,
    observation: bool | Sequence[int] = False,
    lower: ArrayLike | None = None,
    upper: ArrayLike | None = None,
    width: int = 16,
    depth: int = 1,
    prior_std: float = 1.0,
    noise_factors: Sequence[float] = NOISE_FACTORS,
    noise_patience: int = 2,
    level: float = 0.95,
    validation_fraction: float = 0.2,
    window: int | None = None,
    max_epochs: int = 200,
    term_epochs: int = 200,
    patience: int = 30,
    refit: bool = True,
    score_options: Mapping[str, Any] | None = None,
    progress: Callable[[str], Any] | None = None,
) -> HybridFit:
    """The physics model and a learned term, every setting chosen on the training record.

    The procedure (module notes): a loose-to-tight continuation of physics fits, the term
    trained at the physics' best noise weighting and at every decade from it, the weighting and
    the term's training length chosen by the hybrid's free-run RMSE on the held-out tail of
    ``data``; then, with ``refit``, both refitted on every sample.

    Args:
        physics: the physics at its guess, Gaussian noise (its process noise: the loosest).
        data: the training record(s) as the model reads them; never a test record.
        n_init: outputs that set a free run's initial state (the protocol's, e.g. a dataset's).
        dynamics: where the term enters the transition (:func:`ceemx.hybrid`).
        observation: where a term enters the observation (:func:`ceemx.hybrid`).
        lower: lower state bounds (:func:`ceemx.hybrid`).
        upper: upper state bounds.
        width: the term's hidden width.
        depth: the term's hidden layers.
        prior_std: the weight-decay prior's σ.
        noise_factors: candidate factors on the model's process noise, loose to tight.
        noise_patience: weightings in a row not beating the best hybrid before the last.
        level: the confidence at which another weighting or refit iteration must beat the
            default one to replace it (a paired block bootstrap, module notes), in (0, 1).
        validation_fraction: the tail of every record held out for the selection.
        window: fit longer records in windows of this many samples, half overlap (``None``).
        max_epochs: iterations of each physics fit.
        term_epochs: iterations of the term's training at most.
        patience: iterations without a better validation score that stop the term's training.
        refit: refit the chosen settings on every sample (else return the held-out model).
        score_options: :func:`ceemx.benchmark_score`'s options for the validation free runs.
        progress: called with a line of text after each stage (e.g. ``print``).

    Returns:
        A :class:`HybridFit`: ``.system`` the selected model, ``.record()`` the selection.

    Raises:
        TypeError, ValueError: naming the argument, before any fit.
    """
    from ceemx.identification.hybrid_builder import hybrid

    factors, options = _check_options(
        physics, data, n_init, noise_patience, level, patience, max_epochs, term_epochs,
        window, validation_fraction, noise_factors, score_options,
    )  # fmt: skip
    scale0 = _noise_scale(physics)
    say = progress or (lambda _line: None)
    fit_raw, validation = split_tail(data, n_init, validation_fraction)
    fit_part, whole = _windows(fit_raw, window), _windows(data, window)
    bounds = lower is not None or upper is not None
    wall: dict[str, float] = {}

    # 1. the physics on the fit part at every weighting, loose to tight (a continuation)
    t0 = time.perf_counter()
    judge = EarlyStopping(validation, n_init, score_options=options)
    candidates, fits = _physics_path(physics, fit_part, judge, factors, scale0, max_epochs, say)
    wall["noise"] = time.perf_counter() - t0

    # 2. the term at the physics' best weighting and every decade from it; the hybrid decides
    t0 = time.perf_counter()
    build = functools.partial(
        hybrid, dynamics=dynamics, observation=observation, width=width, depth=depth,
        prior_std=prior_std, lower=lower, upper=upper,
    )  # fmt: skip
    train = functools.partial(
        _train_term, build, fit_part=fit_part, validation=validation, n_init=n_init,
        patience=patience, options=options, epochs=term_epochs,
    )  # fmt: skip
    trained = _train_candidates(train, candidates, fits, noise_patience, say)
    chosen, weighting_test = _choose(trained, candidates, fits, judge, level)
    hybrid_rmse, (stopper, held_out, epochs_run, why) = trained[chosen]
    factor, held_physics = candidates[chosen].factor, fits[chosen]
    alone, rmse_of = _validation_scores(candidates, chosen, hybrid_rmse)
    best_epoch = stopper.best_epoch if math.isfinite(stopper.best_rmse) else 0
    say(f"chosen: noise × {factor:.3g}, term's best iteration {best_epoch} of {epochs_run}")
    wall["term"] = time.perf_counter() - t0

    # 3. every sample: the physics and the term refitted at the chosen settings
    final: Any = held_out if best_epoch or bounds else held_physics.system  # (no term: physics)
    final_physics, term_result, refit_scores, refit_epoch, dip = fits[alone], None, [], 0, None
    if refit:
        t0 = time.perf_counter()
        final, final_physics, term_result, refit_scores, refit_epoch, dip = _every_sample(
            build, fits, chosen, alone, whole, data, n_init, options, max_epochs, best_epoch,
            patience, level, bounds,
        )  # fmt: skip
        wall["refit"] = time.perf_counter() - t0
        say(f"refit on every sample: {wall['refit']:.1f} s")
    return HybridFit(
        system=final, physics=final_physics, held_out=held_out,
        held_out_physics=held_physics.system, candidates=candidates, factor=factor,
        process_noise=factor * scale0, physics_factor=candidates[alone].factor,
        term_scores=list(stopper.scores), best_epoch=best_epoch, term_epochs=epochs_run,
        validation_rmse=rmse_of, refit_epoch=refit_epoch, refit_scores=refit_scores,
        term_stop=why, refit=refit, wall_s=wall, term_result=term_result,
        tests={"weighting": weighting_test, "refit": dip},
        samples=_sample_counts(fit_raw, validation, data, n_init),
    )  # fmt: skip
