"""Beyond certainty equivalence: learned noise and calibrated uncertainty by Laplace EM.

Setting: the paper's Figure 2 (§4.1.2) — one Lorenz attractor observed through a known
C ∈ R^{2×3}, σ_w = 0.1, σ_v = 0.5, B = 4 trajectories of T = 128 steps, the initial guess
θ·(1 + U(−0.1, 0.1)) of (σ, ρ, β); seeds 43, 44, … as the Figure-2 experiment.

Per seed, two fits:

- **Laplace EM** (:class:`ceemx.LaplaceEM`) learning (σ, ρ, β) *and* both noise scales, started
  from wrong noise scales (σ_w = 0.3, σ_v = 1.0); standard errors from the observed information of
  the Laplace log-evidence (:func:`ceemx.identification.analysis.uncertainty.evidence_covariance`).
- **CE-EM, joint** (:class:`ceemx.JointLM`) with the true noise scales given (CE-EM cannot learn
  them); standard errors from the Schur complement of the joint Gauss–Newton matrix
  (:func:`ceemx.identification.analysis.uncertainty.parameter_covariance`).

Reported: the noise recovery of the first ``noise_seeds`` seeds (σ_w, σ_v within 10 % of the
truth; σ, ρ, β within 2 SE), and over all seeds the coverage of the nominal 95 % intervals
estimate ± 1.96 SE for σ, ρ, β (and the noise scales), with the z-scores' spread.
"""

from __future__ import annotations

import time
import warnings

import jax
import numpy as np

from ceemx import JointLM, LaplaceEM, fit
from ceemx.evaluation import metrics as ev
from ceemx.evaluation import report
from ceemx.experiments import common
from ceemx.models import with_noise

NAME = "laplace"
SIGMA_W, SIGMA_V = 0.1, 0.5
START_W, START_V = 0.3, 1.0
FIRST_SEED = 43
PARAMS = ("sigma", "rho", "beta")
NOISE = ("sigma_w", "sigma_v")
SYMBOL = {"sigma": "σ", "rho": "ρ", "beta": "β", "sigma_w": "σ_w", "sigma_v": "σ_v"}
TRUTH = {
    **dict(zip(PARAMS, common.TRUE_PARAMS, strict=True)),
    "sigma_w": SIGMA_W,
    "sigma_v": SIGMA_V,
}
NOMINAL = 1.959963984540054  # the 97.5 % normal quantile


def _estimates(res, noise: bool) -> tuple[dict, dict]:
    with warnings.catch_warnings():  # a NaN covariance is recorded as NaN
        warnings.simplefilter("ignore")
        named = res.parameter_estimates()
    est = {p: named[f".{p}[0]"][0] for p in PARAMS}
    se = {p: named[f".{p}[0]"][1] for p in PARAMS}
    if noise:
        for key, field in (("sigma_w", "process_noise"), ("sigma_v", "obs_noise")):
            est[key], se[key] = named[f".{field}.scale"]
    return est, se


def run_one(true, seed: int, *, B: int, T: int, max_epochs: int) -> dict:
    """Laplace EM (noise learned) and joint CE-EM (noise given) on one seed; JSON-able."""
    problem = common.lorenz_problem(
        seed, true, B=B, T=T, sigma_w=SIGMA_W, sigma_v=SIGMA_V, coupling=False
    )
    out: dict = {"seed": seed}
    start = with_noise(problem.init_system, START_W, START_V)
    t0 = time.perf_counter()
    res = fit(
        start,
        problem.data,
        solver=LaplaceEM(),
        trainable=lambda s: (s.sigma, s.rho, s.beta, s.process_noise, s.obs_noise),
        max_epochs=max_epochs,
        progress=False,
    )
    fit_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    est, se = _estimates(res, noise=True)
    out["laplace"] = {
        "estimate": est,
        "se": se,
        "epochs": res.epochs,
        "converged": bool(res.converged),
        "log_evidence": res.history[-1]["log_evidence"] if res.history else None,
        "fit_s": fit_s,
        "se_s": time.perf_counter() - t0,
    }
    known = with_noise(problem.init_system, SIGMA_W, SIGMA_V)
    t0 = time.perf_counter()
    res = fit(
        known,
        problem.data,
        solver=JointLM(),
        trainable=common.LORENZ_PARAMS,
        max_epochs=max_epochs,
        progress=False,
    )
    fit_s = time.perf_counter() - t0
    est, se = _estimates(res, noise=False)
    out["ce-joint"] = {
        "estimate": est,
        "se": se,
        "epochs": res.epochs,
        "converged": bool(res.converged),
        "fit_s": fit_s,
    }
    return out


