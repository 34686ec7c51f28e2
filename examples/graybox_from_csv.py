"""Identify your own gray-box model from a CSV file: the Silverbox electronic Duffing oscillator.

The page to copy when you have measurements in a file and a physical model with a hidden state:

1. write the model as a subclass of ``ceemx.AbstractContinuousSystem`` with physical parameters
   declared ``ceemx.param(positive=True)`` (learned in unconstrained coordinates, reported in
   natural units);
2. read the CSV with NumPy and wrap it in ``ceemx.Trajectories``;
3. fit on windows of a training segment with ``ceemx.fit``;
4. score the free-run simulation by the official benchmark protocol with
   ``ceemx.benchmark_score`` and plot it.

The Silverbox (Wigren & Schoukens 2013) is an electronic circuit that mimics a mass–spring–damper
with a cubic spring,

    m ÿ + d ẏ + k1 y + k3 y³ = u − u0,

with u the input voltage and y the output voltage (the "position"); the "velocity" ẏ is not
measured. Sampling rate fs = 610.35 Hz.

Run (from the repository root)::

    python examples/graybox_from_csv.py          # data from $CEEMX_DATA or ../shared/data
    python examples/graybox_from_csv.py --data /path/to/SNLS80mV.csv --out results/silverbox
    python examples/graybox_from_csv.py --smoke  # a short run (< 40 s), used by the tests

``--data`` takes the CSV file itself or a folder holding ``silverbox/SNLS80mV.csv``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)  # identify in float64 (before any array is created)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jaxtyping import Array  # noqa: E402

import ceemx  # noqa: E402

ceemx.enable_compilation_cache()  # compiled programs persist across runs (seconds saved)

FS = 610.35  # sampling frequency [Hz]
ESTIMATION = (40650, 105712)  # the official estimation range (samples)
TEST = (105712, 127400)  # the official multisine test record (samples)
N_INIT = 50  # test outputs a model may use to set its initial state (official protocol)
PUBLISHED_MV = 2.0  # published deep-encoder free-run RMSE on the multisine test [mV]


# ----------------------------------------------------------------------------------------------
# 1. The model.
# ----------------------------------------------------------------------------------------------
class Silverbox(ceemx.AbstractContinuousSystem):
    """m ÿ + d ẏ + k1 y + k3 y³ = u − u0, measured y, hidden velocity.

    Time is measured in **samples** (τ = t·fs), so the system's ``dt`` is 1 and every parameter
    is of order one: the state is x = (y, dy/dτ) = (y, ẏ / fs), and the parameters are
    m_s = m·fs², d_s = d·fs, k1, k3 and the input offset u0 (unconstrained: either sign).
    :meth:`physical` converts them back to seconds.
    """

    m: Array = ceemx.param(positive=True)  # "mass"     m·fs²
    d: Array = ceemx.param(positive=True)  # damping    d·fs
    k1: Array = ceemx.param(positive=True)  # linear stiffness
    k3: Array = ceemx.param(positive=True)  # cubic (hardening) stiffness
    u0: Array = ceemx.param()  # input offset [V]: a DC part of u that does not drive the circuit

    @property
    def state_dim(self) -> int:
        """Two states: y and its rate of change per sample."""
        return 2

    @property
    def obs_dim(self) -> int:
        """One output: the voltage y."""
        return 1

    @property
    def control_dim(self) -> int:
        """One input, the voltage u (``hold="foh"`` makes ``input_dim`` 2: [u_t, u_{t+1}])."""
        return 1

    def vector_field(self, x, u, t):
        """D/dτ (y, v) = (v, (u − u0 − d v − k1 y − k3 y³) / m), τ in samples."""
        y, v = x[0], x[1]
        return jnp.stack([v, (u[0] - self.u0 - self.d * v - self.k1 * y - self.k3 * y**3) / self.m])

    def observe(self, x, u, t):
        """The measured output: y."""
        return x[:1]

    def physical(self) -> dict[str, float]:
        """The parameters in seconds: m [V·s²/V], d [V·s/V], k1 [-], k3 [1/V²]."""
        return {
            "m": float(self.m) / FS**2,
            "d": float(self.d) / FS,
            "k1": float(self.k1),
            "k3": float(self.k3),
            "u0 [mV]": 1000 * float(self.u0),
            "f0 [Hz]": math.sqrt(float(self.k1) / float(self.m)) * FS / (2 * math.pi),
        }


# ----------------------------------------------------------------------------------------------
# 2. The data.
# ----------------------------------------------------------------------------------------------
def find_csv(arg: str | None) -> Path:
    """The CSV: ``--data`` (a file or a folder), else ``$CEEMX_DATA``, else ``../shared/data``."""
    repo = Path(__file__).resolve().parents[1]
    if arg:
        candidates = [Path(arg)]
    elif os.environ.get("CEEMX_DATA"):
        candidates = [Path(os.environ["CEEMX_DATA"])]
    else:
        candidates = [repo / ".." / "shared" / "data", Path.cwd() / ".." / "shared" / "data"]
    tried = []
    for c in candidates:
        path = c if c.suffix == ".csv" else c / "silverbox" / "SNLS80mV.csv"
        if path.is_file():
            return path.resolve()
        tried.append(str(path))
    sys.exit(
        "Silverbox data not found; tried " + ", ".join(tried) + ".\n"
        "Get SNLS80mV.csv (https://www.nonlinearbenchmark.org, 'Silverbox') and pass its path "
        "with --data, or set CEEMX_DATA to a folder holding silverbox/SNLS80mV.csv."
    )


def read_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read the input u (column V1) and the output y (column V2) from the file.

    The file has a header line ``"V1","V2",`` and a trailing comma on every line (an empty third
    column): read the first two columns only. ``np.loadtxt`` would do as well; with the csv
    module: ``rows = list(csv.reader(f))[1:]; u = [float(r[0]) for r in rows]``.
    """
    table = np.genfromtxt(path, delimiter=",", skip_header=1, usecols=(0, 1), dtype=np.float64)
    return table[:, 0], table[:, 1]


