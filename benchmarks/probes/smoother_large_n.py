"""The smoother at large state dimension: where one step goes, and the two forms of its LM loop.

    python benchmarks/probes/smoother_large_n.py parts [K]      # one trajectory, T = 256; K = 100
    python benchmarks/probes/smoother_large_n.py ratio [K ...]  # linearisation/value; B 4, T 128
    python benchmarks/probes/smoother_large_n.py lazy K B T [S ...]  # eager vs by value
    python benchmarks/probes/smoother_large_n.py solve [n ...]  # vector block solve; T 256, B 2

The coupled-Lorenz problem of ``benchmarks/k100.py`` (states at truth + N(0, 1)). Each piece is
compiled first, then timed (minimum or median of repeats, printed with the load):

* ``parts``: the linearisation of −J, the dynamics' Jacobians alone, the damped block Cholesky,
  the solve (with the block inverses, the form before vector solves went step by step);
* ``ratio``: ``linearize`` against ``neg_log_joint_single`` (vmapped over B), per K;
* ``lazy``: the smoother's compiled kernel traced with the eager form and with trial points judged
  by value (``LAZY_MIN_STATES`` set around the trace), trace/lower/compile times of each, then
  both called in turn with S allowed steps (default 1, 2, 5 and 50; medians of 5);
* ``solve``: ``blocktri.solve`` through the inverted diagonal blocks against per-step triangular
  solves, for a vector right-hand side.

Backs: the ``LAZY_MIN_STATES`` comment in ``ceemx/inference/smoother.py``, ``_by_inverses`` in
``ceemx/lib/blocktri.py``, and benchmarks/README.md ("K = 100 in 10 minutes").
"""

import copy
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
from ceemx import lib  # noqa: E402
from ceemx.inference import smoother as sm  # noqa: E402
from ceemx.inference.objective import linearize, neg_log_joint_single  # noqa: E402
from ceemx.lib import blocktri  # noqa: E402
from ceemx.lib.tree import trace_numbers  # noqa: E402


def load() -> str:
    return f"load {os.getloadavg()[0]:.2f}"


def timed(f, *args, reps: int = 3) -> tuple[float, float]:
    """(first call, fastest of ``reps`` later calls) in seconds."""
    t0 = time.perf_counter()
    jax.block_until_ready(f(*args))
    first = time.perf_counter() - t0
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t0)
    return first, min(ts)


def parts(K: int) -> None:
    _, prob, system, x0 = k100.setup(K, 256, 1, 42)
    x, y, u, mask = x0[0], prob.data.y[0], prob.data.u[0], prob.data.mask[0]
    lin = jax.jit(lambda s, x: linearize(lambda s: s, s, x, y, u, mask))(system, x)
    damped = lib.add_to_diagonal(lin.hess_x, 1.0)
    L = jax.jit(lib.cholesky)(damped)
    pieces = {
        "linearisation": (
            jax.jit(lambda s, x: linearize(lambda s: s, s, x, y, u, mask)),
            system,
            x,
        ),
        "dynamics Jacobians": (
            jax.jit(lambda x: jax.vmap(jax.jacfwd(lambda z: system.dynamics(z, u[0], 0)))(x[:-1])),
            x,
        ),
        "block Cholesky": (
            jax.jit(lambda h: lib.cholesky(lib.add_to_diagonal(h, 1.0))),
            lin.hess_x,
        ),
        "solve (block inverses)": (
            jax.jit(lambda L, g: blocktri.solve(L, g, blocktri.diagonal_inverses(L))),
            L,
            lin.grad_x,
        ),
        "solve (default)": (jax.jit(blocktri.solve), L, lin.grad_x),
    }
    for name, (f, *args) in pieces.items():
        first, steady = timed(f, *args)
        print(
            f"n = {3 * K}, {name}: first {first:.2f} s, steady {steady:.3f} s, {load()}", flush=True
        )


