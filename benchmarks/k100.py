"""K = 100 coupled Lorenz (n = 300, ≈ 90 000 parameters): a bounded identification attempt.

Problem (the Figure-3 protocol of ``ceemx.experiments.figure3`` at a larger K): K attractors,
y = C x + v ∈ R^{3K−2} (C standard normal, known), H standard normal off the own-attractor blocks
(Frobenius norm 5), σ_v = 0.01, no process noise, T steps (RK4, dt = 0.04), B trajectories from
seed 42; θ = [σ, ρ, β, H] (3K + 9K² parameters) starts at θ·(1 + U(−0.1, 0.1)); the states start at
truth + N(0, 1). Fitted with the likelihood weighting (σ_w = σ_v = 0.01, ρ_x = 0). ε(θ) is the
paper's Eq. 14 (``ceemx.evaluation.metrics.dynamics_error``); the target is ε ≤ 1 % of the initial ε
within ``--budget`` seconds (default 600).

Methods (``--method``):

* ``alt-lbfgs`` (default, the first attempt): Algorithm 1,
  ``LMSmoother(max_steps=--smoother-steps)``
  then ``LBFGSLearner(max_steps=--lbfgs-steps)`` on (σ, ρ, β, H);
* ``alt-gncg``: the same with ``GaussNewtonCGLearner(max_steps=--gn-steps,
  cg_max_steps=--cg-steps, cg_rtol=--cg-rtol, scaling=--scaling)``;
* ``joint-mf``: ``JointLM(border="matrix-free", cg_max_steps=--cg-steps, cg_rtol=--cg-rtol,
  border_scaling=--scaling)`` through ``ceemx.fit`` (the joint LM's dense Schur complement,
  P × P, and border, B·T·n·P, cannot be held at P ≈ 90 000; the matrix-free border forms only
  the x-blocks A_b, B·T·n²).

Two drivers for the ``alt-*`` methods (``joint-mf`` always uses ``ceemx.fit``):

* ``--chunk 0`` (default): ``ceemx.fit(..., solver=ceemx.Alternating(...))`` (the library's
  Algorithm 1; from n = 150 its smoother takes two trajectories at a time,
  ``LMSmoother(batch_chunk=2)``, otherwise all B at once, so memory grows as B·T·n²);
* ``--chunk C``: the same epoch written out — ``ceemx.smooth`` on C trajectories at a time, then
  ``ceemx.learn`` on all of them (per-call timings; the run stops inside a smoothing step that
  ends past the budget).

The run stops after the first epoch that ends past the budget, or earlier when the next epoch is
not expected to fit; ε, J and the timings of every epoch are written to ``--out`` after each
epoch, so a killed run keeps what it did.

Usage::

    python benchmarks/k100.py                   # the real attempt (K = 100, T = 256, B = 16)
    python benchmarks/k100.py --chunk 2         # the same epochs written out, 2 trajectories a call
    python benchmarks/k100.py --K 20 --budget 120   # a scaled-down probe
    python benchmarks/k100.py --smoke --out x.json  # K = 4, T = 32, B = 2, 2 epochs (seconds)
    python benchmarks/k100.py --method joint-mf --K 10 --budget 150   # the matrix-free joint LM

The smoother at large state dimension, where one step goes and the two forms of its LM loop
(``python benchmarks/k100.py smoother MODE [ARGS]``; each piece compiled first, then timed, the
load printed):

* ``parts [K]`` (default 100): for one trajectory (T = 256), the linearisation of −J, the
  dynamics' Jacobians alone, the damped block Cholesky, the solve through the block inverses and
  the default solve;
* ``ratio [K ...]``: ``linearize`` against the value ``neg_log_joint_single`` (B = 4, T = 128);
* ``lazy K B T [S ...]``: the smoother's compiled kernel traced eagerly and with trial points
  judged by value (``LAZY_MIN_STATES`` set around the trace), its trace/lower/compile times, then
  both called in turn with S allowed steps (default 1, 2, 5, 50);
* ``solve [n ...]``: a vector right-hand side solved through the inverted diagonal blocks
  against per-step triangular solves (T = 256, B = 2).

Writes ``benchmarks/results/k100.json`` by default (``k100_joint_mf.json`` with
``--method joint-mf``; ``--out`` otherwise). Backs: ``benchmarks/README.md`` (the K = 100 rows)
and ``docs/decisions.md`` (the smoother's lazy form from 48 states, vector solves step by step).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.evaluation import metrics as ev  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.models import with_noise  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "results", "k100.json")
DEFAULT_OUT_JOINT_MF = os.path.join(HERE, "results", "k100_joint_mf.json")
SIGMA_V = 0.01


def rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def setup(K: int, T: int, B: int, seed: int):
    true = common.true_lorenz(K, key=jax.random.PRNGKey(4), obs_noise=SIGMA_V)
    prob = common.lorenz_problem(seed, true, B=B, T=T, sigma_w=0.0, sigma_v=SIGMA_V)
    system = with_noise(prob.init_system, 0.01, SIGMA_V)
    k_x = jax.random.fold_in(jax.random.PRNGKey(seed), 1)
    x0 = prob.states + jax.random.normal(k_x, prob.states.shape, prob.states.dtype)
    return true, prob, system, x0


# ``smoother MODE``: the smoother at large n, piece by piece.


def _load() -> str:
    return f"load {os.getloadavg()[0]:.2f}"


def _timed(f, *args, reps: int = 3) -> tuple[float, float]:
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


def _smoother_parts(K: int) -> None:
    from ceemx import lib
    from ceemx.inference.objective import linearize
    from ceemx.lib import blocktri

    _, prob, system, x0 = setup(K, 256, 1, 42)
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
        first, steady = _timed(f, *args)
        print(
            f"n = {3 * K}, {name}: first {first:.2f} s, steady {steady:.3f} s, {_load()}",
            flush=True,
        )


def _smoother_ratio(Ks: list[int]) -> None:
    from ceemx.inference.objective import linearize, neg_log_joint_single

    for K in Ks:
        _, prob, system, x0 = setup(K, 128, 4, 42)
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
            te.append(_timed(E, *args, reps=1)[1])
            tv.append(_timed(V, *args, reps=1)[1])
        e, v = np.median(te), np.median(tv)
        print(f"n = {3 * K}: linearisation {1e3 * e:.2f} ms, value {1e3 * v:.3f} ms, "
              f"ratio {e / v:.1f}, {_load()}", flush=True)  # fmt: skip


def _smoother_lazy(K: int, B: int, T: int, *bounds: int) -> None:
    import copy

    from ceemx.inference import smoother as sm
    from ceemx.lib.tree import trace_numbers

    _, prob, system, x0 = setup(K, T, B, 42)
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
              f"compile {t3 - t2:.2f} s, {_load()}", flush=True)  # fmt: skip
    for steps in bounds or (1, 2, 5, 50):
        k = jnp.asarray(steps, jnp.int32)
        ts: dict[str, list[float]] = {form: [] for form in programs}
        out = None
        for _ in range(5):
            for form, f in programs.items():
                t0 = time.perf_counter()
                out = jax.block_until_ready(f(k, system, x0, prob.data))
                ts[form].append(time.perf_counter() - t0)
        print(f"n = {3 * K}, at most {steps} steps (took {int(np.max(out.iterations))}): "
              + ", ".join(f"{form} {1e3 * np.median(v):.1f} ms" for form, v in ts.items())
              + f", {_load()}", flush=True)  # fmt: skip


def _smoother_solve(ns: list[int]) -> None:
    from ceemx.lib import blocktri

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
        t1 = [_timed(by_inv, L, b, reps=1)[1] for _ in range(3)]
        t2 = [_timed(per_step, L, b, reps=1)[1] for _ in range(3)]
        diff = float(jnp.max(jnp.abs(r1 - r2)))
        print(f"n = {n}: block inverses {min(t1):.4f} s, step by step {min(t2):.4f} s, "
              f"max difference {diff:.1e}, {_load()}", flush=True)  # fmt: skip


def smoother_profile(argv: list[str]) -> None:
    """``smoother parts|ratio|lazy|solve [INT ...]`` (see the module notes)."""
    if not argv:
        raise SystemExit("smoother MODE: parts, ratio, lazy or solve")
    mode, rest = argv[0], [int(a) for a in argv[1:]]
    if mode == "parts":
        _smoother_parts(*(rest or [100]))
    elif mode == "ratio":
        _smoother_ratio(rest or [3, 6, 12, 20, 40])
    elif mode == "lazy":
        _smoother_lazy(*(rest or [6, 8, 128]))
    elif mode == "solve":
        _smoother_solve(rest or [9, 16, 32, 64, 128, 300])
    else:
        raise SystemExit(f"unknown mode {mode!r}: parts, ratio, lazy or solve")


def main(argv=None) -> dict:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "smoother":
        smoother_profile(argv[1:])
        return {}
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--K", type=int, default=100)
    p.add_argument("--T", type=int, default=256)
    p.add_argument("--B", type=int, default=16)
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--budget", type=float, default=600.0, help="wall seconds for the epochs")
    p.add_argument("--max-epochs", type=int, default=1000)
    p.add_argument("--smoother-steps", type=int, default=1, help="LM iterations per smoothing")
    p.add_argument("--lbfgs-steps", type=int, default=150, help="L-BFGS iterations per epoch")
    p.add_argument(
        "--chunk", type=int, default=None, help="trajectories per smoothing call (0: ceemx.fit)"
    )
    p.add_argument(
        "--method",
        choices=("alt-lbfgs", "alt-gncg", "joint-mf"),
        default="alt-lbfgs",
        help="Algorithm 1 with LBFGSLearner or GaussNewtonCGLearner, or "
        "JointLM(border='matrix-free')",
    )
    p.add_argument("--gn-steps", type=int, default=10, help="LM iterations of GaussNewtonCG")
    p.add_argument("--cg-steps", type=int, default=50, help="CG bound per LM iteration")
    p.add_argument("--cg-rtol", type=float, default=1e-3, help="CG relative tolerance")
    p.add_argument(
        "--scaling", choices=("diagonal", "identity"), default="diagonal", help="θ damping scale"
    )
    p.add_argument("--smoke", action="store_true", help="K = 4, T = 32, B = 2, 2 epochs")
    p.add_argument("--out", type=str, default=None)
    args = p.parse_args(argv)
    if args.smoke:
        args.K, args.T, args.B, args.max_epochs, args.budget = 4, 32, 2, 2, 120.0
    n = 3 * args.K
    chunk = args.chunk if args.chunk is not None else 0
    if args.method == "joint-mf":
        chunk = 0
    default_out = DEFAULT_OUT_JOINT_MF if args.method == "joint-mf" else DEFAULT_OUT
    out_path = args.out if args.out else (None if args.smoke else default_out)

    t_setup = time.perf_counter()
    true, prob, system, x0 = setup(args.K, args.T, args.B, args.seed)
    P = sum(int(np.size(a)) for a in common.LORENZ_PARAMS_H(system))
    eps_cb = ev.DynamicsErrorCallback(true)
    eps0 = eps_cb.error(system)
    setup_s = time.perf_counter() - t_setup
    # ``ceemx.fit`` (``--chunk 0``) smooths in chunks of two trajectories from n = 150 (memory);
    # the manual driver's calls hold two trajectories each anyway.
    smoother = ceemx.LMSmoother(max_steps=args.smoother_steps, batch_chunk=2 if n >= 150 else None)
    if args.method == "alt-gncg":
        learner = ceemx.GaussNewtonCGLearner(
            max_steps=args.gn_steps,
            cg_max_steps=args.cg_steps,
            cg_rtol=args.cg_rtol,
            scaling=args.scaling,
        )
    else:
        learner = ceemx.LBFGSLearner(max_steps=args.lbfgs_steps)
    if args.method == "joint-mf":
        solver = ceemx.JointLM(
            border="matrix-free",
            cg_max_steps=args.cg_steps,
            cg_rtol=args.cg_rtol,
            border_scaling=args.scaling,
            rtol=0.0,
            check_identifiability=False,
        )
    else:
        solver = ceemx.Alternating(smoother=smoother, learner=learner, rtol=0.0)
    result: dict = {
        "config": {
            "K": args.K,
            "n": n,
            "m": n - 2,
            "T": args.T,
            "B": args.B,
            "P": P,
            "seed": args.seed,
            "budget_s": args.budget,
            "smoother_steps": args.smoother_steps,
            "lbfgs_steps": args.lbfgs_steps,
            "method": args.method,
            "gn_steps": args.gn_steps,
            "cg_steps": args.cg_steps,
            "cg_rtol": args.cg_rtol,
            "scaling": args.scaling,
            "driver": (
                f"ceemx.fit({type(solver).__name__})" if chunk == 0 else f"manual, chunk={chunk}"
            ),
            "weighting": "likelihood (σ_w = σ_v = 0.01, ρ_x = 0)",
            "target": "eps <= 0.01 * eps_initial",
        },
        "environment": {
            "jax": jax.__version__,
            "ceemx": ceemx.__version__,
            "cpu_count": os.cpu_count(),
            "date": time.strftime("%Y-%m-%d %H:%M"),
        },
        "setup_s": setup_s,
        "eps_initial": eps0,
        "epochs": [],
        "loadavg_start": os.getloadavg(),
    }
    print(
        f"K={args.K} (n={n}, P={P}), T={args.T}, B={args.B}; driver "
        f"{result['config']['driver']}; ε₀ = {eps0:.6g}; load {os.getloadavg()[0]:.2f}",
        flush=True,
    )

    def save():
        result["rss_max_gb"] = rss_gb()
        eps = [e["eps"] for e in result["epochs"]]
        result["eps_final"] = eps[-1] if eps else eps0
        result["eps_ratio"] = result["eps_final"] / eps0
        result["target_met"] = bool(result["eps_ratio"] <= 0.01)
        if out_path:
            os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
            with open(out_path, "w") as f:
                json.dump(result, f, indent=2)

    t0 = time.perf_counter()

    def log_epoch(epoch, sys_now, J, rec):
        eps = eps_cb.error(sys_now)
        rec = {"epoch": epoch, "eps": eps, "J": J, "wall_s": time.perf_counter() - t0, **rec}
        rec["load"] = os.getloadavg()[0]
        rec["cpu_s"] = resource.getrusage(resource.RUSAGE_SELF).ru_utime  # process CPU, cumulative
        result["epochs"].append(rec)
        print(
            f"epoch {epoch:3d}  ε = {eps:.6g} ({eps / eps0:.3%} of ε₀)  J = {J:.8g}  "
            f"epoch {rec['time']:.1f} s (smooth {rec.get('smooth_time', float('nan')):.1f}, "
            f"learn {rec.get('learn_time', float('nan')):.1f})  wall {rec['wall_s']:.1f} s  "
            f"rss {rss_gb():.2f} GB",
            flush=True,
        )
        elapsed = rec["wall_s"]
        if eps <= 0.01 * eps0:
            result["stop_reason"] = "target reached"
        elif elapsed + rec["time"] > args.budget:
            result["stop_reason"] = (
                f"another epoch of {rec['time']:.0f} s (the last one's time) would end past the "
                f"{args.budget:.0f} s budget"
            )
        else:
            result["stop_reason"] = "max_epochs"
        save()
        return result["stop_reason"] == "max_epochs"

    if chunk == 0:

        def callback(info):
            r = info.record
            keys = ("time", "smooth_time", "learn_time", "learner_steps", "trials", "damping")
            rec = {k: r[k] for k in keys if k in r}
            if not log_epoch(info.epoch, info.system, r["J"], rec):
                return False
            return None

        res = ceemx.fit(
            system,
            prob.data,
            x0,
            solver=solver,
            trainable=common.LORENZ_PARAMS_H,
            max_epochs=args.max_epochs,
            callbacks=[callback],
            progress=False,
            outliers="keep",
        )
        result["initial_J"] = res.initial_J
    else:
        states = x0
        sys_now = system
        idx = [np.arange(i, min(i + chunk, args.B)) for i in range(0, args.B, chunk)]
        for epoch in range(1, args.max_epochs + 1):
            te = time.perf_counter()
            parts, chunk_s = [], []
            for ii in idx:
                tc = time.perf_counter()
                sol = ceemx.smooth(sys_now, prob.data[ii], states[ii], smoother)
                parts.append(jax.block_until_ready(sol.states))
                chunk_s.append(time.perf_counter() - tc)
                print(f"  smoothed trajectories {ii.tolist()} in {chunk_s[-1]:.1f} s", flush=True)
                if time.perf_counter() - t0 > args.budget:
                    break
            if len(parts) < len(idx):  # the budget ran out inside the smoothing step
                result["aborted"] = {
                    "epoch": epoch,
                    "trajectories_smoothed": int(sum(len(i) for i in idx[: len(parts)])),
                    "chunk_times_s": chunk_s,
                    "wall_s": time.perf_counter() - t0,
                    "note": "budget exhausted inside the smoothing step of this epoch",
                }
                result["stop_reason"] = "budget exhausted inside the smoothing step"
                print(f"budget exhausted inside epoch {epoch}'s smoothing step", flush=True)
                save()
                break
            states = jnp.concatenate(parts, axis=0)
            ts = time.perf_counter() - te
            tl = time.perf_counter()
            sys_now, _, info = ceemx.learn(
                sys_now, states, prob.data, learner, trainable=common.LORENZ_PARAMS_H
            )
            jax.block_until_ready(sys_now)
            tl = time.perf_counter() - tl
            J = float(jnp.sum(ceemx.log_joint(sys_now, states, prob.data)))
            rec = {
                "time": time.perf_counter() - te,
                "smooth_chunk_s": chunk_s,
                "smooth_time": ts,
                "learn_time": tl,
                "learner_steps": int(info.steps),
            }
            if not log_epoch(epoch, sys_now, J, rec):
                break
    result["total_wall_s"] = time.perf_counter() - t0
    result["loadavg_end"] = os.getloadavg()
    save()
    print(
        f"ε {eps0:.6g} → {result['eps_final']:.6g} ({result['eps_ratio']:.3%}) after "
        f"{len(result['epochs'])} epochs, {result['total_wall_s']:.1f} s; target (≤ 1 %) "
        f"{'met' if result['target_met'] else 'NOT met'}; max RSS {result['rss_max_gb']:.2f} GB",
        flush=True,
    )
    if out_path:
        print(f"wrote {out_path}")
    return result


if __name__ == "__main__":
    sys.exit(0 if main() is not None else 1)
