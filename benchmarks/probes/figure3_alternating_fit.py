"""One Algorithm-1 fit on the Figure-3 problem in a fresh process: first epoch and steady epoch.

    python benchmarks/probes/figure3_alternating_fit.py

Six coupled Lorenz attractors, B = 8, T = 128, seed 42, the paper's weighting and the noisy
start of ``ceemx experiment figure3``; ``ceemx.fit`` with ``ceemx.Alternating`` (its default
learner and E-step bound) for 6 epochs. Prints one JSON line: the first epoch's seconds (compile
included), the median of epochs 2–6, the last J and the fit's process CPU seconds. For an A/B of
two trees run it alternately with ``PYTHONPATH=<tree>/src``.

Backs: ``benchmarks/README.md`` ("First result sooner": Algorithm 1's Figure-3 fit at LLVM -O1
against -O2, and with the block solves by inverted diagonal blocks).
"""

import json
import resource
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common, figure3  # noqa: E402
from ceemx.models import with_noise  # noqa: E402


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    true6 = common.true_lorenz(6, key=jax.random.PRNGKey(4), obs_noise=figure3.SIGMA_V)
    p6 = common.lorenz_problem(
        42, true6, B=8, T=128, sigma_w=0.0, sigma_v=figure3.SIGMA_V, coupling=True
    )
    pn, on, rho_x = figure3.fit_setup("paper")
    system = with_noise(p6.init_system, pn, on)
    x0 = jnp.asarray(figure3._noisy_states(p6, 42))
    ends = []
    t, c = time.perf_counter(), cpu()
    res = ceemx.fit(
        system,
        p6.data,
        x0,
        solver=ceemx.Alternating(smoother=ceemx.LMSmoother(rho_x=rho_x)),
        trainable=common.LORENZ_PARAMS_H,
        max_epochs=6,
        callbacks=[lambda info: ends.append(time.perf_counter())],
        progress=False,
        diagnose=False,
    )
    steps = [b - a for a, b in zip(ends[:-1], ends[1:], strict=True)]
    record = {
        "first_epoch_s": round(ends[0] - t, 3),
        "epoch_s": round(statistics.median(steps), 4),
        "J": res.history[-1]["J"],
        "fit_cpu_s": round(cpu() - c, 2),
    }
    print(json.dumps(record))


if __name__ == "__main__":
    main()
