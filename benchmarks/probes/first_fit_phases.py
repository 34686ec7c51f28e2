"""Where the first JointLM fit's time goes, phase by phase (cold process; issue 12, compile time).

    python benchmarks/probes/first_fit_phases.py

Single-Lorenz Figure-2 problem (seed 43, B = 4, T = 128): the driver's phases run by hand —
input checks, warm start, problem creation, health test, ``solver.init``, two steps — each timed
(the first call of each compiled function includes its compile). Record ``uptime`` beside it.

Backs: ``benchmarks/README.md`` ("ceemx vs the authors' code": "What remains (load ≈ 3): XLA of
the joint iteration ≈ 55 %, of the smoother ≈ 30 %, tracing and lowering ≈ 1.5 s"; run with
``JAX_LOG_COMPILES=1``).
"""

import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.identification.health import trajectory_health  # noqa: E402
from ceemx.identification.problem import FitProblem  # noqa: E402
from ceemx.inference.smoother import check_inputs, promote_inputs  # noqa: E402
from ceemx.lib.tree import trace_numbers  # noqa: E402
from ceemx.models import with_noise  # noqa: E402

true = common.true_lorenz(
    1, key=jax.random.PRNGKey(4), m=2, coupling=False, process_noise=0.1, obs_noise=0.5
)
p = common.lorenz_problem(43, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False)
guess = with_noise(p.init_system, 0.1, 0.5)
y = np.asarray(p.data.y)
times = {}
t = time.perf_counter()


def tick(name):
    global t
    now = time.perf_counter()
    times[name] = now - t
    t = now


data = ceemx.Trajectories(jnp.asarray(y))
system, data, _ = promote_inputs(guess, data, None)
check_inputs(system, data)
tick("checks")
solver = ceemx.JointLM()
x0 = solver.initial_states(system, data)
x0.block_until_ready()
tick("warm start")
solver = trace_numbers(solver, x0.dtype)
problem, theta = FitProblem.create(system, data, trainable=common.LORENZ_PARAMS)
tick("FitProblem.create")
trajectory_health(problem, theta, x0)
tick("health test")
state = solver.init(problem, theta, x0, jax.random.PRNGKey(0))
tick("solver.init")
state, _ = solver.step(problem, state)
tick("step 1")
state, _ = solver.step(problem, state)
tick("step 2")
for name, s in times.items():
    print(f"{name:20s} {s:6.2f} s")
print(f"{'total':20s} {sum(times.values()):6.2f} s")
