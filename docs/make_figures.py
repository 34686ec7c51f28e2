"""The example figures of docs/figures/: ceemx's plots on real dataset records.

Fits the cascaded tanks' and the Silverbox's gray-box models (as ``ceemx experiment real_data``
does, with its budgets) and N4SID beside them, scores both on the official test records, and draws

- ``benchmark_tanks.png`` — :func:`ceemx.plot_benchmark`: the test output, the gray-box
  simulation (the fit of ``docs/getting_started.md``'s scoring block), the error, and the
  upper-tank level against its physical range [0, h];
- ``benchmark_silverbox.png`` — the same on the Silverbox's 40 000-sample arrow test record
  (decimated for display, the zoom on the largest error);
- ``resid_silverbox.png`` — :func:`ceemx.plot_resid`: the simulation error's autocorrelation and
  its cross-correlation with the input;
- ``diagnostics_tanks.png`` — :meth:`ceemx.FitResult.diagnostics` of the tanks' fit
  (:func:`ceemx.evaluation.plots.plot_residual_diagnostics`).

Data: ``../shared/data``, ``CEEMX_DATA`` or the download (:mod:`ceemx.datasets`). About 2 minutes
on a 2-core CPU. Writes ``figures.json`` beside them: the numbers each figure shows (scores,
the diagnostics' verdicts), which ``tests/test_docs.py`` compares with the numbers the pages
print. Usage: ``PYTHONPATH=src .venv/bin/python docs/make_figures.py [OUT_DIR]`` (default
``docs/figures``).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.baselines import fit_sid  # noqa: E402
from ceemx.evaluation.plots import plot_residual_diagnostics  # noqa: E402
from ceemx.evaluation.report import save_figure  # noqa: E402
from ceemx.systems.gray_box import CascadedTanks, Silverbox  # noqa: E402

DPI = 100  # the figures are 11 in wide: 1100 pixels
NUMBERS: dict[str, dict] = {}  # what each figure shows, written to figures.json


def tanks(out: Path) -> None:
    """The cascaded tanks' benchmark figure and the diagnostics of the fit."""
    ds = ceemx.datasets.cascaded_tanks()
    # The fit of docs/getting_started.md's scoring block: the figure shows what that page prints.
    result = ceemx.fit(CascadedTanks.default(), ds.train, solver=ceemx.JointLM(), max_epochs=200)
    print(result)
    test = ds.tests["test"]
    ours = ceemx.benchmark_score(result.system, test, ds.n_init)
    h = float(result.system.h)
    NUMBERS["benchmark_tanks"] = {"gray-box RMSE [V]": float(ours.rmse[0, 0])}
    fig = ceemx.plot_benchmark(
        test.y[0],
        {"gray-box CE-EM": ours.y_sim[0]},
        n_init=ds.n_init,
        hidden=ours.x_sim[0, :, 0],
        hidden_label="gray-box: upper-tank level x₁ [V]",
        bounds=(0.0, h),
        output_names="lower-tank level",
        unit="V",
        dt=ds.dt,
        zoom_fraction=0.2,
        title="Cascaded tanks, official test record: free-run simulation",
    )
    save_figure(fig, out / "benchmark_tanks.png", dpi=DPI)
    diagnostics = result.diagnostics()
    print(diagnostics)
    plot_residual_diagnostics(diagnostics, out / "diagnostics_tanks.png")
    NUMBERS["diagnostics_tanks"] = {
        "white": [None if w is None else bool(w) for w in diagnostics.white],
        "box_pierce_p": [float(p) for p in diagnostics.box_pierce_p],
        "problems": len(diagnostics.problems),
    }


def silverbox(out: Path) -> None:
    """The Silverbox arrow test's benchmark figure and the simulation error's correlations."""
    ds = ceemx.datasets.silverbox()
    train = ds.train[:, :8192].windows(512, 256)
    guess = Silverbox.default(hold="foh")
    result = ceemx.fit(guess, ceemx.foh_inputs(train), solver=ceemx.JointLM(), max_epochs=200)
    print(result)
    linear = fit_sid(train, state_dim=2)
    test = ds.tests["arrow_full"]
    ours = ceemx.benchmark_score(result.system, ceemx.foh_inputs(test), ds.n_init)
    lin = ceemx.benchmark_score(linear, test, ds.n_init)
    NUMBERS["benchmark_silverbox"] = {
        "gray-box RMSE [mV]": float(ours.rmse[0, 0]) * ds.score_scale,
        "N4SID RMSE [mV]": float(lin.rmse[0, 0]) * ds.score_scale,
    }
    y = np.asarray(test.y[0])
    fig = ceemx.plot_benchmark(
        y,
        {"gray-box CE-EM (Duffing)": ours.y_sim[0], "N4SID (linear, 2 states)": lin.y_sim[0]},
        n_init=ds.n_init,
        hidden=ours.x_sim[0, :, 1],
        hidden_label="gray-box: scaled velocity ẏ/ω [V]",
        output_names="output voltage",
        unit="V",
        score_scale=ds.score_scale,
        score_unit=ds.score_unit,
        zoom_samples=300,
        max_points=1500,  # 750 bins: about one a pixel at 100 dpi, a smaller file
        title="Silverbox, arrow test record (40 000 samples): free-run simulation",
    )
    save_figure(fig, out / "benchmark_silverbox.png", dpi=90)  # < 200 KB
    error = y - np.asarray(ours.y_sim[0])
    error[: ds.n_init] = np.nan  # the initial-state window is not scored
    fig = ceemx.plot_resid(
        error,
        np.asarray(test.u[0]),
        lags=40,
        what="simulation error",
        output_names="output",
        input_names="input",
        title="Silverbox arrow test: gray-box simulation error",
    )
    save_figure(fig, out / "resid_silverbox.png", dpi=DPI)


def main(argv: list[str]) -> None:
    """Draw every figure into ``argv[0]`` (default ``docs/figures``)."""
    out = Path(argv[0] if argv else Path(__file__).parent / "figures")
    out.mkdir(parents=True, exist_ok=True)
    ceemx.enable_compilation_cache()
    for make in (tanks, silverbox):
        t0 = time.perf_counter()
        make(out)
        print(f"{make.__name__}: {time.perf_counter() - t0:.1f} s", flush=True)
    for path in sorted(out.glob("*.png")):
        print(f"{path}: {path.stat().st_size / 1024:.0f} KB")
    # The numbers the figures show, for the docs that quote them (tests/test_docs.py checks them).
    (out / "figures.json").write_text(json.dumps(NUMBERS, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
