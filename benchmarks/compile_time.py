"""Compile time and first-fit latency: where a first fit's time goes and what each compile choice
costs and saves. One subcommand per measurement, each in a fresh process::

    python benchmarks/compile_time.py nocache              # a gray-box fit, no persistent cache
    python benchmarks/compile_time.py cache DIR            # the same with the cache (run twice)
    python benchmarks/compile_time.py phases [CACHE_DIR | -]
    python benchmarks/compile_time.py one-shot [--calls 5] [--only NAME ...] [--out FILE]
    python benchmarks/compile_time.py xla-options [--calls 15] [--option NAME=VALUE]
    python benchmarks/compile_time.py joint-parts

``nocache`` / ``cache DIR``: the friction model of ``tests/test_joint_guard.py`` (Coulomb +
viscous friction, velocity hidden, 2000 samples, 30 Alternating epochs) fitted twice in one
process and its initial state estimated twice: first minus second is the compile time; ``cache``
turns JAX's persistent compilation cache on in DIR (the first run fills it, a second is warm).

``phases``: the single-Lorenz problem of ``compare_reference.py`` (seed 43, B = 4, T = 128,
explicit midpoint, σ_w = 0.1, σ_v = 0.5): one ``ceemx.fit(..., solver=ceemx.JointLM())`` in
this fresh process, then ``NSTEADY`` (default 5) more, timed (median). ``jax.monitoring`` records,
per compiled program, the seconds of tracing, lowering and XLA compilation (with a warm
persistent cache the retrieval); ``VERBOSE=1`` prints them per program, ``PROF=FILE`` writes a
cProfile of the first fit; with ``CACHE_DIR`` the persistent cache is on. ``SOLVER=alternating``
fits with ``ceemx.Alternating()`` instead, ``SOLVER=auto`` by the default path (no solver
named); ``BACKGROUND=1`` / ``0`` forces the background compilation of the epoch programs on /
off (``fit`` decides by ``compiles_ahead()`` otherwise).

``one-shot``: each case compiled twice in one process — optimised (``jit``) and one-shot
(``one_shot_jit``: LLVM -O0, one code-generation module) — then called alternately
``--calls`` times each: compile time (``lower(...).compile()``), run time (median) and the
break-even number of calls (compile saved / run time added). Cases: the initial-state estimate
of a score, the demo's data simulation, the smoother on the single-Lorenz, Figure-3, one-record
(T = 20 000) and K = 20 problems, the Schur complement and the per-trajectory −J on the
single-Lorenz and Figure-3 problems, the joint iteration. Written to
``benchmarks/results/compile_time_one_shot.json``. ``XLA_FLAGS`` must not name the flags.

``xla-options``: an XLA:CPU option (default ``xla_cpu_use_fusion_emitters=false``) as a
per-program compiler option against XLA's defaults, in one process: the Figure-3 joint iteration,
the single-Lorenz smoother and the same on one T = 10⁴ record are each compiled both ways, then
called alternately; the first call of each (compile), the median call (wall and process CPU),
the ratios and the largest difference of the outputs.

``joint-parts``: the demo-size joint iteration (six coupled Lorenz, B = 4, T = 128, 342
parameters) and its parts, each compiled alone and called 5 times: its ahead-of-time lower and
compile (wall and process CPU), the identifiability S's first call, the joint linearisation, S,
the iteration, the batched block Cholesky, its diagonal blocks' inverses, the forward half and
the whole solve with the 342 border columns, a one-column solve and Σ_b WᵀW
(``CEEMX_ONE_SHOT=0`` compiles S optimised).

Record ``uptime`` beside each run. Backs: ``benchmarks/README.md`` (compile time, first fit) and
``docs/decisions.md`` (the compile options, one-shot programs, block solves by inverted blocks).
"""

from __future__ import annotations

import argparse
import collections
import copy
import json
import os
import pathlib
import resource
import statistics
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
RESULTS_ONE_SHOT = HERE / "results" / "compile_time_one_shot.json"


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


# ``nocache`` / ``cache DIR``: a 2-state gray-box fit.


def _friction(k: float, c: float, fc: float):
    """m ẍ = u − k x − c ẋ − F_c tanh(ẋ/ε), m = 1; process noise (1e-4, 1e-3), observation 1e-3."""
    import jax
    import jax.numpy as jnp

    import ceemx

    class Friction(ceemx.AbstractContinuousSystem):
        k: jax.Array = ceemx.param(positive=True)
        c: jax.Array = ceemx.param(positive=True)
        fc: jax.Array = ceemx.param(positive=True)

        @property
        def state_dim(self) -> int:
            return 2

        @property
        def obs_dim(self) -> int:
            return 1

        @property
        def control_dim(self) -> int:
            return 1

        def vector_field(self, x, u, t):
            pos, vel = x
            return jnp.stack(
                [vel, u[0] - self.k * pos - self.c * vel - self.fc * jnp.tanh(vel / 0.01)]
            )

        def observe(self, x, u, t):
            return x[:1]

    return Friction(
        k=jnp.asarray(k),
        c=jnp.asarray(c),
        fc=jnp.asarray(fc),
        dt=0.01,
        process_noise=jnp.array([1e-4, 1e-3]),
        obs_noise=1e-3,
    )


