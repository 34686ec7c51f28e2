"""The README demo: identify six coupled Lorenz attractors (n = 18, y ∈ R^16) from 4 trajectories.

1. Simulate the true system (paper §4.1: σ = 10, ρ = 28, β = 8/3 per attractor, random coupling H
   and observation matrix C, σ_v = 0.01, no process noise, T = 128, dt = 0.04).
2. Guess θ = [σ_{1:6}, ρ_{1:6}, β_{1:6}, H] within ±10 % of the truth; states from the observations
   (least squares, then one smoothing pass with weak dynamics weights).
3. Identify θ and the states by CE-EM (``fit(..., solver=ceemx.JointLM())``), printing ε(θ)
   (Eq. 14) per iteration; print true vs initial vs learned parameters; save a figure.
"""

from __future__ import annotations

import threading
import time
import warnings
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from ceemx import fit
from ceemx.data.checks import prepare
from ceemx.evaluation import metrics as ev
from ceemx.evaluation import report
from ceemx.experiments import common
from ceemx.identification.analysis.noise_check import NoiseCheckWarning
from ceemx.identification.fitting.start import precompile_fit
from ceemx.models import with_noise
from ceemx.systems import CoupledLorenz
from ceemx.systems.lorenz import coupling_mask

NAME = "demo"


def parameter_rows(true, init, learned) -> list[list[str]]:
    """Per attractor: σ, ρ, β true / initial / learned; then ‖H − H_true‖_F (own blocks ignored)."""
    rows = []
    for k in range(true.K):
        row = [str(k + 1)]
        for p in ("sigma", "rho", "beta"):
            row += [f"{float(getattr(s, p)[k]):.4f}" for s in (true, init, learned)]
        rows.append(row)
    return rows


@dataclass(frozen=True)
class Identified:
    """A demo fit: the result, ε(θ) before and after every iteration, seconds per iteration."""

    result: Any
    eps: list[float]
    epoch_s: list[float]


def identify(true, problem, *, method: str, max_epochs: int, say) -> Identified:
    """Warm-start the states and fit θ = (σ, ρ, β, H) by CE-EM, printing ε(θ) per iteration."""
    # Fit with the observation noise σ_v = 0.01 and a small process noise (the data are
    # deterministic; a zero process noise has no density).
    system = with_noise(problem.init_system, 0.01, 0.01)
    solver = common.make_solver(method, rtol=1e-10)
    # The fit's programs compile on another core while the warm start and ε(θ₀) run; join()
    # compiles here what the other core has not started.
    compiling = precompile_fit(
        system, problem.data, solver=solver, trainable=common.LORENZ_PARAMS_H
    )
    # The start states the fit would compute itself (compiled for how often the solver smooths).
    inputs = prepare(system, problem.data, identify=True)
    x_init = solver.initial_states(inputs.system, inputs.data)

    def show(info, eps):
        say(
            f"  iteration {info.epoch:3d}   ε(θ) = {eps:.6g}   J = {info.record['J']:.10g}",
            flush=True,
        )

    record_eps = ev.DynamicsErrorCallback(true, printer=show)
    eps0 = record_eps.error(system)
    compiling.join()
    say(f"start: ε(θ) = {eps0:.6g}, state RMSE {state_rmse(problem, x_init):.4g}")
    timer = ev.FitTimer().start()
    with warnings.catch_warnings():  # the noise check's finding is shown below, with its reason
        warnings.simplefilter("ignore", NoiseCheckWarning)
        res = fit(
            system,
            problem.data,
            x_init,
            solver=solver,
            trainable=common.LORENZ_PARAMS_H,
            max_epochs=max_epochs,
            callbacks=[record_eps, timer],
            progress=False,
        )
    assert isinstance(res.system, CoupledLorenz)
    if res.noise_check is not None and res.noise_check.message:
        say(
            "noise check (expected here: the simulated data have no process noise, the fit "
            f"assumes σ_w = 0.01): {res.noise_check.message}"
        )
    return Identified(res, [eps0] + [h["eps"] for h in res.history], timer.per_epoch())


def coupling_errors(true, problem, learned) -> dict[str, float]:
    """‖H − H_true‖_F of the initial guess and of the learned system (own blocks ignored)."""
    H_true = _coupling(true)
    return {
        "initial": float(np.linalg.norm(_coupling(problem.init_system) - H_true)),
        "learned": float(np.linalg.norm(_coupling(learned) - H_true)),
    }


def _coupling(system) -> np.ndarray:
    """``system.effective_coupling()`` on the host (no eager program)."""
    return np.asarray(system.H) * np.asarray(coupling_mask(system.K))


def state_rmse(problem, states) -> float:
    """RMS error of the smoothed states against the true ones."""
    return float(np.sqrt(np.mean((np.asarray(states) - np.asarray(problem.states)) ** 2)))


