"""Particle EM and CE-EM time per epoch on the paper's Figure-2 setting, beside the authors' code.

Setting: single Lorenz, σ_w = 0.1, σ_v = 0.5, B = 4, T = 128, N_p = 100, N_s = 10, seed 43's
data and initial guess (``ceemx experiment figure2``; classic RK4, dt = 0.04). ceemx: fully
adapted filter, FFBSi, SAEM with the LM learner, memory 10. Each repetition runs a fresh fit of
``--epochs`` epochs of each method; the first epoch of the first repetition includes JIT
compilation and is reported apart. Steady-state time per epoch = median over epochs 2… of all
repetitions; the E-step (filter + FFBSi) and M-step times are split out.

When the reference environment exists (``benchmarks/reference/.venv``, see
``benchmarks/reference/setup.sh``), every repetition first runs the authors' Particle EM
(``ceem`` 0.0.4) in a fresh process on the same data — same y, C, initial (σ, ρ, β), RK4 (their
single-Lorenz default is explicit midpoint; RK4 matches ceemx's data) — with their Figure-2
settings (``benchmarks/reference/run_reference_pem.py``: faPF N = 100, FFBSi 10, Q = σ_w² I,
R = σ_v² I, Px0 = 5 I, x₀ mean (−6, −6, 24), SAEM γ = 0.8, their default M-step of 10 Adam
steps), then ceemx's Particle EM and CE-EM in this process. Reported: both implementations'
s/epoch (median of epochs 2…), E/M split, the ratio measured in the same run, (σ, ρ, β) after the
last epoch, the 1-minute load before and after each repetition. Without the environment only
ceemx is measured and the authors' published quiet-machine figure (1.62 s per SAEM epoch,
``shared/reference/numbers.md``) is quoted for context.

Usage: ``python benchmarks/particle_em.py [--reps 3] [--epochs 12] [--smoke] [--out PATH]``
(default ``--out benchmarks/results/particle_em.json``; ``--smoke``: B = 2, T = 32, N_p = 20,
N_s = 2, 2 epochs, 1 repetition).

Backs: ``benchmarks/README.md`` (Particle EM against the authors' code), ``README.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import tempfile
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.identification.initialize import warm_start  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
REF_PYTHON = HERE / "reference" / ".venv" / "bin" / "python"
REF_DRIVER = HERE / "reference" / "run_reference_pem.py"
RESULTS = HERE / "results" / "particle_em.json"
REFERENCE_S = 1.62  # authors' Particle EM, s per SAEM epoch, quiet 2-core CPU (numbers.md)
TRUTH = {"sigma": 10.0, "rho": 28.0, "beta": 8.0 / 3.0}
SIGMA_W, SIGMA_V = 0.1, 0.5


def load() -> float:
    return os.getloadavg()[0]


def problem(B: int = 4, T: int = 128):
    true = common.true_lorenz(
        1, key=jax.random.PRNGKey(4), m=2, process_noise=SIGMA_W, obs_noise=SIGMA_V
    )
    prob = common.lorenz_problem(
        43, true, B=B, T=T, sigma_w=SIGMA_W, sigma_v=SIGMA_V, coupling=False
    )
    system = ceemx.with_noise(prob.init_system, SIGMA_W, SIGMA_V)
    return true, system, prob.data, warm_start(system, prob.data)


def write_problem(path, true, system, data, n_particles, n_smoothed, epochs) -> None:
    """The reference's input: ceemx's data and initial guess (single Lorenz: same ordering)."""
    assert true.substeps == 1, "the reference takes one integrator step per sample"
    np.savez(
        path,
        y=np.asarray(data.y),
        C=np.asarray(true.C),
        sigma0=np.asarray(system.sigma),
        rho0=np.asarray(system.rho),
        beta0=np.asarray(system.beta),
        dt=np.asarray(true.dt),
        sigma_w=np.asarray(SIGMA_W),
        sigma_v=np.asarray(SIGMA_V),
        n_particles=np.asarray(n_particles),
        n_smoothed=np.asarray(n_smoothed),
        epochs=np.asarray(epochs),
        integrator=np.asarray(true.integrator),
        seed=np.asarray(0),
    )


def theta_of(system) -> dict[str, float]:
    return {k: float(np.asarray(getattr(system, k)).reshape(-1)[0]) for k in TRUTH}


def max_rel_error(theta: dict[str, float]) -> float:
    return max(abs(theta[k] - v) / v for k, v in TRUTH.items())


def run_pem(system, data, x_init, epochs, n_particles=100, n_smoothed=10):
    solver = ceemx.ParticleEM(
        n_particles=n_particles,
        n_smoothed=n_smoothed,
        memory=10,
        initial=common.lorenz_initial_prior(1),
    )
    timer = ceemx.FitTimer().start()
    res = ceemx.fit(
        system,
        data,
        x_init,
        solver=solver,
        trainable=common.LORENZ_PARAMS,
        max_epochs=epochs,
        callbacks=[timer],
        progress=False,
        key=jax.random.PRNGKey(0),
    )
    return (
        timer.per_epoch(),
        [h["e_step_time"] for h in res.history],
        [h["m_step_time"] for h in res.history],
        theta_of(res.system),
    )


def run_ce(system, data, x_init, epochs):
    timer = ceemx.FitTimer().start()
    res = ceemx.fit(
        system,
        data,
        x_init,
        solver=ceemx.Alternating(rtol=0.0),
        trainable=common.LORENZ_PARAMS,
        max_epochs=epochs,
        callbacks=[timer],
        progress=False,
    )
    return timer.per_epoch(), theta_of(res.system)


def run_reference(problem_path: pathlib.Path, out_path: pathlib.Path) -> dict:
    proc = subprocess.run(
        [str(REF_PYTHON), str(REF_DRIVER), str(problem_path), str(out_path)],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"the reference failed:\n{proc.stderr[-4000:]}")
    return json.loads(out_path.read_text())


def _med(xs) -> float | None:
    return float(np.median(xs)) if len(xs) else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--epochs", type=int, default=12)
    parser.add_argument("--smoke", action="store_true", help="B 2, T 32, N_p 20, 2 epochs, 1 rep")
    parser.add_argument("--no-reference", action="store_true", help="measure ceemx only")
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args()
    if args.smoke:
        B, T, n_p, n_s, epochs, reps = 2, 32, 20, 2, 2, 1
    else:
        B, T, n_p, n_s, epochs, reps = 4, 128, 100, 10, args.epochs, args.reps
    have_ref = REF_PYTHON.exists() and not args.no_reference
    if not have_ref:
        why = (
            "--no-reference"
            if args.no_reference
            else f"reference environment absent ({REF_PYTHON})"
        )
        print(
            f"{why}: measuring ceemx only (the authors' published figure, {REFERENCE_S} s/epoch "
            "on a quiet 2-core CPU, is quoted for context; run benchmarks/reference/setup.sh "
            "for a side-by-side run).",
            flush=True,
        )
    true, system, data, x_init = problem(B, T)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        prob_path = tmp / "pem.npz"
        write_problem(prob_path, true, system, data, n_p, n_s, epochs)
        for rep in range(reps):
            rec: dict = {"rep": rep, "load_before": load()}
            if have_ref:
                rec["reference"] = run_reference(prob_path, tmp / "ref.json")
                rec["load_between"] = load()
            t, e, m, th = run_pem(system, data, x_init, epochs, n_p, n_s)
            rec["particle_em"] = {"epoch_s": t, "e_step_s": e, "m_step_s": m, "theta": th}
            c, th_ce = run_ce(system, data, x_init, epochs)
            rec["ce_em"] = {"epoch_s": c, "theta": th_ce}
            rec["load_after"] = load()
            runs.append(rec)
            line = (
                f"rep {rep}: load {rec['load_before']:.2f} → {rec['load_after']:.2f}; "
                f"ceemx particle EM {np.median(t[1:] or t):.4f} s/epoch "
                f"(E {np.median(e[1:] or e):.4f}, M {np.median(m[1:] or m):.4f}); "
                f"CE-EM {np.median(c[1:] or c):.4f}"
            )
            if have_ref:
                r = rec["reference"]
                line += (
                    f"; reference particle EM {np.median(r['epoch_s'][1:] or r['epoch_s']):.3f} "
                    f"s/epoch (E {np.median(r['e_step_s'][1:] or r['e_step_s']):.3f}, "
                    f"M {np.median(r['m_step_s'][1:] or r['m_step_s']):.3f})"
                )
            print(line, flush=True)

    def steady(name, key):
        return [s for r in runs if name in r for s in r[name][key][1:]]

    pem, ce = steady("particle_em", "epoch_s"), steady("ce_em", "epoch_s")
    summary: dict = {
        "ceemx_particle_em": {
            "first_epoch_s": runs[0]["particle_em"]["epoch_s"][0],
            "s_per_epoch": _med(pem),
            "e_step_s": _med(steady("particle_em", "e_step_s")),
            "m_step_s": _med(steady("particle_em", "m_step_s")),
            "theta_last": [r["particle_em"]["theta"] for r in runs],
            "max_rel_error_last": [max_rel_error(r["particle_em"]["theta"]) for r in runs],
        },
        "ceemx_ce_em": {
            "first_epoch_s": runs[0]["ce_em"]["epoch_s"][0],
            "s_per_epoch": _med(ce),
            "theta_last": [r["ce_em"]["theta"] for r in runs],
            "max_rel_error_last": [max_rel_error(r["ce_em"]["theta"]) for r in runs],
        },
        "ratio_particle_to_ce": _med(pem) / _med(ce) if pem and ce else None,
    }
    if have_ref:
        ref = steady("reference", "epoch_s")
        summary["reference_particle_em"] = {
            "first_epoch_s": [r["reference"]["epoch_s"][0] for r in runs],
            "s_per_epoch": _med(ref),
            "e_step_s": _med(steady("reference", "e_step_s")),
            "m_step_s": _med(steady("reference", "m_step_s")),
            "last_epoch_s": [r["reference"]["epoch_s"][-1] for r in runs],
            "theta_last": [r["reference"]["theta"][-1] for r in runs],
            "max_rel_error_last": [max_rel_error(r["reference"]["theta"][-1]) for r in runs],
        }
        summary["speedup_particle_em_same_run"] = _med(ref) / _med(pem) if ref and pem else None
        summary["speedup_per_rep"] = [
            float(
                np.median(r["reference"]["epoch_s"][1:])
                / np.median(r["particle_em"]["epoch_s"][1:])
            )
            for r in runs
            if len(r["particle_em"]["epoch_s"]) > 1
        ]
    else:
        summary["reference_published_s_per_epoch"] = REFERENCE_S
        summary["speedup_vs_published_reference"] = REFERENCE_S / _med(pem) if pem else None
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "setting": {
            "system": "single Lorenz, RK4, dt 0.04, m 2",
            "sigma_w": SIGMA_W,
            "sigma_v": SIGMA_V,
            "B": B,
            "T": T,
            "n_particles": n_p,
            "n_smoothed": n_s,
            "ceemx_memory": 10,
            "epochs": epochs,
            "reps": reps,
            "reference": "side by side (fresh process per rep)" if have_ref else "absent",
            "initial_theta": theta_of(system),
        },
        "loads": [(r["load_before"], r["load_after"]) for r in runs],
        "summary": summary,
        "runs": runs,
    }
    print(json.dumps(summary, indent=1))
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
