"""First call (compile included) and steady time of three entry points, for A/B runs of two commits.

    python benchmarks/probes/ab_first_call.py smooth        # ceemx.smooth, 16 × 128 single Lorenz
    python benchmarks/probes/ab_first_call.py joint         # fit(JointLM), Figure-2 setting, B = 4
    python benchmarks/probes/ab_first_call.py smoothK 20    # 2 LM iterations, K coupled Lorenz

A/B against another commit: ``git worktree add /tmp/old REV`` and alternate
``PYTHONPATH=/tmp/old/src python benchmarks/probes/ab_first_call.py MODE`` with the current tree,
each in a fresh process, ≥ 2 runs each, recording ``uptime``; ``smoothK`` pinned with
``taskset -c 0``. It also runs on trees from before the package folders (b271a33).

Backs: ``benchmarks/README.md`` ("ceemx vs the authors' code": "``smooth``'s first call 5.5 →
3.9 s, steady +0–8 %", "first JointLM fit 15.5 → 12.4 s at load 3.5–3.9 (−20 %)") and
``docs/design.md`` (the ``inference/objective.py`` row: "smoothing −10–12 % at n = 60–120",
``smoothK 20|40``; "Joint method" notes: "``smooth``'s first call (16 × 128 Lorenz) 5.5 → 3.9 s").
"""

import pathlib
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
import ceemx  # noqa: E402


def timed(call, repeats: int) -> tuple[float, float, object]:
    t0 = time.perf_counter()
    out = jax.block_until_ready(call())
    first = time.perf_counter() - t0
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(call())
        ts.append(time.perf_counter() - t0)
    return first, float(np.median(ts)), out


mode = sys.argv[1] if len(sys.argv) > 1 else "smooth"
if mode == "smooth":
    from compare_peers import from_observations, problem

    system, p = problem(16, 128)
    x0 = from_observations(system, p.data)
    first, steady, s = timed(lambda: ceemx.smooth(system, p.data, x0), 15)
    print(f"smooth: first {first:.2f} s, steady {1e3 * steady:.2f} ms, iterations "
          f"{int(s.iterations.max())}")  # fmt: skip
elif mode == "joint":
    from ceemx.experiments import common
    from ceemx.models import with_noise

    true = common.true_lorenz(
        1, key=jax.random.PRNGKey(4), m=2, coupling=False, process_noise=0.1, obs_noise=0.5
    )
    p = common.lorenz_problem(43, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False)
    guess = with_noise(p.init_system, 0.1, 0.5)

    def fit():
        r = ceemx.fit(
            guess, p.data, solver=ceemx.JointLM(), trainable=common.LORENZ_PARAMS, progress=False
        )
        return r.states

    first, steady, _ = timed(fit, 3)
    print(f"joint fit: first {first:.2f} s, steady {steady:.4f} s")
elif mode == "smoothK":
    from scaling import make_problem

    K = int(sys.argv[2]) if len(sys.argv) > 2 else 20
    system, data, x_init = make_problem(128, 2, K)
    solver = ceemx.LMSmoother(max_steps=2, rtol=0.0, atol=0.0)
    first, steady, s = timed(lambda: ceemx.smooth(system, data, x_init, solver), 5)
    print(f"smooth K={K}: first {first:.2f} s, steady {1e3 * steady:.1f} ms, objective "
          f"{float(s.objective.sum()):.10g}")  # fmt: skip
else:
    raise SystemExit(f"unknown mode {mode!r}: smooth, joint or smoothK")