def ratio(Ks: list[int]) -> None:
    for K in Ks:
        _, prob, system, x0 = k100.setup(K, 128, 4, 42)
        d = prob.data
        args = (x0, d.y, d.u, d.mask)
        E = jax.jit(
            jax.vmap(
                lambda s, x, y, u, m: linearize(lambda s: s, s, x, y, u, m), (None, 0, 0, 0, 0)
            )
        )
        V = jax.jit(jax.vmap(neg_log_joint_single, (None, 0, 0, 0, 0)))
        args = (system, *args)
        jax.block_until_ready((E(*args), V(*args)))
        te, tv = [], []
        for _ in range(7):
            te.append(timed(E, *args, reps=1)[1])
            tv.append(timed(V, *args, reps=1)[1])
        e, v = np.median(te), np.median(tv)
        print(f"n = {3 * K}: linearisation {1e3 * e:.2f} ms, value {1e3 * v:.3f} ms, "
              f"ratio {e / v:.1f}, {load()}", flush=True)  # fmt: skip


def lazy(K: int, B: int, T: int, *bounds: int) -> None:
    _, prob, system, x0 = k100.setup(K, T, B, 42)
    canon = copy.copy(trace_numbers(ceemx.LMSmoother(), x0.dtype))
    object.__setattr__(canon, "max_steps", 0)
    programs = {}
    for form, threshold in (("eager", 10**9), ("by value", 1)):
        saved, sm.LAZY_MIN_STATES = sm.LAZY_MIN_STATES, threshold  # read while tracing
        try:
            f = jax.jit(lambda k, s, x, d: sm._smooth_batch_impl(canon, k, s, x, d, False))
            t0 = time.perf_counter()
            traced = f.trace(jnp.asarray(2, jnp.int32), system, x0, prob.data)
            t1 = time.perf_counter()
            lowered = traced.lower()
            t2 = time.perf_counter()
            programs[form] = lowered.compile()
            t3 = time.perf_counter()
        finally:
            sm.LAZY_MIN_STATES = saved
        print(f"n = {3 * K}, {form}: trace {t1 - t0:.2f} s, lower {t2 - t1:.2f} s, "
              f"compile {t3 - t2:.2f} s, {load()}", flush=True)  # fmt: skip
    for steps in bounds or (1, 2, 5, 50):
        k = jnp.asarray(steps, jnp.int32)
        ts: dict[str, list[float]] = {form: [] for form in programs}
        for _ in range(5):
            for form, f in programs.items():
                t0 = time.perf_counter()
                out = jax.block_until_ready(f(k, system, x0, prob.data))
                ts[form].append(time.perf_counter() - t0)
        print(f"n = {3 * K}, at most {steps} steps (took {int(np.max(out.iterations))}): "
              + ", ".join(f"{form} {1e3 * np.median(v):.1f} ms" for form, v in ts.items())
              + f", {load()}", flush=True)  # fmt: skip


def solve(ns: list[int]) -> None:
    T, B = 256, 2
    key = jax.random.PRNGKey(0)
    for n in ns:
        M = jax.random.normal(key, (B, T, n, n)) / n**0.5
        low = 0.3 * jax.random.normal(key, (B, T - 1, n, n)) / n**0.5
        A = blocktri.BlockTridiagonal(M @ jnp.swapaxes(M, -1, -2) + 3 * jnp.eye(n), low)
        L = jax.jit(jax.vmap(blocktri.cholesky))(A)
        b = jax.random.normal(key, (B, T, n))
        by_inv = jax.jit(jax.vmap(lambda L, b: blocktri.solve(L, b, blocktri.diagonal_inverses(L))))
        per_step = jax.jit(jax.vmap(blocktri.solve))
        r1, r2 = by_inv(L, b), per_step(L, b)
        t1 = [timed(by_inv, L, b, reps=1)[1] for _ in range(3)]
        t2 = [timed(per_step, L, b, reps=1)[1] for _ in range(3)]
        diff = float(jnp.max(jnp.abs(r1 - r2)))
        print(f"n = {n}: block inverses {min(t1):.4f} s, step by step {min(t2):.4f} s, "
              f"max difference {diff:.1e}, {load()}", flush=True)  # fmt: skip


if __name__ == "__main__":
    mode, rest = sys.argv[1], [int(a) for a in sys.argv[2:]]
    if mode == "parts":
        parts(*(rest or [100]))
    elif mode == "ratio":
        ratio(rest or [3, 6, 12, 20, 40])
    elif mode == "lazy":
        lazy(*(rest or [6, 8, 128]))
    elif mode == "solve":
        solve(rest or [9, 16, 32, 64, 128, 300])
    else:
        raise SystemExit(f"unknown mode {mode!r}: parts, ratio, lazy or solve")
