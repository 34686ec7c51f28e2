"""K = 100 coupled Lorenz: ε after one Algorithm-1 epoch against the L-BFGS step bound.

    python benchmarks/probes/k100_learner_steps.py [STEPS ...]    # default: 100 150 200

The `benchmarks/k100.py` problem (K = 100, n = 300, T = 256, B = 16, seed 42, states started at
truth + N(0, 1)): one smoothing step (`LMSmoother(max_steps=1)`, two trajectories per call), then
`LBFGSLearner(max_steps=STEPS)` from the same smoothed states and the same θ for each bound. Prints
ε / ε₀ (Eq. 14), the learning time and the load. Backs: benchmarks/README.md ("K = 100": the
learner's step bound).
"""

import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import k100  # noqa: E402

import ceemx  # noqa: E402
from ceemx.evaluation import metrics as ev  # noqa: E402
from ceemx.experiments import common  # noqa: E402


def main(argv: list[str]) -> None:
    bounds = [int(a) for a in argv] or [100, 150, 200]
    true, prob, system, x0 = k100.setup(100, 256, 16, 42)
    eps = ev.DynamicsErrorCallback(true)
    e0 = eps.error(system)
    smoother = ceemx.LMSmoother(max_steps=1)
    t0 = time.perf_counter()
    parts = [
        jax.block_until_ready(
            ceemx.smooth(system, prob.data[np.arange(i, i + 2)], x0[i : i + 2], smoother).states
        )
        for i in range(0, 16, 2)
    ]
    states = jnp.concatenate(parts)
    print(f"smoothing {time.perf_counter() - t0:.1f} s, load {os.getloadavg()[0]:.2f}", flush=True)
    for steps in bounds:
        t0 = time.perf_counter()
        learner = ceemx.LBFGSLearner(max_steps=steps)
        fitted, _, info = ceemx.learn(
            system, states, prob.data, learner, trainable=common.LORENZ_PARAMS_H
        )
        jax.block_until_ready(fitted)
        print(
            f"L-BFGS {steps}: ε/ε₀ {eps.error(fitted) / e0:.3%}, learning "
            f"{time.perf_counter() - t0:.1f} s ({int(info.steps)} steps), "
            f"load {os.getloadavg()[0]:.2f}",
            flush=True,
        )


if __name__ == "__main__":
    main(sys.argv[1:])