def gray_box(mode: str, argv: list[str]) -> None:
    """``nocache`` / ``cache [DIR]``: time the fits and the initial-state estimation."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import ceemx

    if mode == "cache":
        print("cache folder:", ceemx.enable_compilation_cache(argv[0] if argv else None))
    T = 2000
    u = np.repeat(np.random.default_rng(0).normal(0, 2.0, (T // 50, 1)), 50, axis=0)[None]
    _, data = ceemx.simulate(
        _friction(4.0, 0.5, 0.3), jax.random.PRNGKey(0), jnp.zeros((1, 2)), T, u=jnp.asarray(u)
    )
    guess = _friction(2.0, 1.0, 0.1)
    t = [time.perf_counter()]
    result = ceemx.fit(guess, data, solver=ceemx.Alternating(), max_epochs=30)
    t.append(time.perf_counter())
    ceemx.fit(guess, data, solver=ceemx.Alternating(), max_epochs=30)
    t.append(time.perf_counter())
    ceemx.estimate_initial_state(result.system, data, 50)
    t.append(time.perf_counter())
    ceemx.estimate_initial_state(result.system, data, 50)
    t.append(time.perf_counter())
    d = np.diff(t)
    print(
        f"{mode}: fit first {d[0]:.2f} s, second {d[1]:.2f} s (compile ≈ {d[0] - d[1]:.2f} s); "
        f"initial state first {d[2]:.2f} s, second {d[3]:.3f} s"
    )


# ``phases``: the programs of a first JointLM fit.


def phases(argv: list[str]) -> None:
    """``phases [CACHE_DIR | -]``: a first fit's programs and their trace/lower/compile times."""
    t00 = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    from jax._src import monitoring

    events = []
    monitoring.register_event_duration_secs_listener(
        lambda event, duration, **kw: events.append(
            (event.rsplit("/", 1)[-1], kw.get("fun_name", "?"), duration)
        )
    )
    import jax.numpy as jnp
    import numpy as np

    import ceemx
    from ceemx.experiments import common
    from ceemx.identification.fitting import start

    if os.environ.get("BACKGROUND") in ("0", "1"):  # the name the fit's start calls
        start.compiles_ahead = lambda: os.environ["BACKGROUND"] == "1"
    if argv and argv[0] != "-":
        ceemx.enable_compilation_cache(argv[0])
    t_import = time.perf_counter() - t00

    true = common.true_lorenz(
        1, key=jax.random.PRNGKey(4), m=2, coupling=False, integrator="midpoint"
    )
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

    named = os.environ.get("SOLVER")
    # SOLVER=auto: no solver named, the default path (its noise stage and Laplace finish)
    solver = {"auto": {}, "alternating": {"solver": ceemx.Alternating()}}.get(
        named, {"solver": ceemx.JointLM()}
    )

    def one():
        r = ceemx.fit(
            guess,
            ceemx.Trajectories(y),
            trainable=common.LORENZ_PARAMS,
            progress=False,
            **solver,
        )
        r.states.block_until_ready()
        return r

    events.clear()
    profile = os.environ.get("PROF")
    prof = None
    if profile:
        import cProfile

        prof = cProfile.Profile()
        prof.enable()
    t, c = time.perf_counter(), _cpu()
    res = one()
    first, first_cpu = time.perf_counter() - t, _cpu() - c
    if prof is not None:
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


# ``one-shot``: optimised against one-shot programs.


