"""Tests for ceemx.evaluation.report: Markdown cells and tables, JSON and text files, figures."""

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

from ceemx.evaluation import plots, report
from ceemx.evaluation.estimates import Estimate, mean_se


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
    before = plt.get_fignums()  # figures an earlier test of this worker left open
    fig, ax = plt.subplots()
    ax.plot([0, 1])
    path = report.save_figure(fig, out / "f.png")
    assert path.stat().st_size > 0 and plt.get_fignums() == before  # saved and closed


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


# --------------------------------------------------------------------------------------------
# Figures (ceemx.evaluation.plots): tiny arrays, Agg
# --------------------------------------------------------------------------------------------


def _texts(fig):
    out = []
    for ax in fig.axes:
        out += [ax.get_title(loc) for loc in ("left", "center", "right")]
        leg = ax.get_legend()
        if leg is not None:
            out += [t.get_text() for t in leg.get_texts()]
    return " | ".join(out)


def test_plot_benchmark_panels_zoom_error_and_bounds(tmp_path):
    import ceemx

    assert ceemx.plot_benchmark is plots.plot_benchmark and ceemx.plot_resid is plots.plot_resid
    T, n_init = 400, 20
    t = np.arange(T)
    y = np.sin(t / 8.0)
    good = y + 0.01 * np.cos(t)
    good[300] += 0.5  # the largest error: the default zoom is centred on it
    bad = 1e3 * y  # a diverging model must not squash the measured output
    level = np.cos(t / 8.0)  # leaves its range [-0.5, 2] on a third of the samples
    fig = plots.plot_benchmark(
        y[:, None], {"gray-box": good, "N4SID": bad[None, :, None]}, n_init=n_init,
        hidden=level, hidden_label="level [V]", bounds=(-0.5, 2.0), unit="V",
        score_scale=1000, score_unit="mV", title="tiny",
    )  # fmt: skip
    assert len(fig.axes) == 6  # (output, error, hidden) × (whole record, zoom)
    text = _texts(fig)
    rmse = np.sqrt(np.mean((good - y)[n_init:] ** 2)) * 1000
    assert f"gray-box (RMSE {rmse:.3g} mV)" in text and "N4SID (RMSE" in text
    assert f"initial-state window (n_init = {n_init})" in text
    assert (
        "level [V] — physical range [-0.5, 2]" in text
        and "outside on 34 % of samples (reaches -1)" in text
    )
    full, zoom = fig.axes[0], fig.axes[1]
    assert full.get_ylim()[1] < 2 and full.get_xlim() == (0, T - 1)
    a, b = zoom.get_xlim()
    assert a < 300 < b and b - a == 19  # 5 % of 400 samples, at least 20
    assert fig.axes[2].get_ylim()[1] < 1.0  # the error axis follows the best model
    path = report.save_figure(fig, tmp_path / "b.png", dpi=30)  # layout and render, cheaply
    assert path.stat().st_size > 0
    fig = plots.plot_benchmark(y, good, n_init=0, zoom=False, dt=0.5)
    assert len(fig.axes) == 2 and fig.axes[-1].get_xlabel() == "time [s]"
    fig = plots.plot_benchmark(y, good, zoom=(10, 50))
    assert fig.axes[1].get_xlim() == (10, 49)
    report.plt().close("all")


def test_plot_benchmark_reads_names_units_and_sample_time_from_the_record():
    import ceemx

    t = np.arange(200)
    y = np.sin(t / 8.0)[None, :, None]
    record = ceemx.Trajectories.from_arrays(
        [y[0]], dt=0.25, output_names=("level",), output_units=("V",)
    )
    fig = plots.plot_benchmark(record, {"model": 0.9 * y}, n_init=10, zoom=False)
    assert fig.axes[0].get_ylabel() == "level [V]" and fig.axes[-1].get_xlabel() == "time [s]"
    assert "RMSE" in _texts(fig) and "V)" in _texts(fig)
    fig = plots.plot_benchmark(record, 0.9 * y, output_names="h", unit="mV", zoom=False)
    assert fig.axes[0].get_ylabel() == "h [mV]"  # the call's names and unit win
    two = ceemx.Trajectories.from_arrays([y[0], y[0]])
    with pytest.raises(ValueError, match="`y`: one record"):
        plots.plot_benchmark(two, 0.9 * y)
    report.plt().close("all")


