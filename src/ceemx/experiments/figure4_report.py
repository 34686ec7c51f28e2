"""Figure 4's scores, table and figures: Eq. 15 per test trajectory, the paper beside ours.

:func:`score_models` predicts the test trajectories with the five trained models
(:mod:`ceemx.experiments.figure4_models`) and scores them; :func:`make_table`, :func:`plot_bars`
and :func:`plot_trace` report them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ceemx.data.trajectories import Trajectories
from ceemx.evaluation import report
from ceemx.evaluation.prediction import ResidualPredictor, StateSpacePredictor, prediction_rmse
from ceemx.experiments.figure4_models import MODELS, START, Trained

__all__ = [
    "PAPER",
    "PAPER_NOTE",
    "Scores",
    "make_table",
    "paper_ordering",
    "plot_bars",
    "plot_trace",
    "score_models",
    "win_counts",
]

#: The paper's Figure 4 (mean test RMSE over 100 trajectories; NL median 0.49, NL beats H25 on
#: 87 of 100 trajectories), from the authors' published evaluation file.
PAPER = {"naive": "2.67", "LSTM": "1.30", "H25": "0.92", "SID": "0.75–0.80", "NL": "0.615"}
PAPER_NOTE = "paper: NL median 0.49, NL beats H25 on 87/100 test trajectories"


@dataclass(frozen=True)
class Scores:
    """Test predictions, their RMSE (Eq. 15) per trajectory, and the summary statistics."""

    preds: dict[str, Any]
    rmse: dict[str, np.ndarray]
    sid_model_means: np.ndarray
    mean: dict[str, float]
    median: dict[str, float]
    wins: dict[str, int]
    ordering: bool


def win_counts(rmse: dict[str, np.ndarray], against: str = "NL") -> dict[str, int]:
    """Per model: the number of test trajectories on which ``against`` has the lower RMSE."""
    ref = rmse[against]
    return {k: int(np.sum(ref < v)) for k, v in rmse.items() if k != against}


def paper_ordering(means: dict[str, float]) -> bool:
    """Whether NL < SID < H25 < LSTM < naive holds for the mean test RMSE."""
    order = ("NL", "SID", "H25", "LSTM", "naive")
    return all(means[a] < means[b] for a, b in zip(order, order[1:], strict=False))


def score_models(trained: Trained, test: Trajectories, y_std) -> Scores:
    """Predict the test trajectories with every model and score them (Eq. 15, physical units)."""
    preds = {
        "naive": trained.naive.predict(test),
        "LSTM": trained.lstm.predict(test),
        "H25": trained.h25.predict(test),
        "NL": trained.nl.predict(test),
    }
    rmse = {k: prediction_rmse(v, test, start=START, scale=y_std) for k, v in preds.items()}
    sid_rmse = np.stack(
        [
            prediction_rmse(
                ResidualPredictor(trained.naive, StateSpacePredictor(m)).predict(test),
                test,
                start=START,
                scale=y_std,
            )
            for m in trained.sids
        ]
    )
    rmse["SID"] = sid_rmse.mean(axis=0)  # per trajectory, averaged over the SID models
    means = {k: float(np.mean(rmse[k])) for k in MODELS}
    return Scores(
        preds=preds,
        rmse=rmse,
        sid_model_means=sid_rmse.mean(axis=1),
        mean=means,
        median={k: float(np.median(rmse[k])) for k in MODELS},
        wins=win_counts(rmse),
        ordering=paper_ordering(means),
    )


def _table_rows(scores: Scores, train_s, *, n_test: int, show_paper: bool) -> list[list[str]]:
    """One row per model: mean (SID: the range over its models), median, NL wins, paper, time."""
    rows = []
    for k in MODELS:
        extra = ""
        if k == "SID":
            sid = scores.sid_model_means
            extra = f" (models {sid.min():.3f}–{sid.max():.3f})"
        rows.append(
            [
                k,
                f"{scores.mean[k]:.3f}{extra}",
                f"{scores.median[k]:.3f}",
                "—" if k == "NL" else f"{scores.wins[k]}/{n_test}",
                PAPER[k] if show_paper else "—",
                f"{train_s[k]:.1f}",
            ]
        )
    return rows


def make_table(
    scores: Scores,
    trained: Trained,
    *,
    source: str,
    seed: int,
    method: str,
    n_test: int,
    show_paper: bool,
    total: float,
) -> str:
    """Markdown: the results table, whether the paper's ordering holds, the NL fit and wall time."""
    header = [
        "model",
        "mean test RMSE",
        "median",
        "NL better on",
        "paper (mean)",
        "train s",
    ]
    rows = _table_rows(scores, trained.train_s, n_test=n_test, show_paper=show_paper)
    title = (
        f"## Figure 4 — one-step prediction RMSE (Eq. 15, steps ≥ {START}, physical units), "
        f"{source}, seed {seed}, NL by {method}"
    )
    means, nl_record = scores.mean, trained.nl_record
    lines = [
        title,
        "",
        report.markdown_table(header, rows),
        "",
        f"Paper ordering NL < SID < H25 < LSTM < naive holds: "
        f"**{'yes' if scores.ordering else 'no'}**"
        f" (ours: {' < '.join(sorted(MODELS, key=lambda k: means[k]))}). {PAPER_NOTE}.",
        f"NL model: {nl_record['epochs']} CE-EM epochs ({nl_record['per_epoch_s']:.2f} s/epoch, "
        f"first {nl_record['first_epoch_s']:.1f} s incl. compile), best validation epoch "
        f"{nl_record['best_epoch']}, {nl_record['parameters']} parameters. "
        f"Total wall time {total:.1f} s.",
    ]
    return "\n".join(lines)