def _one_shot_cases() -> dict:
    import jax
    import jax.numpy as jnp

    import ceemx
    from ceemx.experiments import common
    from ceemx.identification import schur
    from ceemx.identification.problem import FitProblem, per_trajectory_nll
    from ceemx.identification.solvers import joint
    from ceemx.inference import smoother as sm
    from ceemx.lib.tree import trace_numbers

    def lorenz(K: int, B: int, T: int, coupling: bool):
        true = common.true_lorenz(
            K, key=jax.random.PRNGKey(4), coupling=coupling, integrator="midpoint"
        )
        p = common.lorenz_problem(43, true, B=B, T=T, sigma_w=0.1, sigma_v=0.5, coupling=coupling)
        system = ceemx.models.system.with_noise(p.init_system, process_noise=0.1, obs_noise=0.5)
        return system, p.data, p.states

    def smoother_case(K, B, T, coupling=False):
        system, data, states = lorenz(K, B, T, coupling)
        solver = trace_numbers(ceemx.LMSmoother(max_steps=20), states.dtype)
        steps = jnp.asarray(20, jnp.int32)
        canonical = copy.copy(solver)
        object.__setattr__(canonical, "max_steps", 0)
        x0 = states + 0.5
        return sm._smooth_batch_impl, (canonical, steps, system, x0, data, False)

    def problem_case(K, B, T, fn, coupling=False):
        system, data, states = lorenz(K, B, T, coupling)
        problem, theta = FitProblem.create(system, data)
        weights = jnp.ones((B,), states.dtype)
        if fn == "schur":
            return schur.schur_complement.__wrapped__, (problem, theta, states, weights)
        if fn == "nll":
            return per_trajectory_nll.__wrapped__, (problem, theta, states)
        opts = trace_numbers(ceemx.JointLM(), states.dtype)
        lam = jnp.asarray(opts.damping, states.dtype)
        return joint._iteration.__wrapped__, (opts, problem, weights, theta, states, lam)

    def initial_state_case(K, B, T):
        from ceemx.evaluation import initial_state, simulation

        system, data, states = lorenz(K, B, T, False)
        solver = trace_numbers(ceemx.LMSmoother(), states.dtype)
        weak = ceemx.models.system.with_noise(system, process_noise=jnp.asarray(1.0, states.dtype))
        system, weak = simulation.strongly_typed((system, weak))
        return initial_state.initial_state_batch.__wrapped__, (
            solver,
            system,
            weak,
            data,
            None,
            True,
        )

    def simulate_case(K, B, T):
        from ceemx.data import trajectories

        true = common.true_lorenz(K, key=jax.random.PRNGKey(4), coupling=True)  # RK4, as the demo
        x0 = jnp.ones((B, true.state_dim))
        u = jnp.zeros((B, T, 0))
        fn = trajectories._simulate.__wrapped__
        return fn, (true, jax.random.PRNGKey(0), x0, u, None, true.obs_noise)

    return {
        "smooth_lorenz": lambda: smoother_case(1, 4, 128),
        "smooth_fig3": lambda: smoother_case(6, 8, 128, True),
        "smooth_long": lambda: smoother_case(1, 1, 20000),
        "smooth_k20": lambda: smoother_case(20, 2, 128, True),
        "schur_lorenz": lambda: problem_case(1, 4, 128, "schur"),
        "schur_fig3": lambda: problem_case(6, 8, 128, "schur", True),
        "nll_lorenz": lambda: problem_case(1, 4, 128, "nll"),
        "nll_fig3": lambda: problem_case(6, 8, 128, "nll", True),
        "iteration_lorenz": lambda: problem_case(1, 4, 128, "iteration"),
        "initial_state_lorenz": lambda: initial_state_case(1, 4, 50),
        "simulate_demo": lambda: simulate_case(6, 4, 128),
    }


def one_shot(argv: list[str]) -> None:
    """``one-shot``: compile and run time of each case, optimised and one-shot."""
    ap = argparse.ArgumentParser(prog="compile_time.py one-shot")
    ap.add_argument("--calls", type=int, default=5)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--out", default=str(RESULTS_ONE_SHOT))
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from ceemx.infra.compilation import jit, one_shot_jit

    out = {"load_before": os.getloadavg()[0], "cases": {}}
    for name, make in _one_shot_cases().items():
        if args.only and name not in args.only:
            continue
        fn, fargs = make()
        compiled, compile_s = {}, {}
        for variant in ("optimised", "one_shot"):
            f = one_shot_jit(fn) if variant == "one_shot" else jit(fn)
            t = time.perf_counter()
            compiled[variant] = f.lower(*fargs).compile()
            compile_s[variant] = time.perf_counter() - t
        runs = {v: [] for v in compiled}
        for _ in range(args.calls):
            for v, c in compiled.items():
                t = time.perf_counter()
                jax.block_until_ready(c(*fargs))
                runs[v].append(time.perf_counter() - t)
        run_s = {v: statistics.median(r) for v, r in runs.items()}
        extra = run_s["one_shot"] - run_s["optimised"]
        saved = compile_s["optimised"] - compile_s["one_shot"]
        row = {
            "compile_s": compile_s,
            "run_s": run_s,
            "run_ratio": run_s["one_shot"] / run_s["optimised"],
            "break_even_calls": saved / extra if extra > 0 else float("inf"),
        }
        out["cases"][name] = row
        print(
            f"{name:18s} compile {compile_s['optimised']:6.2f} → {compile_s['one_shot']:6.2f} s   "
            f"run {run_s['optimised'] * 1e3:9.2f} → {run_s['one_shot'] * 1e3:9.2f} ms "
            f"({row['run_ratio']:.2f}×)   break-even {row['break_even_calls']:.0f} calls",
            flush=True,
        )
    out["load_after"] = os.getloadavg()[0]
    print(f"load {out['load_before']:.2f} → {out['load_after']:.2f}")
    pathlib.Path(args.out).write_text(json.dumps(out, indent=1))


