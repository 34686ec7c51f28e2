"""Laplace EM with learned noise on the Figure-2 setting: plain EM, SQUAREM, quasi-Newton.

    python benchmarks/probes/laplace_acceleration.py [SEED ...] [--acc plain squarem quasi_newton]

Per seed and acceleration (default: plain and SQUAREM; seeds 43–52): epochs to convergence
(≤ 600), wall time (the first fit of each acceleration compiles), the final Laplace
log-evidence, learned σ_w, σ_v and σ, ρ, β — the setting of ``ceemx experiment laplace``.

Backs: ``docs/results.md`` ("Learned noise and calibrated intervals": "seed 45: 358 plain epochs
in 15.3 s, first fit with compile, against 19 SQUAREM epochs in 1.3 s") and ``docs/design.md``
(Laplace EM: "SQUAREM cuts that 5–20×"; the quasi-Newton steps on this setting).
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)
import ceemx  # noqa: E402
from ceemx.experiments import common, laplace  # noqa: E402
from ceemx.models import with_noise  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("seeds", type=int, nargs="*", default=list(range(43, 53)))
ap.add_argument("--acc", nargs="+", default=["plain", "squarem"])
args = ap.parse_args()
true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, process_noise=0.1, obs_noise=0.5)
for seed in args.seeds:
    p = common.lorenz_problem(seed, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False)
    start = with_noise(p.init_system, laplace.START_W, laplace.START_V)
    for name in args.acc:
        t0 = time.perf_counter()
        res = ceemx.fit(
            start,
            p.data,
            solver=ceemx.LaplaceEM(acceleration=None if name == "plain" else name),
            trainable=lambda s: (s.sigma, s.rho, s.beta, s.process_noise, s.obs_noise),
            max_epochs=600,
            progress=False,
        )
        s = res.system
        print(
            f"seed {seed} {name}: {res.epochs} epochs, "
            f"{time.perf_counter() - t0:.2f} s, converged {res.converged}; log-evidence "
            f"{res.history[-1]['log_evidence']:.6f}; σ_w "
            f"{float(s.process_noise.scale):.4f}, σ_v {float(s.obs_noise.scale):.4f}, σ "
            f"{float(s.sigma[0]):.3f}, ρ {float(s.rho[0]):.3f}, β {float(s.beta[0]):.4f}",
            flush=True,
        )
