"""Particle EM and CE-EM time per epoch on the paper's Figure-2 setting (single Lorenz).

Setting: σ_w = 0.1, σ_v = 0.5, B = 4, T = 128, N_p = 100, N_s = 10 (fully adapted filter, FFBSi,
SAEM with the LM learner, memory 10), seed 43's data and initial guess (``ceemx experiment
figure2``). Each repetition runs a fresh fit of ``--epochs`` epochs of each method, alternating
Particle EM and CE-EM (Algorithm 1); the first epoch of the first repetition includes JIT
compilation and is reported apart. Steady-state time per epoch = median over epochs 2… of all
repetitions; the E-step (filter + FFBSi) and M-step times are split out. The 1-minute load
average is recorded before each repetition.

The authors' Particle EM (``ceem`` 0.0.4) took 1.62 s per SAEM epoch on this setting on a quiet
2-core CPU (E-step 1.44 s; 12.4 s under load ≈ 6) — ``shared/reference/numbers.md``; a
side-by-side run needs the reference environment of the performance issue.

Usage: ``python benchmarks/particle_em.py [--reps 3] [--epochs 12] [--out results.json]``
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.initialize import warm_start  # noqa: E402

REFERENCE_S = 1.62  # authors' Particle EM, s per SAEM epoch, quiet 2-core CPU (numbers.md)


def load() -> float:
    return os.getloadavg()[0]


def problem():
    true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, process_noise=0.1, obs_noise=0.5)
    prob = common.lorenz_problem(43, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False)
    system = ceemx.with_noise(prob.init_system, 0.1, 0.5)
    return system, prob.data, warm_start(system, prob.data)


def run_pem(system, data, x_init, epochs):
    solver = ceemx.ParticleEM(
        n_particles=100, n_smoothed=10, memory=10, initial=common.lorenz_initial_prior(1)
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
    )


def run_ce(system, data, x_init, epochs):
    timer = ceemx.FitTimer().start()
    ceemx.fit(
        system,
        data,
        x_init,
        solver=ceemx.Alternating(rtol=0.0),
        trainable=common.LORENZ_PARAMS,
        max_epochs=epochs,
        callbacks=[timer],
        progress=False,
    )
    return timer.per_epoch()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--epochs", type=int, default=12)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    system, data, x_init = problem()
    pem, pem_e, pem_m, ce, loads = [], [], [], [], []
    first = {}
    for rep in range(args.reps):
        loads.append(load())
        t, e, m = run_pem(system, data, x_init, args.epochs)
        c = run_ce(system, data, x_init, args.epochs)
        if rep == 0:
            first = {"particle_em_first_epoch_s": t[0], "ce_em_first_epoch_s": c[0]}
        pem += t[1:]
        pem_e += e[1:]
        pem_m += m[1:]
        ce += c[1:]
        print(
            f"rep {rep}: load {loads[-1]:.2f}; particle EM {np.median(t[1:]):.4f} s/epoch "
            f"(E {np.median(e[1:]):.4f}, M {np.median(m[1:]):.4f}); CE-EM {np.median(c[1:]):.4f}",
            flush=True,
        )
    out = {
        "setting": "single Lorenz, σ_w 0.1, σ_v 0.5, B 4, T 128, N_p 100, N_s 10, memory 10",
        "reps": args.reps,
        "epochs": args.epochs,
        "loads": loads,
        **first,
        "particle_em_s_per_epoch": float(np.median(pem)),
        "particle_em_e_step_s": float(np.median(pem_e)),
        "particle_em_m_step_s": float(np.median(pem_m)),
        "ce_em_s_per_epoch": float(np.median(ce)),
        "ratio_particle_to_ce": float(np.median(pem) / np.median(ce)),
        "reference_s_per_epoch": REFERENCE_S,
        "speedup_vs_reference": float(REFERENCE_S / np.median(pem)),
        "time": time.strftime("%Y-%m-%d %H:%M"),
    }
    print(json.dumps(out, indent=2))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
