"""Scaling of ceemx on coupled Lorenz problems: smoothing iterations, FLOP bound, fit iterations.

Backs: ``benchmarks/README.md`` (smoother scaling, the FLOP bound, long records; the default
grid plus the pinned K sweep in ``benchmarks/results/scaling.json``, the long records in
``scaling_long.json``), ``README.md`` and ``docs/results.md`` (smoother scaling).

What is measured (float64, JAX on CPU):

1. **Smoothing** (``ceemx.smooth`` with ``LMSmoother(max_steps=s, rtol=0, atol=0)``, exactly ``s``
   LM iterations, checked from ``sol.iterations``): time per LM iteration swept over T, B and
   K (n = 3K, m = 3K − 2), each case in a fresh Python process. Compile time = first call − median
   steady call; ≥ 3 steady calls; the 1-min load average is recorded per case. Log–log slopes of
   the time per iteration against T, B and n.
2. **FLOP bound** of one smoothing LM iteration, counted analytically from what the code does
   (``ceemx.inference.objective.linearize``, ``ceemx.lib.blocktri``; see :func:`smoother_flops`),
   against a
   peak measured on this machine (a large float64 matmul in JAX): achieved GFLOP/s and the ratio
   ``time / (bound / peak)``. Target: ratio ≤ 5 at n ≥ 18.
3. **Fit iterations**: one ``JointLM`` iteration and one Algorithm-1 epoch (``Alternating``) with
   the LM learner and with the L-BFGS learner, vs T and K (K ≤ 10), compile apart (first epoch −
   median of the later ones, from the history's ``time``), a fresh process per (T, K).

4. **Long records** (``--only long``): one record of the mass–spring–damper of
   ``benchmarks/laplace_long_record.py`` (n = 2, m = 1, dt 0.1, foh, 2 RK4 substeps) for T from
   10³ to 10⁵ (log spaced), each (T, method) in a fresh process: smoothing
   (``ceemx.smooth``, 5 LM iterations per call at the start θ), a ``JointLM`` fit and a
   ``LaplaceEM(acceleration="quasi_newton", coarse_start=None)`` fit with learned noise (both
   to convergence from the same start, as ``laplace_long_record.py``; an iteration of it is one
   E-step and one gradient of Q, so its time per epoch is the Laplace E-step's and M-step's
   scaling; without the coarse start, whose epochs on part of the record are not in it). Steady
   time per call and per iteration/epoch (median of ≥ 3 calls
   after a first, compiling one; compile = first − steady), peak memory of the process
   (``ru_maxrss``) beside the same process's high-water mark before the first call, the steady
   calls' own peak (the high-water mark reset after the first call, whose peak is the
   compiler's), and log–log fits (slope, intercept, R²) of the time per iteration (all T and the
   two largest) and of the memory increments against T, written to
   ``benchmarks/results/scaling_long.json``.

The K = 100 identification attempt is ``benchmarks/k100.py`` (``--k100`` here runs it).

Usage::

    python benchmarks/scaling.py                      # default grid, ≈ 12–15 min on 2 cores
    python benchmarks/scaling.py --quick              # ≈ 6 min under load
    python benchmarks/scaling.py --smoke --out x.json # seconds per case, a few tiny cases
    python benchmarks/scaling.py --only smooth        # or: fit
    python benchmarks/scaling.py --only long          # long records, T = 10³…10⁵ (≈ 10 min)
    python benchmarks/scaling.py --grid b8 --out x.json  # the first smoother sweep (≈ 5 min)
    taskset -c 0 python benchmarks/scaling.py --only smooth --sweeps K \
        --variant pinned_one_core --out benchmarks/results/scaling.json  # add a pinned K sweep
    python benchmarks/scaling.py --k100 [k100 options]  # = python benchmarks/k100.py ...

Writes ``--out`` (default ``benchmarks/results/scaling.json`` for the default and ``--quick``
grids, ``benchmarks/results/scaling_long.json`` for ``--only long``; no default with ``--smoke``
or ``--grid b8``).

The ``b8`` grid is the first smoother sweep: T ∈
{128, …, 4096} and B ∈ {1, …, 64} around T = 128, B = 8, K = 6, and K ∈ {1, 2, 5, 10, 20} at
T = 128, B = 8; 5 LM iterations per call at every n (``steps_for`` is not used), smoothing only.

On a small machine shared with other jobs, XLA-CPU's intra-op thread hand-offs can stall for a
scheduler time slice (≈ 8 ms) per small linear-algebra call, making some block sizes 10–1000×
slower at random; pinning the process to one core (``taskset -c 0``) removes the stalls, so the
pinned K sweep is the one to read the FLOP ratios from on such a machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.systems import (  # noqa: E402
    CoupledLorenz,
    initial_states,
    random_coupling,
    random_observation_matrix,
)

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "results", "scaling.json")
DEFAULT_LONG_OUT = os.path.join(HERE, "results", "scaling_long.json")
#: T of the long-record sweep (``--only long``) per grid
LONG_T = {
    "default": [1000, 3162, 10000, 31623, 100000],
    "quick": [1000, 10000, 100000],
    "smoke": [300, 1000],
    "b8": [],
}
LONG_METHODS = ("smooth", "joint_lm", "laplace_em_qn")
LONG_SMOOTH_STEPS = 5

# --- grids ------------------------------------------------------------------------------------
# Each sweep: (variable, values, base case). The K sweep uses a small T·B so that K = 100 fits.
GRIDS = {
    "default": {
        "smooth": [
            ("T", [128, 512, 2048, 8192], {"T": 128, "B": 8, "K": 6}),
            ("B", [1, 4, 16, 64, 256], {"T": 128, "B": 8, "K": 6}),
            ("K", [1, 2, 6, 10, 20, 40, 100], {"T": 128, "B": 2, "K": 6}),
        ],
        "fit": {"B": 4, "cases": [(128, 2), (128, 6), (128, 10), (256, 6), (512, 6)]},
        "fit_epochs": 4,
    },
    "quick": {
        "smooth": [
            ("T", [128, 512, 2048], {"T": 128, "B": 8, "K": 6}),
            ("B", [1, 8, 64], {"T": 128, "B": 8, "K": 6}),
            ("K", [1, 6, 20, 40], {"T": 128, "B": 2, "K": 6}),
        ],
        "fit": {"B": 4, "cases": [(128, 2), (128, 6), (256, 6)]},
        "fit_epochs": 3,
    },
    "smoke": {
        "smooth": [
            ("T", [32, 64], {"T": 32, "B": 2, "K": 1}),
            ("B", [1, 2], {"T": 32, "B": 2, "K": 1}),
            ("K", [1, 2], {"T": 32, "B": 2, "K": 1}),
        ],
        "fit": {"B": 2, "cases": [(32, 2)]},
        "fit_epochs": 3,
    },
    # The first smoother sweep (formerly smoother_scaling.py): B = 8 in every sweep, K ≤ 20,
    # a fixed 5 LM iterations per call, no fits.
    "b8": {
        "smooth": [
            ("T", [128, 256, 512, 1024, 2048, 4096], {"T": 128, "B": 8, "K": 6}),
            ("B", [1, 2, 4, 8, 16, 32, 64], {"T": 128, "B": 8, "K": 6}),
            ("K", [1, 2, 5, 10, 20], {"T": 128, "B": 8, "K": 6}),
        ],
        "steps": 5,
        "fit": None,
        "fit_epochs": 0,
    },
}
PERTURBATION = 0.1  # x_init = truth + PERTURBATION · N(0, 1)


# --- problem ----------------------------------------------------------------------------------


def make_problem(T: int, B: int, K: int, seed: int = 0):
    """Truth, observations and a perturbed initial guess for one coupled-Lorenz case.

    ``random_coupling(K)`` (Frobenius norm 5), ``random_observation_matrix(K)`` (m = 3K − 2),
    ``initial_states(B, K)``; σ, ρ, β = 10, 28, 8/3, dt = 0.04, noise scales 0.01 / 0.01; the
    data simulated without process noise; ``x_init = truth + PERTURBATION · N(0, 1)``, the same
    size in every case so that the iterations do comparable work.
    """
    kH, kC, kx0, ksim, kpert = jax.random.split(jax.random.PRNGKey(seed), 5)
    H = random_coupling(kH, K)
    C = random_observation_matrix(kC, K)
    ones = jnp.ones(K, jnp.float64)
    system = CoupledLorenz(
        10.0 * ones, 28.0 * ones, (8.0 / 3.0) * ones, C, H=H, process_noise=0.01, obs_noise=0.01
    )
    x0 = initial_states(kx0, B, K)
    truth, data = ceemx.simulate(system, ksim, x0, T, process_noise=False)
    x_init = truth + PERTURBATION * jax.random.normal(kpert, truth.shape, truth.dtype)
    return system, data, jax.block_until_ready(x_init)


def slope(xs, ys) -> float:
    """Least-squares slope of log y against log x."""
    return float(np.polyfit(np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float)), 1)[0])


def loglog_fit(xs, ys) -> dict[str, float]:
    """Least-squares line through (log x, log y): slope, intercept and R²."""
    lx, ly = np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float))
    b, a = np.polyfit(lx, ly, 1)
    resid = ly - (a + b * lx)
    ss = float(np.sum((ly - ly.mean()) ** 2))
    return {
        "slope": float(b),
        "intercept": float(a),
        "r2": 1.0 - float(np.sum(resid**2)) / ss if ss > 0 else float("nan"),
    }


def steps_for(n: int) -> int:
    """LM iterations per timed call: fewer for large n (one iteration at n = 300 is seconds)."""
    return 5 if n < 60 else (2 if n <= 120 else 1)


# --- FLOP count -------------------------------------------------------------------------------


def smoother_flops(n: int, m: int) -> dict[str, float]:
    """Floating-point operations per trajectory-step of the smoother, counted from the code.

    One LM iteration (``ceemx.lib.lm.levenberg_marquardt`` body) = one damped solve + one
    evaluation (linearisation) at the trial point + the model's quadratic form. Per time step:

    * block Cholesky (``blocktri.cholesky``): ``L_low = A_low L_prev⁻ᵀ`` (triangular solve with n
      right-hand sides) n³, ``L_low L_lowᵀ`` as a full matmul 2n³, ``cholesky`` n³/3;
    * ``blocktri.solve``: per step ``L_low y`` (2n²) + a triangular solve (n²), forward and
      backward: 6n²; the quadratic form ``blocktri.matvec``: 6n²;
    * forming the Gauss–Newton blocks (``objective.linearize``; S are the noise models' square-root
      curvatures, dense n×n / m×m diagonal matrices): ``Sv G`` 2m²n, ``Sw F`` 2n³, ``(SG)ᵀSG``
      2mn², ``(SF)ᵀSF`` 2n³, ``SwᵀSw`` 2n³, ``SwᵀSF`` 2n³, gradients 2mn + 2n²;
    * the Jacobians themselves: F by ``jacfwd`` through 4 RK4 stages, each multiplying the n×n
      coupling by n tangents: 8n³; G by ``jacrev`` of ``C x``: 2m²n.

    The count multiplies by the dense S; the library scales rows for diagonal noise instead, so
    ``forming`` overstates its work on these (diagonal-noise) problems.

    Returns a dict of per-trajectory-step counts: ``iteration`` (Cholesky + solves + quad +
    forming: the dense linear algebra of one iteration as the code does it — the bound the
    target is checked against), ``jacobians`` (per linearisation), ``forming`` (per
    linearisation), and ``minimal`` (the algorithm's irreducible linear algebra per iteration:
    potrf n³/3 + trsm n³ + syrk n³ for the Schur update, FᵀWF as a syrk n³ with diagonal W,
    GᵀWG m n², solves 6n²).
    """
    chol = n**3 + 2 * n**3 + n**3 / 3
    solves = 6 * n**2 + 6 * n**2
    forming = 2 * m * m * n + 8 * n**3 + 2 * m * n * n + 2 * m * n + 2 * n**2
    jac = 8 * n**3 + 2 * m * m * n
    minimal = n**3 / 3 + n**3 + n**3 + n**3 + m * n * n + 6 * n**2
    return {
        "cholesky": chol,
        "solves": solves,
        "forming": forming,
        "jacobians": jac,
        "iteration": chol + solves + forming,
        "minimal": minimal,
    }


def call_flops(T: int, B: int, n: int, m: int, steps: int) -> dict[str, float]:
    """FLOPs of one ``smooth`` call of ``steps`` iterations: each iteration plus the initial
    linearisation (``levenberg_marquardt`` evaluates the start point once)."""
    f = smoother_flops(n, m)
    N = B * T
    return {
        "bound": N * (steps * f["iteration"] + f["forming"]),
        "with_jacobians": N
        * (steps * (f["iteration"] + f["jacobians"]) + f["forming"] + f["jacobians"]),
        "minimal": N * steps * f["minimal"],
    }


def measure_peak(sizes=(1024, 2048), repeats: int = 5) -> dict:
    """Float64 matmul rate of this machine in JAX (best of ``repeats`` per size), GFLOP/s."""
    out = {}
    for s in sizes:
        a = jax.random.normal(jax.random.PRNGKey(0), (s, s), jnp.float64)
        b = jax.random.normal(jax.random.PRNGKey(1), (s, s), jnp.float64)
        f = jax.jit(jnp.matmul)
        f(a, b).block_until_ready()
        best = _best_time(f, (a, b), repeats)
        out[str(s)] = 2 * s**3 / best / 1e9
    # Small batched blocks, as the smoother sees them (a roofline for its block shapes).
    small = {}
    for n, batch in ((18, 4096), (60, 512), (300, 16)):
        a = jax.random.normal(jax.random.PRNGKey(2), (batch, n, n), jnp.float64)
        f = jax.jit(jnp.matmul)
        f(a, a).block_until_ready()
        best = _best_time(f, (a, a), repeats)
        small[str(n)] = 2 * batch * n**3 / best / 1e9
    return {
        "matmul_gflops": out,
        "peak_gflops": max(out.values()),
        "batched_small_matmul_gflops": small,
        "loadavg_1min": os.getloadavg()[0],
    }


def _best_time(fn, args, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args).block_until_ready()
        best = min(best, time.perf_counter() - t0)
    return best


# --- workers (run in a fresh process) -----------------------------------------------------------


def smooth_case(T: int, B: int, K: int, steps: int, repeats: int, min_time: float) -> dict:
    """One smoothing case in this process (see the module docstring)."""
    load0 = os.getloadavg()[0]
    system, data, x_init = make_problem(T, B, K)
    solver = ceemx.LMSmoother(max_steps=steps, rtol=0.0, atol=0.0)

    def call():
        t0 = time.perf_counter()
        sol = ceemx.smooth(system, data, x_init, solver)
        jax.block_until_ready(sol)
        return time.perf_counter() - t0, sol

    first, sol = call()
    iters = np.asarray(sol.iterations)
    if not np.all(iters == steps):
        raise RuntimeError(f"T={T} B={B} K={K}: expected {steps} iterations, got {iters.tolist()}")
    if not np.all(np.isfinite(np.asarray(sol.objective))):
        raise RuntimeError(f"T={T} B={B} K={K}: non-finite objective")
    runs: list[float] = []
    while len(runs) < repeats or (sum(runs) < min_time and len(runs) < 20):
        runs.append(call()[0])
    steady = statistics.median(runs)
    n, m = 3 * K, 3 * K - 2
    return {
        "T": T,
        "B": B,
        "K": K,
        "n": n,
        "m": m,
        "iterations": steps,
        "first_call_s": first,
        "steady_call_s": steady,
        "steady_runs_s": runs,
        "compile_s": first - steady,
        "per_iter_s": steady / steps,
        "per_iter_min_s": min(runs) / steps,
        "per_iter_per_traj_step_s": steady / steps / (B * T),
        "flops_call": call_flops(T, B, n, m, steps),
        "loadavg_1min": [load0, os.getloadavg()[0]],
    }


def fit_case(T: int, K: int, B: int, epochs: int) -> dict:
    """JointLM iterations and Algorithm-1 epochs (LM and L-BFGS learners) on one (T, K) problem."""
    from ceemx.experiments import common
    from ceemx.models import with_noise

    true = common.true_lorenz(K, key=jax.random.PRNGKey(4), obs_noise=0.01)
    prob = common.lorenz_problem(42, true, B=B, T=T, sigma_w=0.0, sigma_v=0.01, coupling=True)
    system = with_noise(prob.init_system, 1.0, 1.0)  # the paper's Figure-3 weighting
    rho_x = 0.5 * 0.01**2
    x0 = prob.states + jax.random.normal(jax.random.PRNGKey(1), prob.states.shape)
    never = {"rtol": 0.0, "atol": 0.0}  # run all epochs (negative tolerances are refused)
    solvers = {
        "joint": ceemx.JointLM(rho_x=rho_x, **never),
        "alternate_lm": ceemx.Alternating(
            smoother=ceemx.LMSmoother(rho_x=rho_x), learner=ceemx.LMLearner(), **never
        ),
        "alternate_lbfgs": ceemx.Alternating(
            smoother=ceemx.LMSmoother(rho_x=rho_x),
            learner=ceemx.LBFGSLearner(max_steps=100),
            **never,
        ),
    }
    P = sum(int(np.size(a)) for a in common.LORENZ_PARAMS_H(system))
    out = {"T": T, "K": K, "B": B, "n": 3 * K, "m": 3 * K - 2, "P": P, "methods": {}}
    for name, solver in solvers.items():
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        res = ceemx.fit(
            system,
            prob.data,
            x0,
            solver=solver,
            trainable=common.LORENZ_PARAMS_H,
            max_epochs=epochs,
            progress=False,
            outliers="keep",
        )
        wall = time.perf_counter() - t0
        times = [h["time"] for h in res.history]
        steady = statistics.median(times[1:]) if len(times) > 1 else float("nan")
        rec = {
            "epochs": len(times),
            "epoch_times_s": times,
            "first_epoch_s": times[0],
            "steady_epoch_s": steady,
            "compile_s": times[0] - steady,
            "fit_wall_s": wall,
            "loadavg_1min": [load0, os.getloadavg()[0]],
        }
        for key in ("smooth_time", "learn_time", "learner_steps", "smoother_steps"):
            if key in res.history[0]:
                rec[key] = [h[key] for h in res.history]
        out["methods"][name] = rec
    return out


def _maxrss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def _status_mb(field: str) -> float:
    """``VmRSS`` / ``VmHWM`` of this process in MB (Linux ``/proc/self/status``)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return float(line.split()[1]) / 1024.0
    return float("nan")