def initial_guess(y: np.ndarray, u: np.ndarray) -> dict[str, float]:
    """m, d, k1, k3, u0 (sample units) by least squares on finite differences of y.

    u ≈ m ÿ + d ẏ + k1 y + k3 y³ + u0 with ÿ, ẏ central differences — biased by the noise and the
    discretisation, but a start of the right size; CE-EM then fits the model itself.
    """
    ydd = y[2:] - 2 * y[1:-1] + y[:-2]
    yd = (y[2:] - y[:-2]) / 2
    y0 = y[1:-1]
    A = np.stack([ydd, yd, y0, y0**3, np.ones_like(y0)], axis=1)
    coef = np.linalg.lstsq(A, u[1:-1], rcond=None)[0]
    coef[:4] = np.maximum(coef[:4], 1e-3)  # m, d, k1, k3 must be positive
    return dict(zip(("m", "d", "k1", "k3", "u0"), (float(c) for c in coef), strict=True))


# ----------------------------------------------------------------------------------------------
# 3.–5. Fit, score, plot.
# ----------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> dict:
    """Fit and score the model; return the RMSE [mV], fit %, parameters and fit time."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--data", help="SNLS80mV.csv, or a folder holding silverbox/SNLS80mV.csv")
    parser.add_argument("--out", default="results/example_graybox", help="output folder")
    parser.add_argument("--smoke", action="store_true", help="a short run (tests)")
    args = parser.parse_args(argv)

    # Sizes: training samples, window length and step, epochs, scored test samples.
    if args.smoke:
        n_train, length, step, epochs, n_test = 1024, 256, 128, 4, 2000
    else:
        n_train, length, step, epochs, n_test = 4096, 512, 256, 30, TEST[1] - TEST[0]

    path = find_csv(args.data)
    u, y = read_csv(path)
    print(f"data: {path} ({len(y)} samples, fs = {FS} Hz)")

    # Training segment from the start of the estimation range, with a first-order-hold input
    # (the model integrates u linearly between samples: input pairs [u_t, u_{t+1}]). Build the
    # pairs on the whole segment, then cut it into overlapping windows.
    seg = slice(ESTIMATION[0], ESTIMATION[0] + n_train)
    train = ceemx.data.trajectories.foh_inputs(ceemx.Trajectories.from_arrays(y[seg], u[seg]))
    assert isinstance(train, ceemx.Trajectories)
    windows = train.windows(length, step)
    n_windows = windows.y.shape[0]
    print(f"training: samples [{seg.start}, {seg.stop}) as {n_windows} windows of {length}")

    # The model at a least-squares start; noise scales in volts (per sample for the process).
    guess = initial_guess(y[seg], u[seg])
    model = Silverbox(
        *(jnp.asarray(guess[name]) for name in ("m", "d", "k1", "k3", "u0")),
        dt=1.0,
        hold="foh",
        substeps=2,
        process_noise=jnp.array([1e-4, 1e-4]),
        obs_noise=1e-3,
    )

    t0 = time.perf_counter()
    result = ceemx.fit(model, windows, solver=ceemx.JointLM(), max_epochs=epochs)
    fit_s = time.perf_counter() - t0
    fitted = result.system
    assert isinstance(fitted, Silverbox)
    print(
        f"fit: {len(result.history)} iterations, converged = {bool(result.converged)}, "
        f"{fit_s:.1f} s (JIT compilation included)"
    )
    print(f"{'parameter':<10}{'start':>14}{'fitted':>14}")
    start_phys, fitted_phys = model.physical(), fitted.physical()
    for name in start_phys:
        print(f"{name:<10}{start_phys[name]:>14.6g}{fitted_phys[name]:>14.6g}")

    # Official protocol: x̂₁ from the first 50 test outputs, free run over the whole test input,
    # RMSE on y[50:] in mV.
    test_slice = slice(TEST[0], TEST[0] + n_test)
    test = ceemx.data.trajectories.foh_inputs(
        ceemx.Trajectories.from_arrays(y[test_slice], u[test_slice])
    )
    assert isinstance(test, ceemx.Trajectories)
    t0 = time.perf_counter()
    score = ceemx.benchmark_score(fitted, test, N_INIT, scale=1000.0)
    score_s = time.perf_counter() - t0
    rmse = float(score.rmse_overall[0])
    fit_pct = float(score.fit_percent_overall[0])
    label = "multisine test" + (" (smoke: first samples only)" if args.smoke else "")
    print(f"{label}: RMSE = {rmse:.3f} mV, fit = {fit_pct:.2f} %, scored in {score_s:.1f} s")
    print(f"published deep-encoder RMSE on the same test: ≈ {PUBLISHED_MV} mV")

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    png = out / "silverbox_graybox.png"
    plot(np.asarray(test.y)[0, :, 0], score, png)
    print(f"figure: {png}")
    return {"rmse_mV": rmse, "fit_percent": fit_pct, "parameters": fitted_phys, "fit_s": fit_s}


def plot(y_test: np.ndarray, score, png: Path) -> None:
    """Measured vs simulated test output, the error, and the simulated hidden velocity."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    y_sim = np.asarray(score.y_sim)[0, :, 0]
    velocity = np.asarray(score.x_sim)[0, :, 1] * FS  # dy/dτ · fs = ẏ [V/s]
    t = np.arange(len(y_test)) / FS
    show = slice(0, min(len(t), 600))  # one second, readable
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=False)
    axes[0].plot(t[show], 1000 * y_test[show], label="measured", lw=1)
    axes[0].plot(t[show], 1000 * y_sim[show], "--", label="free-run simulation", lw=1)
    axes[0].axvline(N_INIT / FS, color="gray", lw=0.5)
    axes[0].set_ylabel("y [mV]")
    axes[0].legend(loc="upper right")
    axes[1].plot(t, 1000 * (y_sim - y_test), lw=0.5, color="C3")
    axes[1].set_ylabel("error [mV]")
    axes[2].plot(t[show], velocity[show], lw=1, color="C2")
    axes[2].set_ylabel("estimated ẏ [V/s] (hidden)")
    axes[2].set_xlabel("time in the test record [s]")
    fig.suptitle(f"Silverbox gray-box model, RMSE {float(score.rmse_overall[0]):.2f} mV")
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