def plot_bars(rmse, sid_model_means, path, source) -> None:
    """Figure 4a: per-trajectory test RMSE of each model (points) with the mean (bar)."""
    plt = report.plt()
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    rng = np.random.default_rng(0)
    for i, k in enumerate(MODELS):
        v = rmse[k]
        err = np.std(sid_model_means) if k == "SID" else None
        ax.bar(i, np.mean(v), color="0.85", edgecolor="0.3", yerr=err, capsize=4)
        ax.plot(i + rng.uniform(-0.25, 0.25, v.shape), v, ".", ms=3, alpha=0.6)
    ax.set_xticks(range(len(MODELS)), list(MODELS))
    ax.set_ylabel("test RMSE (Eq. 15)")
    ax.set_title(f"One-step prediction, {source}", fontsize=9)
    report.save_figure(fig, path)


def plot_trace(test, preds, rmse, stats, names, path) -> None:
    """Figure 4b: measured and predicted outputs on a hard test trajectory (H25's 90th pct.)."""
    plt = report.plt()
    order = np.argsort(rmse["H25"])
    b = int(order[int(0.9 * (len(order) - 1))])
    y_mean, y_std = stats
    y = np.asarray(test.y[b]) * y_std + y_mean
    m = min(3, y.shape[-1])
    fig, axes = plt.subplots(m, 1, figsize=(7, 1.9 * m + 0.4), sharex=True, squeeze=False)
    t = np.arange(y.shape[0])
    for j in range(m):
        ax = axes[j, 0]
        ax.plot(t, y[:, j], "k", lw=1.2, label="measured")
        for k, style in (("H25", "C1--"), ("NL", "C0-")):
            ax.plot(t, np.asarray(preds[k][b, :, j]) * y_std[j] + y_mean[j], style, lw=0.9, label=k)
        ax.set_ylabel(names[j] if j < len(names) else f"y{j}")
    axes[0, 0].legend(fontsize=7, ncol=3)
    axes[-1, 0].set_xlabel("time step")
    fig.suptitle(f"test trajectory {b}: H25 RMSE {rmse['H25'][b]:.3f}, NL {rmse['NL'][b]:.3f}")
    report.save_figure(fig, path)
