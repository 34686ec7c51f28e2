"""Tests for ceemx.evaluation.report: Markdown cells and tables, JSON and text files, figures."""

import json
import math

import jax.numpy as jnp
import numpy as np

from ceemx.evaluation import report
from ceemx.evaluation.metrics import Estimate, mean_se


def test_format_estimate():
    est = mean_se([1.0, 2.0, 3.0, 4.0])
    assert report.format_estimate(est) == "2.500 (0.645)"
    assert report.format_estimate(est, 2.5) == "2.500 (0.645)"
    assert report.format_estimate(est, 10.0) == "**2.500 (0.645)**†"  # not within 2 SE
    assert report.format_estimate(est, 10.0, k=20.0) == "2.500 (0.645)"
    # Numbers reported elsewhere carry their own flag.
    assert report.format_estimate(Estimate(2.676, 0.004, 10), flagged=True) == "**2.676 (0.004)**†"
    assert report.format_estimate(est, 10.0, flagged=False, digits=1) == "2.5 (0.6)"


def test_markdown_and_parameter_table():
    assert report.markdown_table(["a", "b"], [[1, "x"]]) == "| a | b |\n|---|---|\n| 1 | x |\n"
    table = report.parameter_table(
        {"a": {"σ": ([10.0, 10.1, 9.9], 10.0), "ρ": ([27.0, 27.1, 26.9], 28.0)}}, label="setting"
    )
    lines = table.splitlines()
    assert lines[0] == "| setting | σ | ρ |"
    assert "10.000 (0.058)" in lines[2] and "**27.000 (0.058)**†" in lines[2]
    assert "not within 2 standard errors" in table
    assert report.parameter_table({}) == ""


def test_files_and_figure(tmp_path):
    out = report.output_dir(tmp_path / "a" / "b", "unused")
    assert out.is_dir() and report.output_dir(None, tmp_path / "d").is_dir()
    obj = {"x": jnp.arange(3.0), "y": np.float64(math.inf), "z": (np.int64(2), np.bool_(True))}
    saved = json.loads(report.save_json(out / "r.json", obj).read_text())
    assert saved == {"x": [0.0, 1.0, 2.0], "y": "inf", "z": [2, True]}
    assert report.save_text(out / "t.md", "hi\n").read_text() == "hi\n"
    plt = report.plt()
    fig, ax = plt.subplots()
    ax.plot([0, 1])
    path = report.save_figure(fig, out / "f.png")
    assert path.stat().st_size > 0 and not plt.get_fignums()


def test_benchmark_score_prints_a_few_lines_not_its_arrays():
    """repr(score): RMSE / NRMSE / fit % per record and output; trajectories only on request."""
    from ceemx.evaluation.metrics import BenchmarkScore
    from ceemx.lib.results import RESULTS

    rmse = np.array([[0.0123, 2.5], [0.02, 3.0]])
    nrmse = np.array([[0.05, 0.4], [0.1, 0.5]])
    y_sim = np.arange(2 * 5000 * 2, dtype=float).reshape(2, 5000, 2)
    score = BenchmarkScore(
        rmse, nrmse, 100 * (1 - nrmse), np.array([1.8, 2.1]), nrmse.mean(1),
        100 * (1 - nrmse.mean(1)), y_sim, np.zeros((2, 5000, 3)), np.zeros((2, 3)),
        RESULTS.successful, 50,
    )  # fmt: skip
    text = repr(score)
    assert str(score) == text and len(text.splitlines()) <= 9 and "4999" not in text
    lines = text.splitlines()
    assert lines[0].startswith("BenchmarkScore: free-run simulation of 2 records")
    assert "n_init = 50" in lines[0]
    assert lines[1].split() == ["record", "output", "RMSE", "NRMSE", "fit", "%"]
    assert lines[2].split() == ["0", "y1", "0.0123", "0.05", "95.00"]
    assert lines[6].split() == ["0", "all", "1.8", "0.225", "77.50"]  # overall, 2 outputs
    named = score.table(output_names=["left", "right"], unit="mV", format="markdown")
    assert "| record | output | RMSE [mV] | NRMSE | fit % |" in named and "| 1 | right |" in named
    full = score.table(arrays=True)
    assert "y_sim (2, 5000, 2)" in full and "..." in full  # abbreviated by NumPy
