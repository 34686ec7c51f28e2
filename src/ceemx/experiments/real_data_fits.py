"""The fits of ``ceemx experiment real_data``: gray-box, linear baselines, learned models, scores.

Everything a fit needs to know about its dataset comes from the dataset's registry entry
(:data:`ceemx.datasets.REGISTRY`) through a :class:`Plan`: the gray-box model and its options,
the settings chosen by hand (process noise, scoring start, network size, epochs) with the run's
changes (:class:`Settings`), and whether the estimation record is fitted whole or in windows.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ceemx.data.trajectories import Trajectories
from ceemx.datasets import REGISTRY, RealDataset
from ceemx.datasets.registry import DatasetEntry, HandChosen, Windowing
from ceemx.experiments import common

__all__ = [
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
        entry.chosen, max_epochs=settings.max_epochs, hybrid_epochs=settings.hybrid_epochs
    )
    windowing = entry.windowing
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


def test_records(plan: Plan) -> dict:
    """The official test records, cut to ``settings.test_samples`` when set."""
    tests = dict(plan.data.tests)
    n = plan.settings.test_samples
    if n is not None:
        tests = {k: v[:, :n] for k, v in tests.items()}
    return tests


def inputs_for(system, data):
    """The data as the system reads it: [u_t, u_{t+1}] under a first-order hold."""
    from ceemx.data.trajectories import foh_inputs

    if getattr(system, "hold", "zoh") != "foh":
        return data
    out = foh_inputs(data)
    assert isinstance(out, Trajectories)
    return out


def reads(system):
    """How ``system`` reads a record (a function of the record).

    The linear models and hybrids of them: with the constant input channel of
    :func:`ceemx.baselines.with_constant_input`; the rest: :func:`inputs_for`.
    """
    from ceemx.baselines import with_constant_input
    from ceemx.systems import LinearSystem

    if isinstance(getattr(system, "physics", system), LinearSystem):
        return with_constant_input
    return lambda data: inputs_for(system, data)


def score(system, test, n_init: int, scale: float, options: dict[str, Any]):
    """:func:`ceemx.benchmark_score` of ``system`` on ``test`` and its wall time."""
    from ceemx.evaluation.metrics import benchmark_score

    t0 = time.perf_counter()
    s = benchmark_score(system, reads(system)(test), n_init, scale=scale, **options)
    return s, time.perf_counter() - t0


def _scalar_parameters(guess, system) -> dict[str, float]:
    """The learned scalar parameters of a fitted gray-box model, by name."""
    from ceemx.identification.problem import trainable_mask

    learned = trainable_mask(guess)
    return {
        f.name: float(np.asarray(getattr(system, f.name)))
        for f in dataclasses.fields(system)
        if getattr(learned, f.name, False) is True and np.ndim(getattr(system, f.name)) == 0
    }


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


def fit_linear(train, order: int):
    """The linear baseline: N4SID of the same order, affine and refitted for simulation.

    :func:`ceemx.baselines.fit_affine_sid` (plain N4SID free-ran the tanks to 532.5 V).
    """
    from ceemx.baselines import fit_affine_sid

    t0 = time.perf_counter()
    try:
        model = fit_affine_sid(train, state_dim=order)
    except ValueError as e:  # too little data for the horizon, etc.
        return None, {"error": str(e), "wall_s": time.perf_counter() - t0}
    radius = float(np.max(np.abs(np.linalg.eigvals(np.asarray(model.A)))))
    return model, {"wall_s": time.perf_counter() - t0, "spectral_radius": radius}


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


def _net_leaves(system):
    import equinox as eqx
    import jax.tree_util as jtu

    terms = (system.dynamics_term, system.observation_term)
    return jtu.tree_leaves(
        eqx.filter([t.net for t in terms if t is not None], eqx.is_inexact_array)
    )


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