def z_scores(runs, method: str, name: str) -> np.ndarray:
    """(estimate − truth) / SE per seed (NaN where the SE is not finite)."""
    z = [
        (r[method]["estimate"][name] - TRUTH[name]) / r[method]["se"][name]
        for r in runs
        if name in r[method]["se"]
    ]
    return np.asarray(z, float)


def noise_table(runs) -> str:
    """The noise recovery of each seed (Laplace EM): estimates ± SE and the 10 % / 2-SE checks."""
    rows = []
    for r in runs:
        lap = r["laplace"]
        cells = [r["seed"]]
        for name in (*NOISE, *PARAMS):
            e, s = lap["estimate"][name], lap["se"][name]
            cells.append(f"{e:.4g} ± {s:.2g}")
        w_ok = all(abs(lap["estimate"][n] / TRUTH[n] - 1) <= 0.1 for n in NOISE)
        p_ok = all(abs(lap["estimate"][p] - TRUTH[p]) <= 2 * lap["se"][p] for p in PARAMS)
        cells += ["yes" if w_ok else "no", "yes" if p_ok else "no", lap["epochs"]]
        cells.append(f"{lap['fit_s']:.1f}")
        rows.append(cells)
    header = ["seed", *(f"{SYMBOL[n]}" for n in (*NOISE, *PARAMS))]
    header += ["σ_w, σ_v within 10 %", "σ, ρ, β within 2 SE", "epochs", "fit s"]
    n_w = sum(r[-4] == "yes" for r in rows)
    n_p = sum(r[-3] == "yes" for r in rows)
    return (
        report.markdown_table(header, rows)
        + f"\nσ_w and σ_v within 10 % of the truth: {n_w}/{len(rows)} seeds; σ, ρ, β within "
        f"2 SE: {n_p}/{len(rows)} seeds.\n"
    )


def coverage_table(runs) -> str:
    """Coverage of the nominal 95 % intervals per method and parameter, with the z spread."""
    rows = []
    for method, names in (("laplace", (*PARAMS, *NOISE)), ("ce-joint", PARAMS)):
        for name in names:
            z = z_scores(runs, method, name)
            ok = np.isfinite(z)
            cover = int(np.sum(np.abs(z[ok]) <= NOMINAL))
            k = int(ok.sum())
            rows.append(
                [
                    method,
                    SYMBOL[name],
                    f"{cover}/{k}",
                    f"{100 * cover / max(k, 1):.1f} %",
                    f"{np.mean(z[ok]):+.2f}",
                    f"{np.std(z[ok]):.2f}",
                    f"{ev.mean_se([r[method]['estimate'][name] for r in runs]).mean:.4g}",
                ]
            )
    header = ["method", "parameter", "covered", "coverage", "mean z", "sd z", "mean estimate"]
    return report.markdown_table(header, rows)


def plot(runs, path) -> None:
    """Histograms of z = (estimate − truth)/SE per parameter and method, N(0, 1) beside."""
    plt = report.plt()
    names = (*PARAMS, *NOISE)
    fig, axes = plt.subplots(1, len(names), figsize=(15, 3.2))
    grid = np.linspace(-4, 4, 200)
    for ax, name in zip(axes, names, strict=True):
        for method, colour in (("laplace", "tab:blue"), ("ce-joint", "tab:orange")):
            z = z_scores(runs, method, name)
            z = z[np.isfinite(z)]
            if z.size:
                ax.hist(
                    z, bins=15, range=(-4, 4), density=True, alpha=0.45, color=colour, label=method
                )
        ax.plot(grid, np.exp(-0.5 * grid**2) / np.sqrt(2 * np.pi), "k", lw=1)
        ax.axvline(-NOMINAL, color="k", ls=":", lw=0.8)
        ax.axvline(NOMINAL, color="k", ls=":", lw=0.8)
        ax.set_title(f"z of {SYMBOL[name]}")
    axes[0].legend(fontsize=8)
    fig.suptitle("(estimate − truth) / SE over seeds; N(0, 1) and the 95 % band")
    report.save_figure(fig, path)


