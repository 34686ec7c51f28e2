"""``ceemx.smooth`` at known θ: iterations and time by start (least squares / EKF), rtol, damping.

    python benchmarks/probes/smoother_start.py

The problem of ``benchmarks/compare_peers.py`` (16 single-Lorenz trajectories × 128 steps).
Median of 5 steady calls per case; RMSE against the simulated states.

Backs: ``benchmarks/README.md`` ("ceemx.smooth: per iteration vs iteration count": "the default
``rtol = 1e-10`` and the least-squares start take 9 iterations where the MAP changes after the
fourth only in the sixth digit").
"""

import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from compare_peers import problem  # noqa: E402

import ceemx  # noqa: E402
from ceemx.identification.initialize import from_observations  # noqa: E402

system, p = problem(16, 128)
starts = {
    "least squares": from_observations(system, p.data),
    "EKF means": ceemx.ekf(system, p.data).filtered_means,
}
for name, x0 in starts.items():
    for rtol, damping in ((1e-10, 1e-3), (1e-6, 1e-3), (1e-6, 1e-6)):
        smoother = ceemx.LMSmoother(rtol=rtol, damping=damping)
        ceemx.smooth(system, p.data, x0, smoother).states.block_until_ready()
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            sol = ceemx.smooth(system, p.data, x0, smoother)
            sol.states.block_until_ready()
            ts.append(time.perf_counter() - t0)
        rmse = float(jnp.sqrt(jnp.mean((sol.states - p.states) ** 2)))
        print(
            f"{name:14s} rtol {rtol:g}, damping {damping:g}: {1e3 * np.median(ts):.1f} ms, "
            f"iterations {int(sol.iterations.max())}, RMSE {rmse:.5f}"
        )
