"""``fit`` without a solver: the stages :func:`~.choice.choose` picked, run as one result.

:func:`fit_default` runs them one after the other, each from the previous one's θ, noise and
(on the same data) states, and merges them into one :class:`FitResult`; :func:`user_choice` is
the record of a fit whose solver the user named; :func:`check_checkpoint` refuses a checkpoint
where a stage learns the noise (the rule and its reasons: :mod:`~.choice`).
"""

from __future__ import annotations

import dataclasses
import os
import time
import warnings

import jax.numpy as jnp
import numpy as np

from ceemx.data.arrays import indexed
from ceemx.data.checks import Prepared, promote_tree
from ceemx.identification.analysis.noise_check import NoiseCheckWarning, noise_check
from ceemx.identification.analysis.noise_estimate import start_states
from ceemx.identification.analysis.noise_floor import EVIDENCE_MARGIN
from ceemx.identification.fitting.choice import (
    Choice,
    Noise,
    Stage,
    StageNoise,
    choose,
    problem_facts,
)
from ceemx.identification.fitting.fit_options import FitOptions
from ceemx.identification.fitting.health import check_start, near_bound
from ceemx.identification.fitting.noise_rounds import learn_noise
from ceemx.identification.fitting.result import FitResult
from ceemx.identification.fitting.run import run_fit
from ceemx.identification.noise_moments import NOISE_FIELDS
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import AbstractFitSolver
from ceemx.infra.warn import warn
from ceemx.models.system import AbstractSystem

__all__ = ["check_checkpoint", "fit_default", "fit_named", "run_stages", "user_choice"]


def fit_named(
    system: AbstractSystem, inputs: Prepared, options: FitOptions, noise: Noise | None
) -> FitResult:
    """``fit`` with the solver the user named (``options.solver``), run as named.

    One fit at the system's noise, or noise rounds with ``noise="learn"``; the result records
    the choice (:func:`user_choice`).
    """
    t0 = time.perf_counter()
    result = (learn_noise if noise == "learn" else run_fit)(system, inputs, options)
    choice = user_choice(result, options.solver, noise, time.perf_counter() - t0)
    return dataclasses.replace(result, choice=choice)


def user_choice(
    result: FitResult, solver: AbstractFitSolver, noise: Noise | None, seconds: float
) -> Choice:
    """The :class:`Choice` of a fit whose solver the user named (run as named), once run."""
    problem = result.problem
    learned = problem is not None and any(problem.trains(f) for f in NOISE_FIELDS)
    kind: StageNoise = "learn" if noise == "learn" else ("parameters" if learned else "fixed")
    stage = Stage(solver, kind, None, _epochs(result), bool(result.converged), seconds)
    return Choice((stage,), "named by the user", "user", seconds)


def check_checkpoint(choice: Choice, options: FitOptions) -> None:
    """Refuse ``checkpoint`` for a path that learns the noise (its rounds do not checkpoint)."""
    if options.checkpoint is not None and choice.learns_noise:
        raise ValueError(
            "fit(checkpoint=...) without a solver: the default path learns the noise in rounds "
            f"of fits, which do not checkpoint ({choice.describe()}). Pass noise='fixed' (each "
            "stage is then checkpointed in a folder of its own under the checkpoint folder), "
            "or name a solver, e.g. solver=ceemx.JointLM()."
        )


def fit_default(
    system: AbstractSystem, inputs: Prepared, options: FitOptions, noise: Noise | None
) -> FitResult:
    """``fit`` without a solver: the stages :func:`~.choice.choose` picks, as one result.

    ``checkpoint`` is refused before any compute where a stage learns the noise
    (:func:`check_checkpoint`). Then :func:`run_stages`.
    """
    problem, theta = FitProblem.create(
        system, inputs.data, trainable=options.trainable, overrides=options.overrides
    )
    placed = options.mesh is not None
    choice = choose(noise=noise, **problem_facts(problem, theta, system, options.spread, placed))
    check_checkpoint(choice, options)
    return run_stages(system, inputs, options, choice)