def run(
    *,
    smoke: bool = False,
    seeds=None,
    out=None,
    method: str | None = None,
    max_epochs: int | None = None,
    noise_seeds: int = 10,
    verbose: bool = True,
) -> dict:
    """Run the study and write ``results.json``, ``table.md`` and ``laplace.png``.

    Args:
        smoke: a tiny run (2 seeds, T = 32, 5 epochs) for the tests.
        seeds: N (the first N of 43, 44, …; default 100) or a list / ``--seeds`` string.
        out: output folder (default ``./results/laplace``).
        method: unused (both methods run); accepted for the command line's uniformity.
        max_epochs: epoch bound per fit (default 300; smoke 5).
        noise_seeds: how many of the first seeds the noise-recovery table lists (default 10).
        verbose: print progress and the tables.
    """
    del method
    common.enable_x64()
    seeds = common.seed_list(seeds, first=FIRST_SEED, default=2 if smoke else 100)
    B, T = (2, 32) if smoke else (4, 128)
    max_epochs = (5 if smoke else 300) if max_epochs is None else max_epochs
    outdir = report.output_dir(out, "results/laplace")
    true = common.true_lorenz(
        1, key=jax.random.PRNGKey(4), m=2, process_noise=SIGMA_W, obs_noise=SIGMA_V
    )
    t0 = time.perf_counter()
    runs = []
    for seed in seeds:
        r = run_one(true, seed, B=B, T=T, max_epochs=max_epochs)
        runs.append(r)
        if verbose:
            lap = r["laplace"]
            txt = ", ".join(
                f"{SYMBOL[n]} = {lap['estimate'][n]:.4g} ± {lap['se'][n]:.2g}"
                for n in (*NOISE, *PARAMS)
            )
            print(
                f"[seed {seed}] laplace {lap['epochs']} epochs {lap['fit_s']:.1f} s: {txt}",
                flush=True,
            )
    total = time.perf_counter() - t0
    head = (
        f"## Laplace EM — single Lorenz, σ_w = {SIGMA_W}, σ_v = {SIGMA_V}, B = {B}, T = {T}; "
        f"noise learned from σ_w = {START_W}, σ_v = {START_V}; {len(seeds)} seeds; total wall "
        f"time {total:.1f} s\n"
    )
    table = (
        head
        + f"\n### Learned noise, first {min(noise_seeds, len(runs))} seeds (Laplace EM)\n\n"
        + noise_table(runs[:noise_seeds])
        + f"\n### Coverage of the nominal 95 % intervals over {len(runs)} seeds\n\n"
        + coverage_table(runs)
        + "\nlaplace: Laplace EM, noise learned, SE from the observed information of the Laplace "
        "log-evidence; ce-joint: CE-EM (joint LM) with the true noise given, SE from the "
        "joint-posterior Schur complement. z = (estimate − truth)/SE; a calibrated SE gives "
        "sd z ≈ 1 and 95 % coverage.\n"
    )
    summary = {
        "experiment": NAME,
        "seeds": seeds,
        "B": B,
        "T": T,
        "truth": TRUTH,
        "start_noise": {"sigma_w": START_W, "sigma_v": START_V},
        "max_epochs": max_epochs,
        "runs": runs,
        "wall_s": total,
        "table": table,
    }
    report.save_json(outdir / "results.json", summary)
    report.save_text(outdir / "table.md", table)
    plot(runs, outdir / "laplace.png")
    if verbose:
        print(table)
    return summary
