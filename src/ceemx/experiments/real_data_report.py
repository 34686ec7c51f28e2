"""The report of ``ceemx experiment real_data``: the tables, the figure, the JSON summary."""

from __future__ import annotations

from typing import Any

import numpy as np

from ceemx.datasets import REGISTRY

__all__ = ["json_datasets", "make_tables", "plot", "table_row"]


def table_row(name: str, test_name: str, entry: dict[str, Any], unit: str) -> list[str]:
    """One row of the results table: every model's RMSE and up to three published ones."""

    def cell(key):
        value = entry.get(f"{key}_rmse")
        return "—" if value is None else f"{value:.4g}"

    return [
        name,
        test_name,
        cell("graybox"),
        cell("hybrid"),
        cell("neural"),
        cell("linear_ceem"),
        cell("linear"),
        "; ".join(entry["published"][:3]) or "—",
        unit,
    ]


def make_tables(results: list[dict], *, method: str, wall: float) -> str:
    """Markdown: the scores beside the published ones, then each fit's epochs, time, parameters."""
    from ceemx.evaluation import report

    header = [
        "dataset",
        "test",
        "physics (gray-box)",
        "physics + learned term",
        "neural state space (linear + learned term)",
        "linear (CE-EM from N4SID)",
        "N4SID (affine, refitted)",
        "published",
        "unit",
    ]
    table = report.markdown_table(header, [row for r in results for row in r["rows"]])
    fits = report.markdown_table(
        ["dataset", "epochs", "converged", "fit s (compile incl.)", "s/epoch after the first",
         "parameters"],
        [
            [
                r["dataset"],
                r["fit"]["epochs"],
                r["fit"]["converged"],
                f"{r['fit']['wall_s']:.1f}",
                f"{r['fit']['steady_epoch_s']:.3f}",
                ", ".join(f"{k} = {v:.4g}" for k, v in r["fit"]["parameters"].items()),
            ]
            for r in results
        ],
    )  # fmt: skip
    learned_rows = [
        [
            r["dataset"],
            key,
            info["weights"],
            f"{info['best_epoch']} / {info['epochs']}",
            f"{info['validation_rmse']:.4g}",
            f"{info['wall_s']:.1f}",
        ]
        for r in results
        for key, info in r.get("learned", {}).items()
    ]
    learned = ""
    if learned_rows:
        learned = "\n\n" + report.markdown_table(
            ["dataset", "model", "weights", "best epoch / epochs", "validation RMSE", "fit s"],
            learned_rows,
        )
    every = "; ".join(
        f"{r['dataset']} {t}: "
        + ", ".join(
            f"{label} {e[key + '_rmse_every_sample']:.4g}"
            for key, label in (("graybox", "gray-box"), ("hybrid", "hybrid"), ("linear", "N4SID"))
            if key + "_rmse_every_sample" in e
        )
        for r in results
        for t, e in r["tests"].items()
    )
    learned += (
        "\n\nOver every test sample, the n_init outputs included (how some datasets' published "
        f"results are scored): {every}."
    )
    return (
        f"## CE-EM on real datasets (method {method}; official protocol: free-run "
        f"simulation RMSE after n_init test samples)\n\n{table}\n\n{fits}{learned}\n\n"
        "Physics + learned term: the gray-box model with a zero-initialised MLP added to its "
        "vector field (ceemx.hybrid), trained with it by the joint method, weight decay and "
        "early stopping on the held-out tail of the training record, from a physics fit of the "
        "rest of the record (the test records are never seen). Neural state space: no physics — "
        "the CE-EM linear model plus the same MLP in its transition (x⁺ = A x + B u + N(x, u)), "
        "trained and stopped the same way. "
        "N4SID: order of the gray-box model, on centred data, B, D and offsets refitted to the "
        "free-run error (ceemx.baselines.fit_affine_sid); linear (CE-EM): that model refined by "
        "the joint method with a small process noise (close to an output-error fit)."
        f"\n\nTotal wall time {wall:.1f} s."
    )


def json_datasets(results: list[dict]) -> list[dict]:
    """The per-dataset results without the figure's arrays (as ``results.json`` holds them)."""
    return [
        {
            **{k: v for k, v in r.items() if k != "tests"},
            "tests": {
                t: {k: v for k, v in e.items() if not isinstance(v, np.ndarray)}
                for t, e in r["tests"].items()
            },
        }
        for r in results
    ]


def plot(results: list[dict], path) -> None:
    """One panel group per test record (:func:`ceemx.evaluation.plots.plot_benchmark`).

    Measured and simulated outputs over the whole record and a zoomed window, the errors, and
    the hybrid's (else the gray-box's) hidden state with its physical bound.
    """
    from ceemx.evaluation import report
    from ceemx.evaluation.plots import plot_benchmark

    plt = report.plt()
    panels = [(r, t) for r in results for t in r["tests"]]
    fig = plt.figure(figsize=(12, 4.2 * len(panels)), layout="constrained")
    subs = fig.subfigures(len(panels), 1, squeeze=False)[:, 0]
    for (r, test_name), sub in zip(panels, subs, strict=True):
        e = r["tests"][test_name]
        sims = {"gray-box": e["y_sim"]}
        labels = (("hybrid", "hybrid"), ("neural", "neural SS"), ("linear_ceem", "linear CE-EM"))
        for key, label in labels:
            if f"{key}_y_sim" in e:
                sims[label] = e[f"{key}_y_sim"]
        if "linear_y_sim" in e:
            sims["N4SID"] = e["linear_y_sim"]
        model = REGISTRY[r["dataset"]].model
        label, idx = model.hidden
        lower = model.bounds.get("lower")
        x = e.get("hybrid_x_sim", e["x_sim"])
        which = "hybrid" if "hybrid_x_sim" in e else "gray-box"
        plot_benchmark(
            e["y"],
            sims,
            n_init=r["n_init"],
            hidden=x[:, idx],
            hidden_label=f"{label} ({which})",
            bounds=None if lower is None else (lower, None),
            score_unit=r["unit"],
            score_scale=r.get("scale", 1.0),
            title=f"{r['dataset']} / {test_name}: free-run simulation",
            fig=sub,
        )
    report.save_figure(fig, path, dpi=90)  # six record panels: a readable, smaller file
    plt.close(fig)
