"""Paper Figure 3 (§4.1.3): convergence of CE-EM on six coupled Lorenz attractors (n = 18).

Setup: K = 6 attractors, y = C x + v ∈ R^16 with C standard normal (full row rank) from a fixed key
and known (frozen), H standard normal with each attractor's own 3×3 block zeroed and scaled to
Frobenius norm 5 (fixed key), σ_v = 0.01, no process noise, T = 128, dt = 0.04 (RK4),
B ∈ {2, 4, 8} trajectories, 4 seeds each (42–45, as the authors' script: each seed draws the data
and the initial guess). θ = [σ_{1:6}, ρ_{1:6}, β_{1:6}, H] is initialised elementwise at
θ·(1 + U(−0.1, 0.1)); ρ_θ = 0; the smoother starts from the true states + N(0, 1) noise (as the
authors' script). ε(θ) (Eq. 14, :func:`ceemx.evaluation.metrics.dynamics_error`) is recorded every
epoch.

Weightings (noise scales of the fitted system):

- ``"paper"`` — the authors' Figure-3 script: unit weights on observation and dynamics residuals
  (obs_noise = process_noise = 1) and a smoother trust region of 0.01 in their residual form,
  i.e. ρ_x = ½·0.01² = 5·10⁻⁵ in ours (penalty ρ_x‖x − x_k‖²).
- ``"likelihood"`` — obs_noise = σ_v = 0.01 and, since the data are deterministic and a zero
  process noise has no density, a small process noise 0.01 (documented choice); ρ_x = 0.

``method="joint"`` (default) minimises J jointly in (x, θ); ``"alternate"`` is Algorithm 1 with
the learner selected by ``learner`` (``"lm"``: :class:`ceemx.LMLearner`; ``"lbfgs"``: 100 L-BFGS
steps per epoch, as the authors).

Reference (authors' code, measured on a 2-core CPU): ε ≈ 102 → 6.4 after 184 epochs for B = 8
(20 min, 6.2 s per epoch).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ceemx import LBFGSLearner, LMLearner, fit
from ceemx.evaluation import metrics as ev
from ceemx.evaluation import report
from ceemx.experiments import common
from ceemx.models import with_noise
from ceemx.systems import CoupledLorenz

NAME = "figure3"
SIGMA_V = 0.01
FIRST_SEED = 42  # seeds 42, 43, …; the paper's runs use 42–45
BATCH_SIZES = (2, 4, 8)
#: Per-epoch diagnostics kept in results.json, besides the solver's own (its ``history_keys``).
HISTORY_KEYS = ("J", "eps", "wall")
REFERENCE = "authors' code: ε ≈ 102 → 6.4 after 184 epochs for B = 8 (20 min, 6.2 s per epoch)"
#: Particle EM (``method="particle"``): the paper's N_p = 100, N_s = 10; the fit runs its epochs.
PARTICLE_OPTIONS = {"n_particles": 100, "n_smoothed": 10, "burn_in": 5, "alpha": 0.7, "memory": 5}
PARTICLE_NOTE = (
    "Particle EM models the data as they are generated with the authors' Particle-EM noise "
    "(σ_w = σ_v = 0.01, the likelihood weighting), a fully adapted filter with N_p = 100 and the "
    "prior N((−6, −6, 24), 2.5²) on x₁, FFBSi N_s = 10, SAEM (burn-in 5, α = 0.7, memory 5), "
    "the M-step by L-BFGS (100 steps). Paper: Particle EM 'appears to initially improve but then "
    "converges to very poor parameter estimates'."
)


def fit_setup(weighting: str) -> tuple[float, float, float]:
    """(process_noise, obs_noise, ρ_x) of the fitted system for a weighting."""
    if weighting == "paper":
        return 1.0, 1.0, 0.5 * 0.01**2
    if weighting == "likelihood":
        return 0.01, SIGMA_V, 0.0
    raise ValueError(f"unknown weighting {weighting!r}; use 'paper' or 'likelihood'.")


def make_learner(name: str):
    """``"lm"`` → :class:`LMLearner`; ``"lbfgs"`` → :class:`LBFGSLearner` (100 steps per epoch)."""
    if name == "lm":
        return LMLearner()
    if name == "lbfgs":
        return LBFGSLearner(max_steps=100)
    raise ValueError(f"unknown learner {name!r}; use 'lm' or 'lbfgs'.")


def _noisy_states(problem, seed: int):
    """Start states: the true states plus N(0, 1) noise (the authors' script), keyed by the seed."""
    k_x = jax.random.fold_in(jax.random.PRNGKey(seed), 1)
    return problem.states + jax.random.normal(k_x, problem.states.shape, problem.states.dtype)


def _epoch_printer(B: int, seed: int):
    """The per-epoch progress line of one run (a :class:`DynamicsErrorCallback` printer)."""

    def show(info, eps):
        print(
            f"  [B={B} seed={seed}] epoch {info.epoch:4d}  ε = {eps:.6g}  "
            f"J = {info.record['J']:.8g}",
            flush=True,
        )

    return show


def _record(res, true, *, B: int, seed: int, eps0: float, times, keep) -> dict:
    """The JSON-able record of one run: ε and J per epoch, timings, learned parameters."""
    eps = [eps0] + [h["eps"] for h in res.history]
    learned = res.system
    assert isinstance(learned, CoupledLorenz)
    H_err = float(jnp.linalg.norm(learned.effective_coupling() - true.effective_coupling()))
    return {
        "B": B,
        "seed": seed,
        "eps": eps,
        "J": [res.initial_J] + [h["J"] for h in res.history],
        "epochs": res.epochs,
        "converged": bool(res.converged),
        "monotone": ev.is_monotone(res.initial_J, res.history),
        "first_epoch_s": times[0] if times else float("nan"),
        "per_epoch_s": float(np.mean(times[1:])) if len(times) > 1 else float("nan"),
        "total_s": float(sum(times)),
        "H_error": H_err,
        "sigma": np.asarray(learned.sigma),
        "rho": np.asarray(learned.rho),
        "beta": np.asarray(learned.beta),
        "status": res.messages(),
        "history": [{k: h[k] for k in keep if k in h} for h in res.history],
    }


def run_one(true, seed, B, *, T, method, weighting, learner, max_epochs, rtol, verbose):
    """One identification; returns a JSON-able record with ε per epoch and timings."""
    problem = common.lorenz_problem(
        seed, true, B=B, T=T, sigma_w=0.0, sigma_v=SIGMA_V, coupling=True
    )
    pn, on, rho_x = fit_setup("likelihood" if method == "particle" else weighting)
    system = with_noise(problem.init_system, pn, on)
    x_init = _noisy_states(problem, seed)
    record_eps = ev.DynamicsErrorCallback(
        true, printer=_epoch_printer(B, seed) if verbose else None
    )
    eps0 = record_eps.error(system)
    solver = common.make_solver(
        method,
        rho_x=rho_x,
        learner=make_learner(learner),
        rtol=rtol,
        initial=common.lorenz_initial_prior(true.K),  # used by Particle EM only
        particle_options=PARTICLE_OPTIONS,
    )
    timer = ev.FitTimer().start()
    res = fit(
        system,
        problem.data,
        x_init,
        solver=solver,
        trainable=common.LORENZ_PARAMS_H,
        max_epochs=max_epochs,
        callbacks=[record_eps, timer],
        progress=False,
        key=jax.random.PRNGKey(seed),
    )
    keep = (*HISTORY_KEYS, *solver.history_keys)
    return _record(res, true, B=B, seed=seed, eps0=eps0, times=timer.per_epoch(), keep=keep)


def make_table(runs: Sequence[dict], header_note: str) -> str:
    """Markdown: per run, initial/final ε, epochs, monotonicity, timings; the authors' reference."""
    rows = [
        [
            r["B"],
            r["seed"],
            f"{r['eps'][0]:.4g}",
            f"{r['eps'][-1]:.4g}",
            r["epochs"],
            "yes" if r["monotone"] else "**no**",
            f"{r['first_epoch_s']:.2f}",
            f"{r['per_epoch_s']:.3f}",
            f"{r['total_s']:.1f}",
        ]
        for r in runs
    ]
    header = [
        "B",
        "seed",
        "ε initial",
        "ε final",
        "epochs",
        "J monotone",
        "1st epoch s (JIT)",
        "s / epoch",
        "total s",
    ]
    per_B = []
    for B in sorted({r["B"] for r in runs}):
        finals = [r["eps"][-1] for r in runs if r["B"] == B]
        per_B.append(
            [B, len(finals), f"{np.median(finals):.4g}", f"{min(finals):.4g}", f"{max(finals):.4g}"]
        )
    summary = report.markdown_table(["B", "seeds", "median ε final", "min", "max"], per_B)
    runs_table = report.markdown_table(header, rows)
    return f"{header_note}\n\n{runs_table}\n{summary}\nReference — {REFERENCE}.\n"


def plot(runs: Sequence[dict], path, title: str) -> None:
    """ε(θ) against epoch on a log scale: one colour per B, one line per seed (paper Figure 3)."""
    plt = report.plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    colours = dict(zip(BATCH_SIZES, ("tab:blue", "tab:orange", "tab:green"), strict=False))
    seen = set()
    for r in runs:
        c = colours.get(r["B"], None)
        label = f"B = {r['B']}" if r["B"] not in seen else None
        seen.add(r["B"])
        ax.semilogy(
            np.arange(len(r["eps"])),
            np.maximum(r["eps"], 1e-300),
            color=c,
            lw=1.2,
            alpha=0.85,
            label=label,
        )
    ax.set_xlabel("epoch")
    ax.set_ylabel("ε(θ)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    report.save_figure(fig, path)


@dataclass(frozen=True)
class Config:
    """The settings of one weighting's run, defaults filled in (Particle EM's applied)."""

    method: str
    weighting: str
    learner: str
    seeds: list[int]
    batch_sizes: tuple[int, ...]
    K: int
    T: int
    max_epochs: int
    rtol: float


def configure(
    *,
    smoke: bool,
    seeds,
    method: str | None,
    weighting: str,
    learner: str,
    max_epochs: int | None,
    batch_sizes: Sequence[int] | None,
    K: int | None,
    T: int | None,
    rtol: float | None,
) -> Config:
    """:func:`run`'s arguments with their defaults (smoke or paper scale) filled in."""
    method = "joint" if method is None else method
    if method == "particle":
        weighting = "likelihood"
        learner = "lbfgs"
        batch_sizes = batch_sizes or ((2,) if smoke else (8,))
        max_epochs = (3 if smoke else 50) if max_epochs is None else max_epochs
    if rtol is None:
        rtol = 1e-10 if method == "joint" else 0.0
    return Config(
        method=method,
        weighting=weighting,
        learner=learner,
        seeds=common.seed_list(seeds, first=FIRST_SEED, default=1 if smoke else 4),
        batch_sizes=tuple(batch_sizes or ((2,) if smoke else BATCH_SIZES)),
        K=(2 if smoke else 6) if K is None else K,
        T=(32 if smoke else 128) if T is None else T,
        max_epochs=(3 if smoke else 200) if max_epochs is None else max_epochs,
        rtol=rtol,
    )


def run_all(true, c: Config, *, verbose: bool) -> list[dict]:
    """Every (B, seed) identification, in order, with a one-line summary of each."""
    runs = []
    for B in c.batch_sizes:
        for seed in c.seeds:
            r = run_one(
                true,
                seed,
                B,
                T=c.T,
                method=c.method,
                weighting=c.weighting,
                learner=c.learner,
                max_epochs=c.max_epochs,
                rtol=c.rtol,
                verbose=verbose,
            )
            runs.append(r)
            if verbose:
                print(
                    f"[B={B} seed={seed}] ε {r['eps'][0]:.4g} → {r['eps'][-1]:.4g} "
                    f"after {r['epochs']} epochs; "
                    f"J monotone: {r['monotone']}; first epoch {r['first_epoch_s']:.2f}s, then "
                    f"{r['per_epoch_s']:.3f}s/epoch; ‖H − H_true‖ = {r['H_error']:.4g}",
                    flush=True,
                )
    return runs


def _note(c: Config, total: float) -> str:
    """The table's heading: the problem, the method and its settings, the wall time."""
    note = (
        f"## Figure 3 — {c.K} coupled Lorenz (n = {3 * c.K}), T = {c.T}, σ_v = {SIGMA_V}, "
        f"method = {c.method}"
        + (f" (learner {c.learner})" if c.method == "alternate" else "")
        + f", weighting = {c.weighting}, max_epochs = {c.max_epochs}; "
        f"total wall time {total:.1f} s"
    )
    if c.method == "particle":
        note += "\n\n" + PARTICLE_NOTE
    return note


def _summary(c: Config, runs: list[dict], *, total: float, table: str) -> dict:
    """The results of a run as ``results.json`` holds them."""
    return {
        "experiment": NAME,
        "method": c.method,
        "weighting": c.weighting,
        "learner": c.learner,
        "K": c.K,
        "T": c.T,
        "sigma_v": SIGMA_V,
        "seeds": c.seeds,
        "rtol": c.rtol,
        "batch_sizes": list(c.batch_sizes),
        "max_epochs": c.max_epochs,
        "runs": runs,
        "wall_s": total,
        "reference": REFERENCE,
        "table": table,
    }


def _run_weightings(out, **kwargs) -> dict:
    """:func:`run` for the paper and the likelihood weighting, each in its subfolder of ``out``."""
    base = report.output_dir(out, "results/figure3")
    return {w: run(out=base / w, weighting=w, **kwargs) for w in ("paper", "likelihood")}


def run(
    *,
    smoke: bool = False,
    seeds=None,
    out=None,
    method: str | None = None,
    weighting: str = "paper",
    learner: str = "lm",
    max_epochs: int | None = None,
    batch_sizes: Sequence[int] | None = None,
    K: int | None = None,
    T: int | None = None,
    rtol: float | None = None,
    verbose: bool = True,
) -> dict:
    """Run the Figure 3 experiment; writes ``results.json``, ``table.md`` and ``figure3.png``.

    Args:
        smoke: a tiny run (B = 2, one seed, K = 2 attractors, T = 32, 3 epochs) for the tests.
        seeds: N (the first N of the seeds 42, 43, …; default 4), a list of seeds, or a string
            as ``--seeds`` takes (:func:`ceemx.experiments.common.parse_seeds`).
        out: output folder (default ``./results/figure3``).
        method: ``"joint"`` (default), ``"alternate"`` (Algorithm 1) or ``"particle"`` (Particle
            EM with L-BFGS M-steps and the likelihood weighting; B = 8 and 50 epochs by default,
            as the authors' Particle-EM script ran B = 8 only).
        weighting: ``"paper"`` (default) or ``"likelihood"`` (``"both"`` runs both, in subfolders).
        learner: ``"lm"`` or ``"lbfgs"`` (alternate only).
        max_epochs: epochs (or joint iterations) per run (default 200; smoke 3).
        batch_sizes: B values (default 2, 4, 8).
        K: number of attractors (default 6; smoke 2).
        T: time steps per trajectory (default 128; smoke 32).
        rtol: relative stopping tolerance on the improvement of J (the solver's ``rtol``; default
            1e-10 for the joint method, 0 for alternation, which then runs all ``max_epochs``
            epochs unless J stops improving).
        verbose: print ε per epoch and the table.

    Returns:
        The results (also in ``results.json``), with the Markdown table under ``"table"``.

    """
    common.enable_x64()
    options: dict[str, Any] = dict(
        smoke=smoke,
        seeds=seeds,
        method=method,
        learner=learner,
        max_epochs=max_epochs,
        batch_sizes=batch_sizes,
        K=K,
        T=T,
        rtol=rtol,
    )
    if weighting == "both":
        return _run_weightings(out, **options, verbose=verbose)
    c = configure(**options, weighting=weighting)
    outdir = report.output_dir(out, "results/figure3")
    true = common.true_lorenz(c.K, key=jax.random.PRNGKey(4), obs_noise=SIGMA_V)
    t_start = time.perf_counter()
    runs = run_all(true, c, verbose=verbose)
    total = time.perf_counter() - t_start
    table = make_table(runs, _note(c, total))
    summary = _summary(c, runs, total=total, table=table)
    _save(outdir, c, summary, verbose=verbose)
    return summary


def _save(outdir, c: Config, summary: dict, *, verbose: bool) -> None:
    """``results.json``, ``table.md`` and ``figure3.png``; the table printed when verbose."""
    report.save_json(outdir / "results.json", summary)
    report.save_text(outdir / "table.md", summary["table"])
    title = f"{c.K} coupled Lorenz: ε(θ) per epoch ({c.method}, {c.weighting})"
    plot(summary["runs"], outdir / "figure3.png", title)
    if verbose:
        print(summary["table"])
