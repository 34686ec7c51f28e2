"""The fits of ``ceemx experiment real_data``: gray-box, linear baselines, learned models, scores.

Every dataset goes through one code path with one set of settings (:class:`Settings`, the same
for every dataset): the physics and hybrid by :func:`ceemx.fit_hybrid` from the registry entry's
gray-box model at its default guess, the neural state-space model by :func:`ceemx.fit_hybrid`
from the N4SID model of the same order, each choosing its noise weighting and the learned term's
training length on the held-out tail of the training records. What a fit reads from the registry
is the protocol (records, ``n_init``, units) and the user's physics model (its structure, state
bounds, where a term enters); nothing here names a dataset
(``tests/test_real_data_selection.py`` checks it).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ceemx.data.trajectories import Trajectories
from ceemx.datasets import REGISTRY, RealDataset
from ceemx.datasets.registry import DatasetEntry
from ceemx.evaluation.hybrid_selection import NOISE_FACTORS

__all__ = [
    "SMOKE",
    "Plan",
    "Settings",
    "fit_linear",
    "fit_selected",
    "linear_guess",
    "make_plan",
    "reads",
    "score",
    "test_records",
    "training_data",
    "window_of",
]

#: How the initial state of every free run is set, on every dataset: two starts of the
#: initial-state smoother (its weak-dynamics pass and none), the lower window simulation error
#: kept — a sensor with several window minima (a sign-insensitive one) needs both, the others
#: lose nothing.
SCORE_OPTIONS: dict[str, Any] = {"warm_process_noise": (1.0, None)}


@dataclass(frozen=True)
class Settings:
    """One run's settings, the same for every dataset.

    Attributes:
        max_epochs: iterations of each physics and linear fit.
        hybrid_epochs: iterations of a learned term's training at most (early stopping on the
            validation tail usually ends it sooner).
        max_samples: samples of each training record used (its first ones; a budget: the rest
            of a longer record is not read).
        window: a record of more than ``4 × window`` samples is fitted in windows of ``window``
            samples with half overlap.
        test_samples: samples of each official test record scored (``None``: all).
        hybrid: fit the learned models beside the gray-box (physics only) and N4SID.
        patience: early stopping's patience (iterations without a better validation score).
        validation_fraction: the tail of each training record held out for the selection
            (never the test records).
        noise_factors: the candidate factors on each model's default process noise.
        linear_noise: (process, observation) noise std of the linear model's guess, × std(y)
            (the loosest candidate of its selection).
        width: hidden units of a learned term's network.
        depth: hidden layers of a learned term's network.
        prior_std: σ of the learned term's Gaussian weight prior (weight decay).
        refit: refit the selected settings on every training sample.
        score_options: options of :func:`ceemx.benchmark_score` for every free run.
    """

    max_epochs: int = 200
    hybrid_epochs: int = 200
    max_samples: int = 10240
    window: int = 512
    test_samples: int | None = None
    hybrid: bool = True
    patience: int = 30
    validation_fraction: float = 0.2
    noise_factors: tuple[float, ...] = NOISE_FACTORS
    linear_noise: tuple[float, float] = (1e-3, 0.05)
    width: int = 16
    depth: int = 1
    prior_std: float = 1.0
    refit: bool = True
    score_options: dict[str, Any] = field(default_factory=lambda: dict(SCORE_OPTIONS))


SMOKE = Settings(
    max_epochs=3,
    hybrid_epochs=2,
    max_samples=1280,
    window=256,
    test_samples=300,
    noise_factors=(1.0, 0.1),
)


@dataclass(frozen=True)
class Plan:
    """One dataset's run: its registry entry, its records, and the settings in force.

    Attributes:
        entry: the dataset's registry entry.
        data: its official records.
        settings: the run's settings.
    """

    entry: DatasetEntry
    data: RealDataset
    settings: Settings


def make_plan(name: str, settings: Settings, data: RealDataset | None = None) -> Plan:
    """The :class:`Plan` of dataset ``name`` (its records read unless ``data`` is given)."""
    from ceemx import datasets

    entry = REGISTRY[name]
    data = datasets.real_dataset(name) if data is None else data
    return Plan(entry, data, settings)


def training_data(plan: Plan) -> Trajectories:
    """The training records the fits read: the first ``max_samples`` samples of each."""
    train = plan.data.train
    return train[:, : plan.settings.max_samples]


def window_of(plan: Plan, data: Trajectories) -> int | None:
    """The window a record is fitted in (``None``: whole), by its length alone."""
    w = plan.settings.window
    return w if data.num_steps > 4 * w else None


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
    import dataclasses

    from ceemx.identification.problem import trainable_mask

    learned = trainable_mask(guess)
    return {
        f.name: float(np.asarray(getattr(system, f.name)))
        for f in dataclasses.fields(system)
        if getattr(learned, f.name, False) is True and np.ndim(getattr(system, f.name)) == 0
    }


def fit_info(result, guess=None) -> dict[str, Any]:
    """A physics (or linear) fit's summary: iterations, convergence, times, parameters."""
    epoch_s = [h["time"] for h in result.history]
    info = {
        "epochs": len(result.history),
        "converged": bool(result.converged),
        "wall_s": float(sum(epoch_s)),
        "first_epoch_s": epoch_s[0] if epoch_s else math.nan,
        "steady_epoch_s": float(np.median(epoch_s[1:])) if len(epoch_s) > 1 else math.nan,
        "J": float(result.history[-1]["J"]) if result.history else math.nan,
    }
    if guess is not None:
        info["parameters"] = _scalar_parameters(guess, result.system)
    return info


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