def _reset_peak_mb() -> float:
    """Return freed heap to the OS, reset the peak RSS to the current RSS; the current RSS (MB).

    After the first (compiling) call the high-water mark holds the compiler's peak, which does not
    depend on T; resetting it (``/proc/self/clear_refs``, Linux ≥ 4.0) leaves the steady calls'
    own peak — the memory the computation needs — to be read from ``VmHWM`` afterwards.
    """
    import ctypes

    ctypes.CDLL("libc.so.6").malloc_trim(0)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    return _status_mb("VmRSS")


def long_case(T: int, method: str, repeats: int) -> dict:
    """One long-record case (T, method) in this process (module docstring, item 4)."""
    sys.path.insert(0, HERE)
    import laplace_long_record as llr

    start, data = llr.problem(T)
    jax.block_until_ready(data)
    base_mb = _maxrss_mb()
    load0 = os.getloadavg()[0]
    out: dict = {"T": T, "method": method}
    if method == "smooth":
        x_init = jnp.zeros((1, T, start.state_dim), data.y.dtype)
        solver = ceemx.LMSmoother(max_steps=LONG_SMOOTH_STEPS, rtol=0.0, atol=0.0)

        def call():
            t0 = time.perf_counter()
            sol = jax.block_until_ready(ceemx.smooth(start, data, x_init, solver))
            return time.perf_counter() - t0, int(np.max(np.asarray(sol.iterations))), None
    else:
        # the time per epoch is the measure here: without the coarse start (whose epochs on the
        # first 10 000 samples the history does not count), as before it existed
        fitter = llr.METHODS["laplace_em_qn_whole" if method == "laplace_em_qn" else method]

        def call():
            t0 = time.perf_counter()
            res = fitter(start, data)
            wall = time.perf_counter() - t0
            est = {"k": float(res.system.k), "c": float(res.system.c)}
            if method.startswith("laplace_em"):
                est["sigma_w"] = float(np.ravel(res.system.process_noise.std())[0])
                est["sigma_v"] = float(np.ravel(res.system.obs_noise.std())[0])
                est["log_evidence"] = res.history[-1].get("log_evidence")
            return wall, len(res.history), est

    first, iters0, est = call()
    first_mb = _maxrss_mb()
    steady_base_mb = _reset_peak_mb()
    runs, per_iter, iters = [], [], []
    for _ in range(max(repeats, 3)):
        wall, it, est = call()
        runs.append(wall)
        iters.append(it)
        per_iter.append(wall / max(it, 1))
    steady = statistics.median(runs)
    out.update(
        {
            "first_call_s": first,
            "steady_call_s": steady,
            "steady_runs_s": runs,
            "compile_s": first - steady,
            "iterations": iters,
            "per_iter_s": statistics.median(per_iter),
            "per_iter_per_step_us": 1e6 * statistics.median(per_iter) / T,
            "estimates": est,
            "baseline_rss_mb": base_mb,
            "peak_rss_after_first_mb": first_mb,
            "peak_rss_mb": _maxrss_mb(),
            "peak_increment_mb": _maxrss_mb() - base_mb,
            "steady_base_rss_mb": steady_base_mb,
            "steady_peak_increment_mb": _status_mb("VmHWM") - steady_base_mb,
            "loadavg_1min": [load0, os.getloadavg()[0]],
        }
    )
    return out