def run_stages(
    system: AbstractSystem, inputs: Prepared, options: FitOptions, choice: Choice
) -> FitResult:
    """The stages of ``choice``, one after the other, as one :class:`FitResult`.

    Each stage starts from the previous one's system (θ and noise) and, on the same data, its
    states. The result is the last stage's (its estimate, states, uncertainty and noise check),
    with every stage's epochs in ``history`` (each record's ``stage``: 1, 2, ...), the noise
    rounds of the stage that learned the noise, the identifiability record of the last stage
    that made one, and ``converged`` only when every stage converged. Warnings of an earlier
    stage are issued when it ends; its own end-of-fit noise check is skipped (the last stage's
    is the one that speaks for the result).
    """
    t_start = time.perf_counter()
    done: list[Stage] = []
    results: list[FitResult] = []
    current = system
    stop = _CallbackStop()
    callbacks = tuple(stop.wrap(cb) for cb in options.callbacks)
    for k, stage in enumerate(choice.stages):
        last = k == len(choice.stages) - 1
        opts = dataclasses.replace(
            options,
            solver=stage.solver,
            diagnose=options.diagnose and last,
            checkpoint=_stage_folder(options.checkpoint, k, stage, len(choice.stages)),
            callbacks=callbacks,
            progress_label=f"stage {k + 1}/{len(choice.stages)}" if len(choice.stages) > 1 else "",
        )
        data, start = _stage_data(inputs, stage, choice.stages[k - 1] if k else None, results)
        if k:
            current, restarted = off_the_bound(current, system, data, options)
            stage = dataclasses.replace(stage, restarted=restarted)
        prepared = Prepared(promote_tree(current, current), data, start)
        if stage.noise == "learn":
            # the start judged at the given noise, before the noise estimate adapts to it
            prepared = _checked_start(current, prepared, opts)
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = (
                learn_noise(current, prepared, opts)
                if stage.noise == "learn"
                else run_fit(current, prepared, opts)
            )
        results.append(result)
        done.append(
            dataclasses.replace(
                stage,
                epochs=_epochs(result),
                converged=bool(result.converged),
                seconds=time.perf_counter() - t0,
            )
        )
        current = result.system
        lost = _finish_lost(results) if last and k else None
        if lost is None:
            for w in caught:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        else:  # the finish's answer, and what it warned of, discarded: the previous stage's stands
            results.pop()
            done[-1] = dataclasses.replace(done[-1], discarded=lost)
            if options.diagnose:
                results[-1] = _with_noise_check(results[-1])
            break
        if stop.stopped:  # a callback stopped the fit: no later stage
            break
        why = None if last else _finish_pointless(result)
        if why is not None:
            done += [dataclasses.replace(s, skipped=why) for s in choice.stages[k + 1 :]]
            if options.diagnose:  # this stage's result is the answer: its noise check
                results[-1] = _with_noise_check(result)
            break
    ran = dataclasses.replace(choice, stages=tuple(done))
    return _merged(results, ran, t_start)


def _stage_data(inputs: Prepared, stage: Stage, previous: Stage | None, results: list[FitResult]):
    """``(data, start states)`` of a stage.

    Its part of the data; on the previous stage's data, that stage's states.
    """
    data, start = inputs.data, inputs.states
    if stage.part is not None:
        b, t = stage.part
        data = data[:b].head(t)
        start = None if start is None else start[:b, :t]
    if previous is not None and stage.part == previous.part:
        start = results[-1].states
    return data, start


def off_the_bound(
    current: AbstractSystem, start: AbstractSystem, data, options: FitOptions
) -> tuple[AbstractSystem, tuple[str, ...]]:
    """``current`` with the entries a stage left at their bound set back to their start values.

    An entry whose transform has saturated (|d natural / dθ| ≤ 1e-6: a positive parameter below
    1e-6) is moved by no step of the next stage — its gradient in θ carries that slope — so a
    finish started there stays and reports converged, wherever its objective's maximum is (the
    mass–spring–damper at process noise 0.1: the joint fit left c at 2.6e-10, the Laplace
    evidence's maximum is c = 0.41, 15 nats higher). Restarted at the user's start value, the
    finish reaches that maximum, or goes back to the bound where the maximum is there. Returns
    the system and the restarted parameters' names.
    """
    problem, theta = FitProblem.create(
        current, data, trainable=options.trainable, overrides=options.overrides
    )
    stuck = near_bound(problem, theta)
    if not stuck.any():
        return current, ()
    _, theta0 = FitProblem.create(
        promote_tree(start, current), data, trainable=options.trainable, overrides=options.overrides
    )
    fresh = np.where(stuck, np.asarray(theta0), np.asarray(theta))
    names = tuple(n for n, s in zip(problem.parameter_names(), stuck, strict=True) if s)
    return problem.build(jnp.asarray(fresh, theta.dtype)), names