def linear_guess(n4sid, train, settings: Settings):
    """N4SID's model with the noise of :func:`ceemx.baselines.refine_linear` (× std(y)).

    ``train`` as the model reads it (:func:`ceemx.baselines.with_constant_input`).
    """
    import jax.numpy as jnp

    from ceemx.baselines.sid import output_spread
    from ceemx.systems import LinearSystem

    scale, per_output = output_spread(train)
    process, obs = settings.linear_noise
    return LinearSystem(
        n4sid.A,
        n4sid.C,
        n4sid.B,
        n4sid.D,
        process_noise=process * scale,
        obs_noise=jnp.asarray(obs * per_output, train.y.dtype),
    )


def _net_leaves(system):
    import equinox as eqx
    import jax.tree_util as jtu

    terms = (getattr(system, "dynamics_term", None), getattr(system, "observation_term", None))
    return jtu.tree_leaves(
        eqx.filter([t.net for t in terms if t is not None], eqx.is_inexact_array)
    )


def fit_selected(plan: Plan, guess, train, *, neural: bool, progress=None):
    """:func:`ceemx.fit_hybrid` of ``guess`` on ``train`` with the run's settings.

    ``neural=False``: the gray-box guess, its learned term where the entry's model says and
    its physical state bounds; ``neural=True``: a linear guess, the term on every equation, no
    bounds. ``train`` as the guess reads it. Returns (the :class:`ceemx.HybridFit`, summary).
    """
    from ceemx import fit_hybrid

    s, model = plan.settings, plan.entry.model
    t0 = time.perf_counter()
    sel = fit_hybrid(
        guess,
        train,
        n_init=plan.data.n_init,
        dynamics=True if neural else model.targets,
        width=s.width,
        depth=s.depth,
        prior_std=s.prior_std,
        noise_factors=s.noise_factors,
        validation_fraction=s.validation_fraction,
        window=window_of(plan, train),
        max_epochs=s.max_epochs,
        term_epochs=s.hybrid_epochs if s.hybrid else 0,
        patience=s.patience,
        refit=s.refit,
        score_options=s.score_options,
        progress=progress,
        **({} if neural else dict(model.bounds)),
    )
    info = {
        "weights": int(sum(np.size(w) for w in _net_leaves(sel.held_out))),
        "best_epoch": sel.best_epoch,
        "epochs": sel.term_epochs,
        "validation_rmse": sel.validation_rmse["hybrid"],
        "wall_s": time.perf_counter() - t0,
        "selection": sel.record(),
    }
    return sel, info
