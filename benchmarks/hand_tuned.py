"""The former, hand-tuned fits of ``ceemx experiment real_data`` (the "before" of the ledger).

Before :func:`ceemx.fit_hybrid` chose them on the training record, the experiment read settings
chosen by hand per dataset (:data:`HAND`: process noise, the scoring start, epochs) and fitted
Silverbox's long record in windows of its first 8192 samples (:data:`WINDOWING`). This module
keeps that procedure, unchanged, for the ablation scripts (``real_data_ablations.py``,
``tanks_model.py``) and to reproduce the former scores; the library no longer holds any of it.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ceemx.data.trajectories import Trajectories
from ceemx.datasets import REGISTRY, RealDataset
from ceemx.datasets.registry import DatasetEntry
from ceemx.experiments import common
from ceemx.experiments.real_data_fits import (
    _net_leaves,
    _scalar_parameters,
    fit_linear,
    inputs_for,
    reads,
    score,
    test_records,
)

__all__ = [
    "HAND",
    "WINDOWING",
    "HandChosen",
    "Windowing",
    "SMOKE",
    "Plan",
    "Settings",
    "fit_graybox",
    "fit_learned",
    "fit_linear",
    "learned_starts",
    "make_plan",
    "reads",
    "refine_linear",
    "score",
    "split",
    "test_records",
    "training_data",
]


@dataclass(frozen=True)
class Windowing:
    """How a long estimation record is fitted: windows of its first samples.

    The first ``samples`` samples are cut into windows of ``window`` samples with half overlap;
    the samples after them hold the validation data of early stopping.

    Attributes:
        samples: samples fitted, from the record's start.
        window: samples per window.
    """

    samples: int
    window: int


@dataclass(frozen=True)
class HandChosen:
    """Settings chosen by hand for one dataset, not by a selection procedure.

    Attributes:
        process_noise: the gray-box model's process-noise std (its ``process_noise`` field).
        score_options: options of :func:`ceemx.benchmark_score` for every model on this
            dataset (how the initial state of a free run is started).
        linear_noise: (process, observation) noise std of the linear baseline's CE-EM
            refinement, × std(y) (:func:`ceemx.baselines.refine_linear`).
        width: hidden units of a learned term's network.
        depth: hidden layers of a learned term's network.
        prior_std: std of the learned term's Gaussian weight prior (weight decay).
        max_epochs: iterations of the gray-box and linear CE-EM fits.
        hybrid_epochs: joint iterations of the learned models (early stopping usually ends
            them sooner).
    """

    process_noise: float
    score_options: Mapping[str, Any] = field(default_factory=dict)
    #: a small process noise makes the CE fit close to a simulation-error (output-error) fit:
    #: the tanks' test RMSE 1.88 V (N4SID) → 0.699 V (1e-4: 0.673 V, 1e-2: 0.870 V; fixed, not
    #: selected on a test record)
    linear_noise: tuple[float, float] = (1e-3, 0.05)
    width: int = 16
    depth: int = 1
    prior_std: float = 1.0
    max_epochs: int = 200
    #: Silverbox's neural model still improves at 200 (multisine 1.94 mV after 30 iterations,
    #: 0.44 after 100, 0.33 after 200)
    hybrid_epochs: int = 200


#: The former hand-chosen settings by dataset (their reasons: docs/results.md).
HAND: dict[str, HandChosen] = {
    # chosen on the held-out tail of the estimation record: validation 0.262 → 0.219 V
    "cascaded_tanks": HandChosen(process_noise=0.001),
    # from an example script: multisine test 1.785 → 0.933 mV
    "silverbox": HandChosen(process_noise=1e-4),
    # chosen with the test scores in view; two starts of the initial state for the even sensor
    "coupled_electric_drives": HandChosen(
        process_noise=0.002, score_options={"warm_process_noise": (1.0, None)}
    ),
}
#: The former windowing of a long record (Silverbox: windows of its first 8192 samples).
WINDOWING: dict[str, Windowing] = {"silverbox": Windowing(samples=8192, window=512)}


@dataclass(frozen=True)
class Settings:
    """One run's budgets and its changes to the registry's hand-chosen settings.

    Attributes:
        max_epochs: iterations of the gray-box and linear fits (``None``: the entry's).
        hybrid_epochs: joint iterations of the learned models (``None``: the entry's).
        fit_samples: samples fitted of a record fitted in windows (``None``: the entry's).
        window: window length of such a record (``None``: the entry's).
        test_samples: samples of each official test record scored (``None``: all).
        hybrid: fit the learned models beside the gray-box (physics only) and N4SID.
        patience: early stopping's patience (epochs without a better validation score).
        validation_fraction: the tail of each training record held out for early stopping
            (never the test records).
    """

    max_epochs: int | None = None
    hybrid_epochs: int | None = None
    fit_samples: int | None = None
    window: int | None = None
    test_samples: int | None = None
    hybrid: bool = True
    patience: int = 5
    validation_fraction: float = 0.2


SMOKE = Settings(max_epochs=3, hybrid_epochs=2, fit_samples=1024, window=256, test_samples=300)


@dataclass(frozen=True)
class Plan:
    """One dataset's run: its registry entry, its records, and the settings in force.

    Attributes:
        entry: the dataset's registry entry.
        data: its official records.
        chosen: the entry's hand-chosen settings with the run's changes.
        windowing: the entry's windowing with the run's changes (``None``: records fitted whole).
        settings: the run's settings.
    """

    entry: DatasetEntry
    data: RealDataset
    chosen: HandChosen
    windowing: Windowing | None
    settings: Settings


def _changed(obj, **changes):
    """``obj`` with the changes that are not ``None``."""
    return dataclasses.replace(obj, **{k: v for k, v in changes.items() if v is not None})


def make_plan(name: str, settings: Settings, data: RealDataset | None = None) -> Plan:
    """The :class:`Plan` of dataset ``name`` (its records read unless ``data`` is given)."""
    from ceemx import datasets

    entry = REGISTRY[name]
    chosen = _changed(
        HAND[name], max_epochs=settings.max_epochs, hybrid_epochs=settings.hybrid_epochs
    )
    windowing = WINDOWING.get(name)
    if windowing is not None:
        windowing = _changed(windowing, samples=settings.fit_samples, window=settings.window)
    data = datasets.real_dataset(name) if data is None else data
    return Plan(entry, data, chosen, windowing, settings)


def training_data(plan: Plan) -> Trajectories:
    """The records the gray-box and linear models are fitted to (a long record: its windows)."""
    w = plan.windowing
    if w is None:
        return plan.data.train
    return plan.data.train[:, : w.samples].windows(w.window, w.window // 2)


def split(plan: Plan) -> tuple[Trajectories, Trajectories]:
    """(fit records, validation records) for the learned models, both from the training data.

    The tail ``validation_fraction`` of every training record is held out (a record fitted in
    windows: the estimation-record samples after those fitted, cut into the same windows); the
    official test records are never used.
    """
    ds, fraction = plan.data, plan.settings.validation_fraction
    if plan.windowing is not None:
        a = plan.windowing.samples
        b = a + max(int(fraction * a), 2 * ds.n_init)
        return training_data(plan), ds.train[:, a:b]
    train = ds.train
    cut = train.num_steps - max(int(fraction * train.num_steps), 2 * ds.n_init)
    return train[:, :cut], train[:, cut - ds.n_init :]


def fit_graybox(plan: Plan, train, method: str, dtype):
    """The gray-box model fitted by CE-EM from its physical guess; returns (result, summary)."""
    from ceemx import JointLM, fit

    model = plan.entry.model
    guess = model.factory(dtype=dtype, **model.options, process_noise=plan.chosen.process_noise)
    solver = JointLM() if method == "joint" else common.make_solver("alternate")
    data = inputs_for(guess, train)
    t0 = time.perf_counter()
    result = fit(guess, data, solver=solver, max_epochs=plan.chosen.max_epochs)
    wall = time.perf_counter() - t0
    epoch_s = [h["time"] for h in result.history]
    return result, {
        "epochs": len(result.history),
        "converged": bool(result.converged),
        "wall_s": wall,
        "first_epoch_s": epoch_s[0] if epoch_s else math.nan,
        "steady_epoch_s": float(np.median(epoch_s[1:])) if len(epoch_s) > 1 else math.nan,
        "parameters": _scalar_parameters(guess, result.system),
        "J": float(result.history[-1]["J"]) if result.history else math.nan,
    }


def refine_linear(n4sid, train, plan: Plan):
    """N4SID's model refined by CE-EM (:func:`ceemx.baselines.refine_linear`).

    The noise is the entry's hand-chosen ``linear_noise``. Returns the fit result (its states
    start the neural model) and its summary.
    """
    from ceemx.baselines import refine_linear as refine
    from ceemx.baselines import with_constant_input

    t0 = time.perf_counter()
    process_noise, obs_noise = plan.chosen.linear_noise
    result = refine(
        n4sid,
        with_constant_input(train),
        process_noise=process_noise,
        obs_noise=obs_noise,
        max_epochs=plan.chosen.max_epochs,
    )
    A = np.asarray(getattr(result.system, "A"))  # noqa: B009  (a LinearSystem)
    return result, {
        "epochs": len(result.history),
        "converged": bool(result.converged),
        "wall_s": time.perf_counter() - t0,
        "spectral_radius": float(np.max(np.abs(np.linalg.eigvals(A)))),
    }


def learned_starts(plan: Plan, method: str, physics, refined):
    """The fits the learned models start from, none of which has seen the validation records.

    Early stopping scores each epoch on the tail of the training records (:func:`split`); a
    start fitted on the whole record has seen that tail, which makes its own validation score
    optimistic and stops the learned model at or near the start. So the starts are the physics
    and the CE-EM linear fits of the fit part alone (a record fitted in windows: its validation
    samples lie after the fitted ones already, the full fits are the starts). Returns (physics
    fit, linear fit or ``None``).
    """
    import jax.numpy as jnp

    if plan.windowing is not None:
        return physics, refined
    fit_part, _ = split(plan)
    start, _ = fit_graybox(plan, fit_part, method, jnp.float64)
    if refined is None:
        return start, None
    n4sid, _ = fit_linear(fit_part, start.system.state_dim)
    return start, None if n4sid is None else refine_linear(n4sid, fit_part, plan)[0]


def fit_learned(plan: Plan, base, states, *, neural: bool, observation=False):
    """A learned term on ``base``, trained by the joint method with early stopping.

    ``neural=False``: the hybrid (the physics fit plus a learned term in its vector field, the
    physical state bounds); ``neural=True``: the neural state-space model (the CE-EM linear
    model plus a learned term in its transition; no physics, no bounds). ``observation``: a
    learned term in the observation too (not used by the experiment).
    """
    import jax.numpy as jnp

    from ceemx import JointLM, fit, hybrid, weight_decay
    from ceemx.evaluation.early_stopping import EarlyStopping

    model, chosen, n_init = plan.entry.model, plan.chosen, plan.data.n_init
    read = reads(base)
    fit_data, val = split(plan)
    fit_data, val = read(fit_data), read(val)  # ``states`` are the fit part's (learned_starts)
    learned = hybrid(
        base,
        fit_data,
        states=states,
        dynamics=True if neural else model.targets,
        observation=observation,
        width=chosen.width,
        depth=chosen.depth,
        prior_std=chosen.prior_std,
        **({} if neural else dict(model.bounds)),
    )
    stopper = EarlyStopping(
        val,
        n_init,
        patience=plan.settings.patience,
        start=learned,
        score_options=dict(chosen.score_options),
    )
    t0 = time.perf_counter()
    result = fit(
        learned,
        fit_data,
        jnp.asarray(states),
        solver=JointLM(),
        trainable=learned.trainable("both"),
        log_prior=weight_decay,
        max_epochs=chosen.hybrid_epochs,
        callbacks=[stopper],
        diagnose=False,
    )
    wall = time.perf_counter() - t0
    result = stopper.restore(result)
    return result.system, {
        "epochs": len(result.history),
        "best_epoch": stopper.best_epoch,
        "validation_rmse": stopper.best_rmse,
        "wall_s": wall,
        "weights": int(sum(np.size(w) for w in _net_leaves(result.system))),
    }