def _finish_pointless(result: FitResult) -> str | None:
    """Why the Laplace finish would not help after ``result`` (``None``: run it).

    When the joint fit's covariance is not positive definite at the noise it learned, that noise
    is degenerate for this model and data (a process noise learned → 0 on a record without any):
    Laplace EM then creeps through its whole epoch budget without converging, and its evidence
    covariance is not finite either; the joint fit's estimate is the answer, said to be so. Not
    where a parameter sits at its bound (that alone makes the covariance singular): the finish
    then runs, from that parameter's start value (:func:`off_the_bound`).
    """
    if result.problem is None or result.theta is None or not result.history:
        return None
    if near_bound(result.problem, result.theta).any():  # S singular there; the finish restarts
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # its own warning names the directions; the summary too
        cov = np.asarray(result.covariance(), np.float64)
    if cov.size and not np.all(np.isfinite(cov)):
        return (
            "the joint fit's covariance is not positive definite at the learned noise (a "
            "degenerate noise, e.g. a process noise → 0), where Laplace EM creeps without "
            "converging"
        )
    return None


def _finish_lost(results: list[FitResult]) -> str | None:
    """Why the finish's result is discarded (``None``: keep it).

    The Laplace-EM finish starts at the noise stage's θ and noise, where the noise rounds
    evaluated the same Laplace evidence; EM only climbs it. A finish that ends below that value
    by more than :data:`~ceemx.identification.analysis.noise_floor.EVIDENCE_MARGIN` nats, or at
    a non-finite one, has met a posterior its E-step cannot evaluate (a noise so small that the
    states' Hessian loses every digit): its estimate is not the evidence's maximiser, and the
    noise stage's estimate is the answer.
    """
    rounds = results[-2].noise_rounds
    history = results[-1].history
    if not rounds or not history or "log_evidence" not in history[-1]:
        return None
    before, after = rounds[-1].get("log_evidence"), history[-1]["log_evidence"]
    if before is None or not np.isfinite(before):
        return None
    if np.isfinite(after) and after >= before - EVIDENCE_MARGIN:
        return None
    return (
        f"its Laplace evidence ended at {after:.6g}, below the "
        f"{before:.6g} of the noise stage's end point it started from (the E-step cannot "
        "evaluate the posterior at this noise); the noise stage's estimate is the answer"
    )


def _with_noise_check(result: FitResult) -> FitResult:
    """The result with its end-of-fit noise check (as a last stage makes it; warns likewise)."""
    problem = result.problem
    assert problem is not None
    keep = np.setdiff1d(np.arange(result.states.shape[0]), np.asarray(result.excluded, int))
    check = noise_check(
        problem.build(result.theta),
        problem.data,
        indexed(result.states, keep),
        weights=result.weights,
        n_params=int(np.size(result.theta)),
        converged=bool(result.converged),
    )
    if check is not None and check.message:
        warn(check.message, NoiseCheckWarning)
    return dataclasses.replace(result, noise_check=check)


class _CallbackStop:
    """The user's callbacks, wrapped: once one returns ``False``, every later stage stops."""

    def __init__(self):
        self.stopped = False

    def wrap(self, callback):
        def run(info):
            if self.stopped:  # a later noise round or stage: stop at its first epoch
                return False
            out = callback(info)
            self.stopped = out is False
            return out

        return run


def _checked_start(system: AbstractSystem, inputs: Prepared, options: FitOptions) -> Prepared:
    """The inputs with their start states, checked at the given noise.

    Refused as :func:`~.run.run_fit` refuses a start
    (:func:`~ceemx.identification.fitting.health.check_start`), before the noise estimate adapts
    the noise to it.
    """
    states = start_states(inputs)
    problem, theta = FitProblem.create(
        inputs.system,
        inputs.data,
        trainable=options.trainable,
        log_prior=options.log_prior,
        overrides=options.overrides,
    )
    check_start(problem, theta, states)
    return Prepared(inputs.system, inputs.data, states)


def _stage_folder(folder: str | None, k: int, stage: Stage, n: int) -> str | None:
    if folder is None or n == 1:
        return folder
    return os.path.join(folder, f"stage-{k + 1}-{type(stage.solver).__name__}")


def _epochs(result: FitResult) -> int:
    """Epochs of a fit, every noise round's together."""
    if result.noise_rounds:
        return sum(int(r.get("epochs") or 0) for r in result.noise_rounds)
    return result.epochs


def _merged(results: list[FitResult], choice: Choice, t_start: float) -> FitResult:
    last = results[-1]
    history = [{**h, "stage": k + 1} for k, r in enumerate(results) for h in r.history]
    rounds = next((r.noise_rounds for r in results if r.noise_rounds), ())
    found = next((r.identifiability for r in reversed(results) if r.identifiability), None)
    return dataclasses.replace(
        last,
        history=history,
        converged=all(bool(r.converged) for r in results),
        noise_rounds=rounds,
        identifiability=found,
        choice=dataclasses.replace(choice, seconds=time.perf_counter() - t_start),
    )
