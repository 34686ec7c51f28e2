"""Where the first JointLM fit's time goes, program by program (cold process; issue 23, item 2).

    python benchmarks/probes/first_fit_phases.py [CACHE_DIR | -]

The single-Lorenz problem of ``compare_reference.py`` (seed 43, B = 4, T = 128, explicit
midpoint, σ_w = 0.1, σ_v = 0.5): one ``ceemx.fit(..., solver=ceemx.JointLM())`` in a fresh
process, then ``NSTEADY`` (default 5) more, timed (median). ``jax.monitoring`` records, per
compiled program, the seconds of tracing (``jaxpr_trace``), lowering to StableHLO
(``jaxpr_to_mlir_module``) and XLA compilation (``backend_compile``; with a warm persistent cache
the retrieval); ``VERBOSE=1`` prints them per program, ``PROF=FILE`` writes a cProfile of the
first fit. With ``CACHE_DIR`` the persistent compilation cache is on (run twice: fill, then
warm). Process CPU seconds of the first fit are printed beside the wall time; record ``uptime``.
``SOLVER=alternating`` fits with ``ceemx.Alternating()`` (Algorithm 1, the default solver) instead.
``BACKGROUND=1`` / ``BACKGROUND=0`` forces the background compilation of the epoch programs on /
off (``fit`` decides by ``ceemx.infra.policy.compiles_ahead()`` otherwise).
``XLA_FLAGS`` is read as usual (e.g. ``--xla_cpu_use_fusion_emitters=false``).

Backs: ``benchmarks/README.md`` ("First-fit latency": the programs of a fit and their compile
times, the first fit cold and with a warm cache).
"""

import collections
import os
import sys
import time

t00 = time.perf_counter()
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
from jax._src import monitoring  # noqa: E402

events = []
monitoring.register_event_duration_secs_listener(
    lambda event, duration, **kw: events.append(
        (event.rsplit("/", 1)[-1], kw.get("fun_name", "?"), duration)
    )
)
import resource  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.identification.fitting import start  # noqa: E402

if os.environ.get("BACKGROUND") in ("0", "1"):
    start.compiles_ahead = lambda: os.environ["BACKGROUND"] == "1"

if len(sys.argv) > 1 and sys.argv[1] != "-":
    ceemx.enable_compilation_cache(sys.argv[1])
t_import = time.perf_counter() - t00


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, coupling=False, integrator="midpoint")
p = common.lorenz_problem(
    43, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False, x1_std=5**0.5
)
g = p.init_system
guess = ceemx.systems.CoupledLorenz(
    g.sigma,
    g.rho,
    g.beta,
    true.C,
    dt=true.dt,
    integrator="midpoint",
    process_noise=0.1,
    obs_noise=0.5,
)
y = jnp.asarray(p.data.y).block_until_ready()


def one():
    r = ceemx.fit(
        guess,
        ceemx.Trajectories(y),
        solver=ceemx.Alternating()
        if os.environ.get("SOLVER") == "alternating"
        else ceemx.JointLM(),
        trainable=common.LORENZ_PARAMS,
        progress=False,
    )
    r.states.block_until_ready()
    return r


events.clear()
profile = os.environ.get("PROF")
if profile:
    import cProfile

    prof = cProfile.Profile()
    prof.enable()
t, c = time.perf_counter(), cpu()
res = one()
first, first_cpu = time.perf_counter() - t, cpu() - c
if profile:
    prof.disable()
    prof.dump_stats(profile)
first_events = list(events)
steady = []
for _ in range(int(os.environ.get("NSTEADY", "5"))):
    t = time.perf_counter()
    one()
    steady.append(time.perf_counter() - t)
totals = collections.defaultdict(float)
programs = collections.defaultdict(lambda: collections.defaultdict(float))
for event, name, duration in first_events:
    totals[event] += duration
    programs[name.removeprefix("jit(").removesuffix(")")][event] += duration
if os.environ.get("VERBOSE"):
    for name, d in sorted(programs.items(), key=lambda kv: -sum(kv[1].values())):
        print(f"  {name[:40]:40s} " + " ".join(f"{k}={v:.2f}" for k, v in d.items()))
n_programs = sum(1 for e, _, _ in first_events if e == "backend_compile_duration")
print(
    f"import {t_import:.2f} s  first fit {first:.2f} s (cpu {first_cpu:.2f} s)  "
    f"steady {np.median(steady) if steady else float('nan'):.3f} s  epochs {res.epochs}  "
    f"programs {n_programs}  "
    + " ".join(f"{k.removesuffix('_duration')}={v:.2f}" for k, v in totals.items())
)
print(
    "estimate",
    float(res.system.sigma[0]),
    float(res.system.rho[0]),
    float(res.system.beta[0]),
    "J",
    res.history[-1]["J"],
)