# ``xla-options``: the steady-state cost of an XLA:CPU option.


def _ab(name, raw, args, options, calls):
    import equinox as eqx
    import jax
    import numpy as np

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


def xla_options(argv: list[str]) -> None:
    """``xla-options``: an XLA:CPU option against the defaults, A/B in one process."""
    ap = argparse.ArgumentParser(prog="compile_time.py xla-options")
    ap.add_argument("--calls", type=int, default=15)
    ap.add_argument("--option", default="xla_cpu_use_fusion_emitters=false")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import ceemx
    from ceemx.experiments import common, figure3
    from ceemx.identification.problem import FitProblem
    from ceemx.identification.solvers import joint
    from ceemx.inference import smoother
    from ceemx.lib.tree import trace_numbers
    from ceemx.models import with_noise

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
    _ab(
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
    _ab(
        "lorenz_smoother",
        smoother._smooth_batch_impl,
        (canonical, steps, s1, x0 + 0.5, p.data, False),
        options,
        args.calls * 3,
    )
    # One long record (T = 10⁴): the smoother's scans dominate, not the dense products.
    pl = common.lorenz_problem(43, true, B=1, T=10_000, sigma_w=0.1, sigma_v=0.5, coupling=False)
    xl = jnp.zeros(pl.states.shape, pl.states.dtype) + pl.states
    _ab(
        "lorenz_smoother_T10000",
        smoother._smooth_batch_impl,
        (canonical, steps, s1, xl + 0.5, pl.data, False),
        options,
        max(3, args.calls // 3),
    )
    print("load", os.getloadavg())


# ``joint-parts``: the demo-size joint iteration and its parts.


def joint_parts(argv: list[str]) -> None:
    """``joint-parts``: each part of the demo-size joint iteration compiled alone, then timed."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import ceemx
    from ceemx.experiments import common
    from ceemx.identification import schur
    from ceemx.identification.initialize import warm_start
    from ceemx.identification.problem import FitProblem
    from ceemx.identification.solvers import joint
    from ceemx.lib.arrowhead import factor, schur_terms
    from ceemx.lib.blocktri import cholesky, diagonal_inverses, forward_solve, solve
    from ceemx.lib.tree import trace_numbers
    from ceemx.models import with_noise

    def timeit(name, f, n=5):
        jax.block_until_ready(f())
        ts = []
        for _ in range(n):
            t = time.perf_counter()
            jax.block_until_ready(f())
            ts.append(time.perf_counter() - t)
        print(f"{name:28s} {np.median(ts) * 1e3:8.1f} ms  (min {min(ts) * 1e3:.1f})", flush=True)

    print("load", os.getloadavg())
    true = common.true_lorenz(6, key=jax.random.PRNGKey(4), obs_noise=0.01)
    pb = common.lorenz_problem(0, true, B=4, T=128, sigma_w=0.0, sigma_v=0.01, coupling=True)
    system = with_noise(pb.init_system, 0.01, 0.01)
    problem, theta = FitProblem.create(system, pb.data, trainable=common.LORENZ_PARAMS_H)
    x = warm_start(system, pb.data)
    w = jnp.ones((4,))
    solver = trace_numbers(ceemx.JointLM(), x.dtype)
    lam = jnp.asarray(solver.damping, x.dtype)
    t, c = time.perf_counter(), _cpu()
    lowered = joint._iteration.lower(solver, problem, w, theta, x, lam)
    t1, c1 = time.perf_counter(), _cpu()
    lowered.compile()
    t2, c2 = time.perf_counter(), _cpu()
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


SUBCOMMANDS = {
    "nocache": lambda argv: gray_box("nocache", argv),
    "cache": lambda argv: gray_box("cache", argv),
    "phases": phases,
    "one-shot": one_shot,
    "xla-options": xla_options,
    "joint-parts": joint_parts,
}


def main(argv: list[str]) -> None:
    """Run the subcommand ``argv[1]`` (default ``nocache``) with the rest of ``argv``."""
    name = argv[1] if len(argv) > 1 else "nocache"
    if name not in SUBCOMMANDS:
        raise SystemExit(__doc__)
    SUBCOMMANDS[name](argv[2:])


if __name__ == "__main__":
    main(sys.argv)