def long_table(rows: list[dict]) -> str:
    lines = [
        "| method | T | steady call (s) | iterations | per iteration (ms) | per iter·step (µs) "
        "| compile (s) | peak RSS (MB) | increment (MB) | steady increment (MB) | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['T']} | {r['steady_call_s']:.3f} | {r['iterations'][0]} "
            f"| {1e3 * r['per_iter_s']:.1f} | {r['per_iter_per_step_us']:.2f} "
            f"| {r['compile_s']:.1f} | {r['peak_rss_mb']:.0f} | {r['peak_increment_mb']:.0f} "
            f"| {r.get('steady_peak_increment_mb', float('nan')):.1f} "
            f"| {r['loadavg_1min'][0]:.1f}–{r['loadavg_1min'][1]:.1f} |"
        )
    return "\n".join(lines)


def long_sweep(Ts: list[int], repeats: int) -> dict:
    """The long-record sweep: a fresh process per (T, method); log–log fits against T."""
    rows, fits = [], {}
    for method in LONG_METHODS:
        mrows = []
        for T in Ts:
            r = run_worker(["--worker-long", str(T), method, "--repeats", str(repeats)])
            mrows.append(r)
            print(
                f"long {method} T={T}: {r['steady_call_s']:.3f} s, {r['iterations'][0]} iter, "
                f"{1e3 * r['per_iter_s']:.1f} ms/iter, peak {r['peak_rss_mb']:.0f} MB "
                f"(+{r['peak_increment_mb']:.0f}), load {r['loadavg_1min'][0]:.1f}",
                flush=True,
            )
        rows += mrows
        xs = [r["T"] for r in mrows]
        fits[method] = {
            "time_per_iteration": loglog_fit(xs, [r["per_iter_s"] for r in mrows]),
            "time_per_call": loglog_fit(xs, [r["steady_call_s"] for r in mrows]),
            "peak_rss": loglog_fit(xs, [r["peak_rss_mb"] for r in mrows]),
            "peak_increment": loglog_fit(xs, [max(r["peak_increment_mb"], 1e-3) for r in mrows]),
        }
        big = [r for r in mrows if r["T"] >= 10000]
        if len(big) >= 2:
            fits[method]["peak_increment_T_ge_1e4"] = loglog_fit(
                [r["T"] for r in big], [max(r["peak_increment_mb"], 1e-3) for r in big]
            )
            fits[method]["steady_peak_increment"] = loglog_fit(
                [r["T"] for r in big], [max(r["steady_peak_increment_mb"], 1e-3) for r in big]
            )
            # the asymptotic slope: between the two largest T, where the T-independent cost of
            # an iteration (dispatch, the θ-sized work) no longer dominates
            top = sorted(big, key=lambda r: r["T"])[-2:]
            fits[method]["time_per_iteration_top"] = loglog_fit(
                [r["T"] for r in top], [r["per_iter_s"] for r in top]
            )
    print(f"### Long records (one record, mass–spring–damper)\n\n{long_table(rows)}\n")
    for method, f in fits.items():
        print(
            f"{method}: slope time/iteration {f['time_per_iteration']['slope']:.2f} "
            f"(R² {f['time_per_iteration']['r2']:.3f}), time/call "
            f"{f['time_per_call']['slope']:.2f}, top two T "
            f"{f.get('time_per_iteration_top', {}).get('slope', float('nan')):.2f}, memory "
            f"increment {f['peak_increment']['slope']:.2f}, steady memory increment "
            f"{f.get('steady_peak_increment', {}).get('slope', float('nan')):.2f}"
        )
    target = {
        "criterion": "linear in T: log–log slope against T at most 1.15 "
        "of the time per iteration (all T and the two largest) and of the steady calls' memory "
        "increment (T ≥ 10⁴); a slope below 0.85 is a T-independent part (dispatch, θ-sized "
        "work, allocator slack), reported, not a failure",
        "met": {
            m: {
                "time": max(
                    f["time_per_iteration"]["slope"],
                    f.get("time_per_iteration_top", f["time_per_iteration"])["slope"],
                )
                <= 1.15,
                "memory": f.get("steady_peak_increment", f["peak_increment"])["slope"] <= 1.15,
            }
            for m, f in fits.items()
        },
    }
    return {"T": Ts, "rows": rows, "fits": fits, "target": target}


