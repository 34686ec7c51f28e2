"""Laplace EM with learned noise on the Figure-2 setting: plain EM against SQUAREM.

    python benchmarks/probes/laplace_acceleration.py [SEED ...]      # default 43–52

Per seed and acceleration: epochs to convergence (≤ 600), wall time (the first fit compiles),
learned σ_w, σ_v and σ, ρ, β — the setting of ``ceemx experiment laplace``.

Backs: ``docs/results.md`` ("Learned noise and calibrated intervals": "seed 45: 358 plain epochs
in 15.3 s, first fit with compile, against 19 SQUAREM epochs in 1.3 s") and ``docs/design.md``
(Laplace EM: "SQUAREM cuts that 5–20×").
"""

import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import ceemx  # noqa: E402
from ceemx.experiments import common, laplace  # noqa: E402
from ceemx.models import with_noise  # noqa: E402

true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, process_noise=0.1, obs_noise=0.5)
seeds = [int(s) for s in sys.argv[1:]] or list(range(43, 53))
for seed in seeds:
    p = common.lorenz_problem(seed, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False)
    start = with_noise(p.init_system, laplace.START_W, laplace.START_V)
    for acceleration in (None, "squarem"):
        t0 = time.perf_counter()
        res = ceemx.fit(
            start,
            p.data,
            solver=ceemx.LaplaceEM(acceleration=acceleration),
            trainable=lambda s: (s.sigma, s.rho, s.beta, s.process_noise, s.obs_noise),
            max_epochs=600,
            progress=False,
        )
        s = res.system
        print(
            f"seed {seed} {acceleration or 'plain'}: {res.epochs} epochs, "
            f"{time.perf_counter() - t0:.1f} s, converged {res.converged}; σ_w "
            f"{float(s.process_noise.scale):.4f}, σ_v {float(s.obs_noise.scale):.4f}, σ "
            f"{float(s.sigma[0]):.3f}, ρ {float(s.rho[0]):.3f}, β {float(s.beta[0]):.4f}",
            flush=True,
        )
