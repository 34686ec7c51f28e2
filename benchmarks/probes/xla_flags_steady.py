"""Steady-state cost of an XLA:CPU option, A/B inside one process (issue 23, item 2).

    python benchmarks/probes/xla_flags_steady.py [--calls 15] [--option NAME=VALUE]

The option defaults to ``xla_cpu_use_fusion_emitters=false``. The Figure-3 joint iteration
(K = 6 coupled Lorenz, B = 8, T = 128, 342 parameters, the ``figure3 --method joint`` start),
the single-Lorenz smoother (B = 4, T = 128) and the same on one long record (T = 10⁴) are each
compiled twice in the same process — XLA's
defaults, and with the option as a per-program compiler option (``jax.jit(...,
compiler_options=...)``, the same effect as ``XLA_FLAGS``) — then called alternately, A B A B …,
so that the shared machine's load hits both alike. Reported: the first call of each (compile),
the median call (wall and process CPU), the ratios, and the largest difference of the outputs.
The 1-min load is printed.

Backs: ``benchmarks/README.md`` ("First-fit latency": steady state with the classic emitters).
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common, figure3  # noqa: E402
from ceemx.identification.problem import FitProblem  # noqa: E402
from ceemx.identification.solvers import joint  # noqa: E402
from ceemx.inference import smoother  # noqa: E402
from ceemx.lib.tree import trace_numbers  # noqa: E402
from ceemx.models import with_noise  # noqa: E402


def ab(name, raw, args, options, calls):
    fa = eqx.filter_jit(raw)
    fb = eqx.filter_jit(raw, compiler_options=options)
    out = {}
    for tag, f in (("default", fa), ("option", fb)):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        out[f"{tag}_first_s"] = time.perf_counter() - t
    walls = {"default": [], "option": []}
    cpus = {"default": [], "option": []}
    for _ in range(calls):
        for tag, f in (("default", fa), ("option", fb)):
            t, c = time.perf_counter(), time.process_time()
            r = jax.block_until_ready(f(*args))
            walls[tag].append(time.perf_counter() - t)
            cpus[tag].append(time.process_time() - c)
            out[f"{tag}_result"] = r
    diff = max(
        float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float))))
        for a, b in zip(
            jax.tree_util.tree_leaves(eqx.filter(out.pop("default_result"), eqx.is_array)),
            jax.tree_util.tree_leaves(eqx.filter(out.pop("option_result"), eqx.is_array)),
            strict=True,
        )
    )
    for tag in walls:
        out[f"{tag}_call_s"] = statistics.median(walls[tag])
        out[f"{tag}_call_cpu_s"] = statistics.median(cpus[tag])
    out["ratio_wall"] = out["option_call_s"] / out["default_call_s"]
    out["ratio_cpu"] = out["option_call_cpu_s"] / out["default_call_cpu_s"]
    out["max_abs_diff"] = diff
    print(name, {k: round(v, 4) if isinstance(v, float) else v for k, v in out.items()}, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--calls", type=int, default=15)
    ap.add_argument("--option", default="xla_cpu_use_fusion_emitters=false")
    args = ap.parse_args()
    key, value = args.option.split("=")
    value = {"false": False, "true": True}.get(value.lower(), value)
    value = int(value) if isinstance(value, str) and value.isdigit() else value
    options = {key: value}
    print("load", os.getloadavg(), "option", options)
    # Figure-3 joint iteration.
    true6 = common.true_lorenz(6, key=jax.random.PRNGKey(4), obs_noise=figure3.SIGMA_V)
    p6 = common.lorenz_problem(
        42, true6, B=8, T=128, sigma_w=0.0, sigma_v=figure3.SIGMA_V, coupling=True
    )
    pn, on, rho_x = figure3.fit_setup("paper")
    system = with_noise(p6.init_system, pn, on)
    problem, theta = FitProblem.create(system, p6.data, trainable=common.LORENZ_PARAMS_H)
    states = jnp.asarray(figure3._noisy_states(p6, 42))
    opts = trace_numbers(ceemx.JointLM(rho_x=rho_x), states.dtype)
    weights = jnp.ones(states.shape[:1], states.dtype)
    lam = jnp.asarray(opts.damping, states.dtype)
    ab(
        "fig3_joint_iteration",
        joint._iteration.__wrapped__,
        (opts, problem, weights, theta, states, lam),
        options,
        args.calls,
    )
    # Single-Lorenz smoother (the warm start's program).
    true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, coupling=False)
    p = common.lorenz_problem(43, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False)
    s1 = with_noise(p.init_system, 0.1, 0.5)
    x0 = jnp.zeros(p.states.shape, p.states.dtype) + p.states
    sm = trace_numbers(ceemx.LMSmoother(), x0.dtype)
    canonical = copy.copy(sm)  # as smooth_batch calls its program: the step bound traced
    object.__setattr__(canonical, "max_steps", 0)
    steps = jnp.asarray(sm.max_steps, jnp.int32)
    ab(
        "lorenz_smoother",
        smoother._smooth_batch_impl,
        (canonical, steps, s1, x0 + 0.5, p.data, False),
        options,
        args.calls * 3,
    )
    # One long record (T = 10⁴): the smoother's scans dominate, not the dense products.
    pl = common.lorenz_problem(43, true, B=1, T=10_000, sigma_w=0.1, sigma_v=0.5, coupling=False)
    xl = jnp.zeros(pl.states.shape, pl.states.dtype) + pl.states
    ab(
        "lorenz_smoother_T10000",
        smoother._smooth_batch_impl,
        (canonical, steps, s1, xl + 0.5, pl.data, False),
        options,
        max(3, args.calls // 3),
    )
    print("load", os.getloadavg())


if __name__ == "__main__":
    main()