def test_plot_benchmark_decimates_long_records_for_display_only():
    rng = np.random.default_rng(0)
    T = 20_000
    y = rng.normal(size=T)
    fig = plots.plot_benchmark(y, 0.9 * y, max_points=1000)
    full, zoom = fig.axes[0], fig.axes[1]
    assert not full.get_lines()  # bands between each of 500 bins' min and max, not 20 000 points
    measured = full.collections[-2].get_paths()[0].vertices  # drawn before the simulation
    assert len(measured) <= 2100
    assert measured[:, 1].max() == y.max() and measured[:, 1].min() == y.min()  # exact envelope
    a, b = zoom.get_xlim()
    assert len(zoom.get_lines()[0].get_ydata()) == b - a + 1 == 600  # every sample; at most 600
    report.plt().close("all")


def test_plot_benchmark_outputs_subfigures_and_errors():
    import pytest

    y = np.stack([np.sin(np.arange(100) / 5), np.cos(np.arange(100) / 5)], -1)
    fig = report.plt().figure(figsize=(11, 8), layout="constrained")
    subs = fig.subfigures(2, 1)
    for sub in subs:
        plots.plot_benchmark(y, {"a": y + 0.1, "b": y - 0.1}, n_init=5,
                             output_names=["left", "right"], fig=sub)  # fmt: skip
    assert len(fig.axes) == 16  # 2 records × 2 outputs × (output, error) × (whole, zoom)
    assert "left" in fig.axes[0].get_ylabel() and "right" in fig.axes[4].get_ylabel()
    with pytest.raises(ValueError, match="shape"):
        plots.plot_benchmark(y, y[:, :1])
    with pytest.raises(ValueError, match="zoom"):
        plots.plot_benchmark(y, y, zoom=(50, 10))
    with pytest.raises(ValueError, match="one record"):
        plots.plot_benchmark(np.zeros((2, 10, 1)), np.zeros((2, 10, 1)))
    with pytest.raises(ValueError, match="bounds"):
        plots.plot_benchmark(y, y, hidden=y, bounds=[(0, 1)])
    report.plt().close("all")


def test_residual_correlations_and_plot_resid_draw_the_99_percent_band():
    from matplotlib.collections import PolyCollection

    from ceemx.evaluation import plots
    from ceemx.identification.analysis.correlations import BAND_Z, residual_correlations

    rng = np.random.default_rng(1)
    u = rng.normal(size=500)
    e = np.convolve(u, [0.0, 0.0, 1.0])[:500] + 0.5 * rng.normal(size=500)  # u acts at lag 2
    c = residual_correlations(e, u, lags=10)
    d = e - e.mean()
    k = 3
    r3 = np.sum(d[k:] * d[:-k]) / (500 - k) / np.mean(d**2)
    np.testing.assert_allclose(c.autocorrelation[0, k], r3)
    assert c.cross_correlation.shape == (1, 1, 21)
    assert np.argmax(c.cross_correlation[0, 0]) == 10 + 2  # lag k = 2: input before error
    np.testing.assert_allclose(c.band()[0, 1], BAND_Z / np.sqrt(499))
    fig = plots.plot_resid(e, u, lags=10, input_names="pump")
    assert len(fig.axes) == 2
    for ax in fig.axes:  # the band is drawn on every panel
        assert any(isinstance(a, PolyCollection) for a in ax.collections)
    assert "pump and residuals" in _texts(fig)
    from matplotlib.collections import LineCollection

    stems = [c for c in fig.axes[1].collections if isinstance(c, LineCollection)]
    red = [c for c in stems if c.get_color()[0][0] > 0.8]
    assert red and "inside" in _texts(fig)  # input-correlated lags drawn red
    fig = plots.plot_resid(rng.normal(size=(3, 200, 2)), lags=5)  # batch, 2 outputs, no input
    assert len(fig.axes) == 2
    report.plt().close("all")


def test_plot_benchmark_open_bounds():
    """A hidden state with bounds open on both sides draws no bound (used to raise)."""
    import numpy as np

    from ceemx.evaluation.plots import plot_benchmark

    t = np.linspace(0, 6, 200)
    fig = plot_benchmark(np.sin(t), np.sin(t) + 0.01, n_init=10, hidden=np.cos(t),
                         hidden_label="velocity", bounds=(None, None))  # fmt: skip
    assert fig is not None
    report.plt().close(fig)