def run_worker(args: list[str]) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), *args]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"worker {args} failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# --- tables -----------------------------------------------------------------------------------


def smooth_table(rows: list[dict]) -> str:
    lines = [
        "| T | B | K | n | iters/call | compile (s) | per iteration, median (ms) | min (ms) "
        "| per traj-step (µs) | load |",
        "|" + "---:|" * 10,
    ]
    for r in rows:
        lines.append(
            f"| {r['T']} | {r['B']} | {r['K']} | {r['n']} | {r['iterations']} "
            f"| {r['compile_s']:.2f} | {1e3 * r['per_iter_s']:.2f} "
            f"| {1e3 * r['per_iter_min_s']:.2f} "
            f"| {1e6 * r['per_iter_per_traj_step_s']:.2f} | {r['loadavg_1min'][0]:.1f} |"
        )
    return "\n".join(lines)


def flop_table(rows: list[dict]) -> str:
    lines = [
        "| n | m | T·B | bound (GFLOP/call) | achieved (GFLOP/s) | time/(bound/peak) "
        "| with Jacobians: GFLOP/s, ratio | minimal: ratio |",
        "|" + "---:|" * 8,
    ]
    for r in rows:
        f = r["flop"]
        lines.append(
            f"| {r['n']} | {r['m']} | {r['T'] * r['B']} | {r['flops_call']['bound'] / 1e9:.3g} "
            f"| {f['achieved_gflops']:.2f} | {f['ratio']:.1f} "
            f"| {f['achieved_gflops_with_jacobians']:.2f}, {f['ratio_with_jacobians']:.1f} "
            f"| {f['ratio_minimal']:.1f} |"
        )
    return "\n".join(lines)