def make_table(true, problem, fitted: Identified, *, method: str) -> str:
    """Markdown: true / initial / learned σ, ρ, β per attractor; H, ε, state error and timings."""
    res, eps = fitted.result, fitted.eps
    H_err = coupling_errors(true, problem, res.system)
    rmse = state_rmse(problem, res.states)
    fit_s = sum(fitted.epoch_s)
    first_s = fitted.epoch_s[0] if res.epochs else 0.0
    header = [
        "k",
        "σ true",
        "σ init",
        "σ learned",
        "ρ true",
        "ρ init",
        "ρ learned",
        "β true",
        "β init",
        "β learned",
    ]
    table = report.markdown_table(header, parameter_rows(true, problem.init_system, res.system))
    table += (
        f"\n‖H − H_true‖_F: initial {H_err['initial']:.4g}, learned {H_err['learned']:.4g} "
        f"(‖H_true‖_F = {float(np.linalg.norm(_coupling(true))):.4g}).\n"
        f"ε(θ): initial {eps[0]:.4g}, learned {eps[-1]:.4g} after {res.epochs} iterations "
        f"({method}); smoothed-state RMSE {rmse:.4g}; fit {fit_s:.1f} s "
        f"(first iteration, with JIT compilation, {first_s:.1f} s).\n"
    )
    return table


def plot(true, problem, fitted: Identified, path) -> None:
    """ε(θ) per iteration (log scale) and attractor 1 of trajectory 1, true against smoothed."""
    plt = report.plt()
    eps, states = fitted.eps, fitted.result.states
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    axes[0].semilogy(np.arange(len(eps)), eps, "o-")
    axes[0].set_xlabel("iteration")
    axes[0].set_ylabel("ε(θ)")
    axes[0].set_title("error in the estimated dynamics")
    axes[0].grid(True, which="both", alpha=0.3)
    t = np.arange(problem.states.shape[1]) * true.dt
    for j, c in zip(range(3), ("tab:blue", "tab:orange", "tab:green"), strict=False):
        axes[1].plot(
            t,
            np.asarray(problem.states[0, :, j]),
            color=c,
            lw=2.5,
            alpha=0.35,
            label=f"x{j + 1},1 true",
        )
        axes[1].plot(
            t, np.asarray(states[0, :, j]), color=c, lw=1, ls="--", label=f"x{j + 1},1 smoothed"
        )
    axes[1].set_xlabel("time [s]")
    axes[1].set_title("attractor 1, trajectory 1: true vs smoothed")
    axes[1].legend(fontsize=7, ncol=3)
    report.save_figure(fig, path)


def _parameters(system) -> dict[str, np.ndarray]:
    """σ, ρ, β of a system as NumPy arrays."""
    return {p: np.asarray(getattr(system, p)) for p in ("sigma", "rho", "beta")}


def run(
    *,
    smoke: bool = False,
    out=None,
    method: str | None = None,
    max_epochs: int | None = None,
    seed: int = 0,
    B: int | None = None,
    verbose: bool = True,
) -> dict:
    """Run the demo; writes ``results.json``, ``table.md`` and ``demo.png`` to ``out``.

    Args:
        smoke: tiny version for the tests (2 attractors, B = 2, T = 32, 3 iterations).
        out: output folder (default ``./ceemx-demo``).
        method: ``"joint"`` (default) or ``"alternate"``.
        max_epochs: bound on iterations (default 30; smoke 3).
        seed: seed of the data and of the initial guess.
        B: number of trajectories (default 4; smoke 2).
        verbose: print progress and the tables.

    Returns:
        A summary dict (ε per iteration, parameters, timings).

    """
    common.enable_x64()
    method = "joint" if method is None else method
    K, T = (2, 32) if smoke else (6, 128)
    B = (2 if smoke else 4) if B is None else B
    max_epochs = (3 if smoke else 30) if max_epochs is None else max_epochs
    outdir = report.output_dir(out, "ceemx-demo")
    say = print if verbose else (lambda *a, **k: None)
    t_start = time.perf_counter()
    # matplotlib loads (≈ 1 s) on the core the data simulation leaves idle.
    plotting = threading.Thread(target=report.plt, name="ceemx-demo-pyplot", daemon=True)
    plotting.start()

    true = common.true_lorenz(K, key=jax.random.PRNGKey(4), obs_noise=0.01)
    problem = common.lorenz_problem(seed, true, B=B, T=T, sigma_w=0.0, sigma_v=0.01, coupling=True)
    say(
        f"{K} coupled Lorenz attractors: n = {true.state_dim}, m = {true.obs_dim}, B = {B}, "
        f"T = {T}, "
        f"{3 * K + (3 * K) ** 2} parameters (σ, ρ, β per attractor and H)"
    )
    fitted = identify(true, problem, method=method, max_epochs=max_epochs, say=say)
    res = fitted.result
    table = make_table(true, problem, fitted, method=method)
    say(table)
    plotting.join()
    plot(true, problem, fitted, outdir / "demo.png")

    summary = {
        "experiment": NAME,
        "method": method,
        "K": K,
        "B": B,
        "T": T,
        "seed": seed,
        "eps": fitted.eps,
        "epochs": res.epochs,
        "converged": bool(res.converged),
        "monotone": ev.is_monotone(res.initial_J, res.history),
        "H_error": coupling_errors(true, problem, res.system),
        "state_rmse": state_rmse(problem, res.states),
        "true": _parameters(true),
        "initial": _parameters(problem.init_system),
        "learned": _parameters(res.system),
        "epoch_s": fitted.epoch_s,
        "wall_s": time.perf_counter() - t_start,
        "table": table,
    }
    report.save_json(outdir / "results.json", summary)
    report.save_text(outdir / "table.md", table)
    say(
        f"wrote {outdir / 'demo.png'}, {outdir / 'table.md'}, {outdir / 'results.json'} "
        f"({summary['wall_s']:.1f} s in all)"
    )
    return summary
