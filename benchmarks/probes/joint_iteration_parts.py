"""The demo-size joint iteration and its parts, each compiled alone (issue 23, item 1).

    python benchmarks/probes/joint_iteration_parts.py

Six coupled Lorenz attractors (n = 18, m = 16, B = 4, T = 128, θ = σ, ρ, β and H: 342
parameters), the demo's data and warm start. Each program is compiled once, then called 5 times
(median and minimum printed, milliseconds): the joint linearisation (``linearize_joint``), the
identifiability check's Schur complement (``schur_complement``, compiled one-shot at this size),
the whole joint iteration (``_iteration``), the batched block Cholesky of the state blocks, its
diagonal blocks' inverses, the forward half of a solve with the 342 border columns, a whole
solve with them, a one-right-hand-side solve, and Σ_b Wᵀ W. First, before any of those: the
joint iteration's ahead-of-time compile in the fresh process — wall and process CPU seconds of
``lower`` and of ``compile`` (the CPU above the wall is XLA:CPU's parallel code generation) —
and the identifiability S's first call (compile and run); ``CEEMX_ONE_SHOT=0`` compiles S
optimised instead of one-shot.
Record ``uptime``.

Backs: ``benchmarks/README.md`` ("First result sooner": the 343-right-hand-side solve, the joint
iteration and S before/after the block solves by inverted diagonal blocks, the linearisation
before/after the observation map's zero θ-Jacobian was skipped; the iteration's compile CPU at
-O1 against -O2 — ``XLA_FLAGS=--xla_backend_optimization_level=2`` — and S one-shot against
optimised).
"""

import os
import resource
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.identification import schur  # noqa: E402
from ceemx.identification.initialize import warm_start  # noqa: E402
from ceemx.identification.problem import FitProblem  # noqa: E402
from ceemx.identification.solvers import joint  # noqa: E402
from ceemx.lib.arrowhead import factor, schur_terms  # noqa: E402
from ceemx.lib.blocktri import cholesky, diagonal_inverses, forward_solve, solve  # noqa: E402
from ceemx.lib.tree import trace_numbers  # noqa: E402
from ceemx.models import with_noise  # noqa: E402


def timeit(name, f, n=5):
    jax.block_until_ready(f())
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        jax.block_until_ready(f())
        ts.append(time.perf_counter() - t)
    print(f"{name:28s} {np.median(ts) * 1e3:8.1f} ms  (min {min(ts) * 1e3:.1f})", flush=True)


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    print("load", os.getloadavg())
    true = common.true_lorenz(6, key=jax.random.PRNGKey(4), obs_noise=0.01)
    pb = common.lorenz_problem(0, true, B=4, T=128, sigma_w=0.0, sigma_v=0.01, coupling=True)
    system = with_noise(pb.init_system, 0.01, 0.01)
    problem, theta = FitProblem.create(system, pb.data, trainable=common.LORENZ_PARAMS_H)
    x = warm_start(system, pb.data)
    w = jnp.ones((4,))
    solver = trace_numbers(ceemx.JointLM(), x.dtype)
    lam = jnp.asarray(solver.damping, x.dtype)
    t, c = time.perf_counter(), cpu()
    lowered = joint._iteration.lower(solver, problem, w, theta, x, lam)
    t1, c1 = time.perf_counter(), cpu()
    lowered.compile()
    t2, c2 = time.perf_counter(), cpu()
    print(
        f"iteration: trace+lower {t1 - t:.2f} s (cpu {c1 - c:.2f}), "
        f"compile {t2 - t1:.2f} s (cpu {c2 - c1:.2f})"
    )
    t = time.perf_counter()
    jax.block_until_ready(schur.schur_complement(problem, theta, x, w))
    print(f"schur_complement first call (compile + run) {time.perf_counter() - t:.2f} s")
    timeit("linearize_joint", lambda: schur.linearize_joint(problem, w, theta, x))
    timeit("schur_complement", lambda: schur.schur_complement(problem, theta, x, w))
    timeit("iteration", lambda: joint._iteration(solver, problem, w, theta, x, lam))
    _, lin = schur.linearize_joint(problem, w, theta, x)
    chol = jax.jit(jax.vmap(cholesky))
    timeit("block Cholesky", lambda: chol(lin.A))
    L = chol(lin.A)
    inverses = jax.jit(jax.vmap(diagonal_inverses))
    timeit("diagonal inverses", lambda: inverses(L))
    inv = inverses(L)
    fwd = jax.jit(jax.vmap(forward_solve))
    timeit("forward half, 342 columns", lambda: fwd(L, lin.E, inv))
    whole = jax.jit(jax.vmap(solve))
    timeit("solve, 342 columns", lambda: whole(L, lin.E, inv))
    timeit("solve, 1 column", lambda: whole(L, lin.grad_x, inv))
    terms = jax.jit(lambda A, E: schur_terms(*factor(A), E))
    timeit("sum W^T W (factor included)", lambda: terms(lin.A, lin.E))
    print("load", os.getloadavg())


if __name__ == "__main__":
    main()