def fit_table(rows: list[dict]) -> str:
    lines = [
        "| T | K | n | P | method | compile (s) | steady epoch (s) | smooth / learn (s) | load |",
        "|" + "---:|" * 4 + "---|" + "---:|" * 4,
    ]
    for r in rows:
        for name, m in r["methods"].items():
            split = ""
            if "smooth_time" in m:
                split = (
                    f"{statistics.median(m['smooth_time'][1:]):.3f} / "
                    f"{statistics.median(m['learn_time'][1:]):.3f}"
                )
            lines.append(
                f"| {r['T']} | {r['K']} | {r['n']} | {r['P']} | {name} | {m['compile_s']:.2f} "
                f"| {m['steady_epoch_s']:.3f} | {split} | {m['loadavg_1min'][0]:.1f} |"
            )
    return "\n".join(lines)


# --- main -------------------------------------------------------------------------------------


def environment() -> dict:
    cpu = "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "jax": jax.__version__,
        "ceemx": ceemx.__version__,
        "backend": jax.devices()[0].platform,
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "cpu_model": cpu,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }


def main(argv=None) -> dict:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "--k100":
        import k100

        return k100.main(argv[1:])
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="smaller grid (≈ 6 min under load)")
    mode.add_argument("--smoke", action="store_true", help="a few tiny cases (tests)")
    mode.add_argument(
        "--grid",
        choices=sorted(GRIDS),
        default=None,
        help="a named grid; b8: the first smoother sweep (B = 8, K ≤ 20, 5 iterations per call, "
        "no fits; ≈ 5 min)",
    )
    p.add_argument("--out", type=str, default=None)
    p.add_argument("--only", choices=("smooth", "fit", "long"), default=None)
    p.add_argument(
        "--sweeps", type=str, default="T,B,K", help="smoothing sweeps to run (default T,B,K)"
    )
    p.add_argument(
        "--variant",
        type=str,
        default=None,
        help="store this run under variants[NAME] of an existing --out file instead of "
        "replacing it (e.g. a run under `taskset -c 0`)",
    )
    p.add_argument("--repeats", type=int, default=3, help="steady calls per case (≥ 3)")
    p.add_argument("--min-time", type=float, default=None, help="min steady seconds per case")
    p.add_argument("--worker-smooth", type=int, nargs=4, help=argparse.SUPPRESS)
    p.add_argument("--worker-fit", type=int, nargs=4, help=argparse.SUPPRESS)
    p.add_argument("--worker-long", nargs=2, help=argparse.SUPPRESS)
    p.add_argument("--long-T", type=int, nargs="+", default=None, help="T of --only long")
    args = p.parse_args(argv)
    min_time = args.min_time if args.min_time is not None else (0.0 if args.smoke else 1.0)

    if args.worker_smooth:
        T, B, K, steps = args.worker_smooth
        print(json.dumps(smooth_case(T, B, K, steps, args.repeats, min_time)))
        return {}
    if args.worker_fit:
        print(json.dumps(fit_case(*args.worker_fit)))
        return {}
    if args.worker_long:
        T, method = int(args.worker_long[0]), args.worker_long[1]
        print(json.dumps(long_case(T, method, args.repeats)))
        return {}

    name = "smoke" if args.smoke else ("quick" if args.quick else (args.grid or "default"))
    grid = GRIDS[name]
    default_out = DEFAULT_LONG_OUT if args.only == "long" else DEFAULT_OUT
    out_path = args.out if args.out else (default_out if name in ("default", "quick") else None)
    t_start = time.perf_counter()
    env = environment()
    print(
        f"jax {env['jax']} on {env['backend']}, {env['cpu_count']} CPUs ({env['cpu_model']}); "
        f"mode {name}; 1-min load {os.getloadavg()[0]:.2f}\n",
        flush=True,
    )
    result: dict = {"config": {"mode": name, "grid": grid, "repeats": args.repeats}}
    result["environment"] = env

    if args.only in (None, "smooth"):
        peak = measure_peak(sizes=(512,) if args.smoke else (1024, 2048))
        result["peak"] = peak
        print(
            f"float64 matmul peak {peak['peak_gflops']:.1f} GFLOP/s "
            f"({', '.join(f'{k}: {v:.1f}' for k, v in peak['matmul_gflops'].items())}); "
            "batched small blocks "
            + ", ".join(f"n={k}: {v:.1f}" for k, v in peak["batched_small_matmul_gflops"].items())
            + " GFLOP/s\n",
            flush=True,
        )
        cache: dict[tuple, dict] = {}
        sweeps, slopes, slopes_min = {}, {}, {}
        wanted = set(args.sweeps.split(","))
        for var, values, base in (sw for sw in grid["smooth"] if sw[0] in wanted):
            rows = []
            for v in values:
                cfg = dict(base, **{var: v})
                steps = 2 if args.smoke else grid.get("steps") or steps_for(3 * cfg["K"])
                key = (cfg["T"], cfg["B"], cfg["K"], steps)
                if key not in cache:
                    cache[key] = run_worker(
                        ["--worker-smooth", *map(str, key), "--repeats", str(args.repeats)]
                        + ["--min-time", str(min_time)]
                    )
                rows.append(cache[key])
            xvar = "n" if var == "K" else var
            sweeps[var] = rows
            slopes[xvar] = slope([r[xvar] for r in rows], [r["per_iter_s"] for r in rows])
            slopes_min[xvar] = slope([r[xvar] for r in rows], [r["per_iter_min_s"] for r in rows])
            fixed = ", ".join(f"{k}={v}" for k, v in base.items() if k != var)
            print(f"### Smoothing: sweep over {var} ({fixed})\n\n{smooth_table(rows)}")
            print(f"\nlog–log slope vs {xvar}: {slopes[xvar]:.2f} (min: {slopes_min[xvar]:.2f})\n")
        # FLOP bound on every distinct case.
        pk = peak["peak_gflops"] * 1e9
        flop_rows = sorted(cache.values(), key=lambda r: (r["n"], r["T"] * r["B"]))
        for r in flop_rows:
            t = r["steady_call_s"]
            fc = r["flops_call"]
            r["flop"] = {
                "achieved_gflops": fc["bound"] / t / 1e9,
                "ratio": t / (fc["bound"] / pk),
                "achieved_gflops_with_jacobians": fc["with_jacobians"] / t / 1e9,
                "ratio_with_jacobians": t / (fc["with_jacobians"] / pk),
                "ratio_minimal": t / (fc["minimal"] / pk),
            }
        big = [r for r in flop_rows if r["n"] >= 18]
        target = {
            "criterion": "time / (bound / peak) <= 5 for every measured case with n >= 18",
            "worst_ratio_n_ge_18": max(r["flop"]["ratio"] for r in big) if big else None,
            "met": bool(big) and all(r["flop"]["ratio"] <= 5 for r in big),
        }
        print(f"### FLOP bound (peak {peak['peak_gflops']:.1f} GFLOP/s)\n\n{flop_table(flop_rows)}")
        print(
            f"\nTarget (≤ 5× the bound at n ≥ 18): {'met' if target['met'] else 'NOT met'}; "
            f"worst ratio {target['worst_ratio_n_ge_18']}\n",
            flush=True,
        )
        result["smoothing"] = {
            "sweeps": sweeps,
            "slopes": slopes,
            "slopes_min": slopes_min,
            "flop_rows": [
                {k: r[k] for k in ("T", "B", "K", "n", "m", "iterations", "flops_call", "flop")}
                for r in flop_rows
            ],
            "flops_per_traj_step": {
                str(n): smoother_flops(n, max(n - 2, 1))
                for n in sorted({r["n"] for r in flop_rows})
            },
            "target_5x": target,
        }

    if args.only == "long":
        result["long"] = long_sweep(args.long_T or LONG_T[name], args.repeats)

    if args.only in (None, "fit") and grid["fit"]:
        fg = grid["fit"]
        rows = []
        for T, K in fg["cases"]:
            rows.append(
                run_worker(["--worker-fit", str(T), str(K), str(fg["B"]), str(grid["fit_epochs"])])
            )
        print(f"### Fit iterations (B={fg['B']}, {grid['fit_epochs']} epochs per fit)\n")
        print(fit_table(rows))
        fit_slopes = {}
        for method in rows[0]["methods"]:
            for var, fixed in (("T", ("K", 6)), ("n", ("T", 128))):
                sel = [r for r in rows if r[fixed[0]] == fixed[1]]
                if len({r[var] for r in sel}) >= 2:
                    fit_slopes[f"{method}_vs_{var}"] = slope(
                        [r[var] for r in sel], [r["methods"][method]["steady_epoch_s"] for r in sel]
                    )
        if fit_slopes:
            print("\nlog–log slopes: " + ", ".join(f"{k}: {v:.2f}" for k, v in fit_slopes.items()))
        result["fit"] = {"rows": rows, "slopes": fit_slopes}

    result["total_wall_s"] = time.perf_counter() - t_start
    result["loadavg_end"] = os.getloadavg()
    print(f"\nTotal wall time {result['total_wall_s']:.1f} s; load {os.getloadavg()[0]:.2f}")
    result["command"] = " ".join([os.path.basename(__file__), *argv])
    if out_path:
        os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
        data = result
        if args.variant:
            with open(out_path) as f:
                data = json.load(f)
            data.setdefault("variants", {})[args.variant] = result
        with open(out_path, "w") as f:
            json.dump(data, f, indent=2)
        print(f"wrote {out_path}")
    return result


if __name__ == "__main__":
    main()
