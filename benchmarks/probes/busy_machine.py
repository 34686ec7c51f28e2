"""Joint iterations of the demo problem, wall and CPU time per iteration (busy-machine effect).

    python benchmarks/probes/busy_machine.py                 # default: all CPUs
    taskset -c 0 python benchmarks/probes/busy_machine.py    # one CPU (as ceemx --threads 1)

Run it on an idle machine and beside CPU hogs (e.g. ``yes > /dev/null &`` once per core) to see
XLA's thread hand-offs stall under oversubscription (benchmarks/README.md, "Busy machines"):
6 coupled Lorenz, B = 4, T = 128, warm start, 7 JointLM iterations called directly (the first
compiles). Prints "wall/cpu" seconds per iteration.

Backs: ``benchmarks/README.md`` ("Busy machines": "1.7–6.5 per iteration (two runs)" with 2
threads, "0.57–0.99" pinned) and, with ``ceemx demo`` / ``ceemx --threads 1 demo``, the
``infra/runtime.py`` row of ``docs/design.md`` ("0.9–2.4 s with 2 threads against 0.6–1.0 s
with 1").
"""

import resource
import time

import jax

jax.config.update("jax_enable_x64", True)
import ceemx  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.identification.initialize import warm_start  # noqa: E402
from ceemx.identification.problem import FitProblem  # noqa: E402
from ceemx.lib.tree import trace_numbers  # noqa: E402
from ceemx.models import with_noise  # noqa: E402


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


true = common.true_lorenz(6, key=jax.random.PRNGKey(4), obs_noise=0.01)
pr = common.lorenz_problem(0, true, B=4, T=128, sigma_w=0.0, sigma_v=0.01, coupling=True)
system = with_noise(pr.init_system, 0.01, 0.01)
x0 = warm_start(system, pr.data)
solver = trace_numbers(ceemx.JointLM(), x0.dtype)
problem, theta = FitProblem.create(system, pr.data, trainable=common.LORENZ_PARAMS_H)
state = solver.init(problem, theta, x0, jax.random.PRNGKey(0))
out = []
for _ in range(7):
    t0, c0 = time.perf_counter(), cpu()
    state, _ = solver.step(problem, state)
    jax.block_until_ready(state.states)
    out.append(f"{time.perf_counter() - t0:.2f}/{cpu() - c0:.2f}")
print("wall/cpu per iteration (s):", " ".join(out))
