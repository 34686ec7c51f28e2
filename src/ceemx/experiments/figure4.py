"""Paper Figure 4 (§4.2): one-step prediction of accelerations with hidden states — five models.

Models (paper §4.2.2–4.2.3), all predicting y_t one step ahead through
:class:`ceemx.evaluation.prediction.AbstractPredictor`, all scored by Eq. 15 as the authors'
evaluation file (RMS over steps 25–499 and the 6 outputs, in physical units):

- *naive*: y_t = NN(u_t) (MLP 8×32 tanh, Adam 1e-4 decayed, normalised RMS loss, best validation);
- *H25*: y_t = NN(u_{t−24..t}), same network and training;
- *LSTM*: the naive model plus a 2×32 LSTM of the naive model's residual ỹ = y − NN(u) from u;
- *SID*: the naive model plus a 10-state linear model of ỹ by multi-trajectory N4SID, fitted on
  10 random subsets of 100 training trajectories; predictions by the Kalman filter;
- *NL* (paper Eq. 17): the naive model plus x_{t+1} = A x + B u, ỹ = C x + D u + NN(x, u),
  n = 10, σ_w = σ_v = 1, hot-started from the best SID model, NN output gain 0.1, trained by CE-EM
  (Algorithm 1: smoothing trust region 0.1, Adam learning rates 5·10⁻⁴ (observation model) and
  10⁻³ (dynamics), 500 steps per epoch on minibatches of trajectories, learning trust region 0.5,
  states initialised at 0.01·N(0, 1)); the epoch with the best validation RMSE is kept; predictions
  by the extended Kalman filter with x₁ ~ N(0, I), Q = R = I (the authors' evaluation).

Data: by default the documented helicopter-like generator (:mod:`ceemx.datasets.heli_sim`,
docs/helicopter_benchmark.md), since the Stanford dataset cannot be downloaded here; ``data=DIR``
reads the paper's published dataset (:func:`ceemx.datasets.load_helicopter`); ``dataset=NAME``
runs the same five models on windows of a real dataset's records (cascaded tanks, Silverbox,
coupled electric drives; :func:`ceemx.datasets.window_splits`).

The authors' smoothing trust region is a residual r·(x − x_k) in their ½-sum of squares, so
ρ_x = r²/2 = 0.005 in ours (ρ_x‖x − x_k‖²); their learning trust region is added as
r·‖θ − θ_k‖², so ρ_θ = 0.5. Their Adam restarts every epoch on the full batch with gradients
clipped to norm 1; ours keeps its moments across epochs (:class:`ceemx.OptaxLearner`) and uses
minibatches of trajectories, with the same clipping.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from ceemx.datasets import REGISTRY
from ceemx.evaluation import report
from ceemx.experiments import common
from ceemx.experiments.figure4_models import (
    MODELS,
    SMOKE,
    Settings,
    Splits,
    Trained,
    printer,
    train_models,
)
from ceemx.experiments.figure4_report import (
    PAPER,
    Scores,
    make_table,
    plot_bars,
    plot_trace,
    score_models,
)

__all__ = ["DATASETS", "NAME", "load_splits", "run"]

NAME = "figure4"
DATASETS = tuple(REGISTRY)


def load_splits(*, data: str | None, dataset: str | None, smoke: bool, seed: int) -> Splits:
    """The data of one run: the generator, the paper's dataset, or a real dataset's windows."""
    from ceemx import datasets

    if data is not None and dataset is not None:
        raise ValueError(
            "give `data` (the helicopter dataset) or `dataset` (a real dataset), not both."
        )
    if dataset is not None:
        if dataset not in DATASETS:
            raise ValueError(f"unknown dataset {dataset!r}; choose from {', '.join(DATASETS)}.")
        w = datasets.window_splits(dataset, smoke=smoke)
        return Splits(
            w.train,
            w.valid,
            w.test,
            np.asarray(w.y_mean),
            np.asarray(w.y_std),
            w.source,
            tuple(w.output_names),
        )
    if data is not None:
        h = datasets.load_helicopter(data)
    elif smoke:
        h = datasets.helicopter_like(seed, n_train=8, n_valid=4, n_test=4, steps=80)
    else:
        h = datasets.helicopter_like(seed)
    names = ("ax", "ay", "az", "ṗ", "q̇", "ṙ")
    return Splits(
        h.train, h.valid, h.test, np.asarray(h.y_mean), np.asarray(h.y_std), h.source, names
    )


def _summary(
    s: Splits,
    trained: Trained,
    scores: Scores,
    *,
    seed: int,
    method: str,
    settings: Settings,
    total: float,
    table: str,
) -> dict[str, Any]:
    """The results of a run as ``results.json`` holds them."""
    return {
        "experiment": NAME,
        "source": s.source,
        "seed": seed,
        "method": method,
        "settings": settings.__dict__,
        "sizes": [s.train.batch_size, s.valid.batch_size, s.test.batch_size],
        "rmse": {k: scores.rmse[k].tolist() for k in MODELS},
        "sid_model_means": scores.sid_model_means.tolist(),
        "sid_valid": trained.sid_valid,
        "mean": scores.mean,
        "median": scores.median,
        "nl_better_on": scores.wins,
        "paper_ordering": scores.ordering,
        "train_s": trained.train_s,
        "nn_history": trained.nn_history,
        "nl": trained.nl_record,
        "wall_s": total,
        "paper": PAPER,
        "table": table,
    }


def run(
    *,
    smoke: bool = False,
    out=None,
    seeds: int | Sequence[int] | None = None,
    method: str | None = None,
    max_epochs: int | None = None,
    data: str | None = None,
    dataset: str | None = None,
    settings: Settings | None = None,
    verbose: bool = True,
) -> dict[str, Any]:
    """Train the five models, score them on the test trajectories, write table and figures.

    Args:
        smoke: tiny sizes (seconds; what the tests run).
        out: output folder (default ``results/figure4`` or ``results/figure4-NAME``).
        seeds: one seed (the generator's and the models' initialisation; default 0).
        method: the NL model's CE-EM solver: ``"alternate"`` (Algorithm 1, default) or
            ``"joint"`` (the joint LM on a subset of trajectories: its Schur system is dense in θ).
        max_epochs: CE-EM epochs of the NL model (default: ``settings.nl_epochs``).
        data: folder of the paper's helicopter dataset (default: the generator).
        dataset: a real dataset (``cascaded_tanks``, ``silverbox``, ``coupled_electric_drives``).
        settings: sizes and budgets (default :class:`Settings` or :data:`SMOKE`).
        verbose: print progress and the table.

    Returns:
        The results (also in ``results.json``) with the Markdown table under ``"table"``.
    """
    common.enable_x64()
    method = "alternate" if method is None else method
    seed_values = common.seed_list(seeds, first=0, default=1)
    if len(seed_values) != 1:
        raise ValueError(f"figure4 runs one seed at a time; got {seed_values}.")
    seed = seed_values[0]
    settings = settings or (SMOKE if smoke else Settings())
    if max_epochs is not None:
        settings = Settings(**{**settings.__dict__, "nl_epochs": max_epochs})
    default_out = "results/figure4" + ("" if dataset is None else f"-{dataset}")
    outdir = report.output_dir(out, default_out)
    t_start = time.perf_counter()
    s = load_splits(data=data, dataset=dataset, smoke=smoke, seed=seed)
    say = printer(verbose)
    say(
        f"[figure4] data: {s.source}; train/valid/test = {s.train.batch_size}/"
        f"{s.valid.batch_size}/{s.test.batch_size} trajectories of {s.train.y.shape[1]} steps"
    )
    trained = train_models(s, settings, method=method, seed=seed, verbose=verbose)
    scores = score_models(trained, s.test, s.y_std)
    total = time.perf_counter() - t_start
    table = make_table(
        scores,
        trained,
        source=s.source,
        seed=seed,
        method=method,
        n_test=s.test.batch_size,
        show_paper=data is not None or dataset is None,
        total=total,
    )
    summary = _summary(
        s, trained, scores, seed=seed, method=method, settings=settings, total=total, table=table
    )
    report.save_json(outdir / "results.json", summary)
    report.save_text(outdir / "table.md", table)
    plot_bars(scores.rmse, scores.sid_model_means, outdir / "figure4a.png", s.source)
    plot_trace(
        s.test,
        scores.preds,
        scores.rmse,
        (s.y_mean, s.y_std),
        s.output_names,
        outdir / "figure4b.png",
    )
    say(table)
    return summary
