"""Laplace EM on one long record beside a JointLM fit of the same model.

Model: the mass–spring–damper of ``docs/custom_systems.md`` (x = (q, q̇), y = q, dt 0.1,
first-order hold, 2 RK4 substeps), one record of T samples simulated with k = 4, c = 0.5,
σ_w = 1e-3, σ_v = 0.01 under a white-noise force. Start: k = 3, c = 1, σ_w = 3e-3, σ_v = 0.03.
Laplace EM learns (k, c, σ_w, σ_v); JointLM learns (k, c) with the noise fixed at the start (it
cannot learn noise) — same data, same start, ``max_epochs`` 100, default tolerances (both stop at
a relative change of 1e-10 of their objective). Laplace EM runs three times: with its default
SQUAREM epochs, with ``acceleration="quasi_newton"`` (one E-step and one gradient of Q per epoch,
BFGS on the EM fixed-point equation; on T ≥ 40 000 after its default coarse start, a fit of the
first 10 000 samples whose θ and curvature start it), and the same without the coarse start
(``coarse_start=None``, the quasi-Newton fit before the coarse start existed); the estimates of
each are recorded (the same fixed point).
Also timed: Laplace EM learning (k, c) with the noise fixed as JointLM's, which separates the
cost of learning the noise (EM's slow epochs) from that of the method, and JointLM with
``noise="learn"`` (CE fits alternated with the Laplace-evidence noise estimate), the CE way to
the noise.

Timing: the first fit of each method in the process includes JIT compilation (reported as
``first_fit_s``; ``compile_s`` ≈ first − steady; programs shared by two methods compile in
the first of them); then ``--reps`` steady-state fits of each,
cycling the methods in the order of ``ORDER`` (the machine is shared), reported as
the median wall time of the fit call, with epochs, time per epoch and Laplace EM's E-step /
M-step split (history ``smooth_time``, ``learn_time``). ``uptime`` before and after each fit.

Usage: ``python benchmarks/laplace_long_record.py [--T 25000 100000] [--reps 3] [--smoke]
[--out PATH]`` (default ``--out benchmarks/results/laplace_long_record.json``; ``--smoke``:
T = 2000, 1 repetition, no output file unless ``--out`` is given); the JSON is written after
each T.

Subcommands, the pieces behind Laplace EM's defaults (record ``uptime`` beside each)::

    python benchmarks/laplace_long_record.py gradient [T]          # default T = 100 000
    python benchmarks/laplace_long_record.py coarse [T] [SIZE ...]  # 10 000 5 000 2 500
    python benchmarks/laplace_long_record.py escape
    python benchmarks/laplace_long_record.py acceleration [SEED ...] [--acc plain squarem ...]

``gradient``: on the record (θ after 3 quasi-Newton epochs), the Laplace posterior (E-step from
converged states) and the θ-gradient of Q by cubature, each compiled, then timed (median of 5).
``coarse``: quasi-Newton Laplace EM with ``coarse_start`` = each SIZE (median of 3 steady fits:
time, epochs on the record, the coarse fit's epochs), and the coarse θ alone — the first SIZE
samples fitted, then the record from their θ with ``coarse_start=None``, so with EM's metric as
the curvature's start: its epochs. ``escape``: ``fit(noise="learn")`` with JointLM on the stiff
model of ``tests/stiff_model.py`` (process noise guessed 100× too small) with and without
``estimate_noise``'s decade escape: wall time, posterior evaluations, evidence.
``acceleration``: Laplace EM with learned noise on the Figure-2 Lorenz setting of ``ceemx
experiment calibration`` (seeds 43–52 by default), per seed and acceleration (``plain``,
``squarem``, ``quasi_newton``; default the first two): epochs (≤ 600), time (the first fit of each
acceleration compiles), the final log-evidence and the estimates.

Backs: ``benchmarks/README.md`` (the Laplace EM rows), ``docs/known_issues.md`` and
``docs/decisions.md`` (SQUAREM by default, the coarse start, the noise estimate's escape).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import ceemx

jax.config.update("jax_enable_x64", True)

ROOT = pathlib.Path(__file__).resolve().parent.parent
OPTIONS = dict(dt=0.1, hold="foh", substeps=2)


class MassSpringDamper(ceemx.AbstractContinuousSystem):
    """m q̈ = u − k q − c q̇; x = (q, q̇); y = q + v (docs/custom_systems.md)."""

    k: Array = ceemx.param(positive=True)
    c: Array = ceemx.param(positive=True)
    m: Array = ceemx.param(fixed=True, default=1.0)

    @property
    def state_dim(self) -> int:
        """n = 2."""
        return 2

    @property
    def obs_dim(self) -> int:
        """m = 1."""
        return 1

    @property
    def control_dim(self) -> int:
        """One force."""
        return 1

    def vector_field(self, x, u, t):
        """(q̇, (u − k q − c q̇)/m)."""
        q, v = x[0], x[1]
        return jnp.stack([v, (u[0] - self.k * q - self.c * v) / self.m])

    def observe(self, x, u, t):
        """The position."""
        return x[:1]


def problem(T: int, seed: int = 0):
    """(start, data) of one record of T samples."""
    true = MassSpringDamper(k=4.0, c=0.5, process_noise=1e-3, obs_noise=0.01, **OPTIONS)
    force = jax.random.normal(jax.random.PRNGKey(seed), (1, T, 1))
    u = ceemx.data.trajectories.foh_inputs(force)
    _, data = ceemx.simulate(true, jax.random.PRNGKey(seed + 1), jnp.zeros((1, 2)), T, u)
    start = MassSpringDamper(k=3.0, c=1.0, process_noise=3e-3, obs_noise=0.03, **OPTIONS)
    return start, data


def laplace_fit(start, data, max_epochs: int = 100):
    """Laplace EM learning (k, c, σ_w, σ_v)."""
    return ceemx.fit(
        start,
        data,
        solver=ceemx.LaplaceEM(),
        trainable=lambda s: (s.k, s.c, s.process_noise, s.obs_noise),
        max_epochs=max_epochs,
    )


def laplace_qn_fit(start, data, max_epochs: int = 100):
    """Laplace EM learning (k, c, σ_w, σ_v) by quasi-Newton steps on its fixed-point equation."""
    return ceemx.fit(
        start,
        data,
        solver=ceemx.LaplaceEM(acceleration="quasi_newton"),
        trainable=lambda s: (s.k, s.c, s.process_noise, s.obs_noise),
        max_epochs=max_epochs,
    )


def laplace_qn_whole_fit(start, data, max_epochs: int = 100):
    """As ``laplace_qn_fit`` without the coarse start (``coarse_start=None``): the fit before it."""
    return ceemx.fit(
        start,
        data,
        solver=ceemx.LaplaceEM(acceleration="quasi_newton", coarse_start=None),
        trainable=lambda s: (s.k, s.c, s.process_noise, s.obs_noise),
        max_epochs=max_epochs,
    )


def laplace_fixed_noise_fit(start, data, max_epochs: int = 100):
    """Laplace EM learning (k, c) only, noise fixed at the start (as JointLM)."""
    return ceemx.fit(start, data, solver=ceemx.LaplaceEM(), max_epochs=max_epochs)


def joint_noise_learn_fit(start, data, max_epochs: int = 100):
    """JointLM learning (k, c) with ``noise="learn"`` (CE fits and noise estimates)."""
    return ceemx.fit(start, data, solver=ceemx.JointLM(), noise="learn", max_epochs=max_epochs)


def joint_fit(start, data, max_epochs: int = 100):
    """JointLM learning (k, c), noise fixed at the start."""
    return ceemx.fit(start, data, solver=ceemx.JointLM(), max_epochs=max_epochs)


METHODS = {
    "laplace_em": laplace_fit,
    "laplace_em_qn": laplace_qn_fit,
    "laplace_em_qn_whole": laplace_qn_whole_fit,
    "joint_lm": joint_fit,
    "joint_lm_noise_learn": joint_noise_learn_fit,
    "laplace_em_fixed_noise": laplace_fixed_noise_fit,
}
ORDER = (
    "joint_lm",
    "laplace_em",
    "laplace_em_qn",
    "laplace_em_qn_whole",
    "laplace_em_fixed_noise",
    "joint_lm_noise_learn",
)


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def timed(name: str, start, data) -> dict:
    """One fit of ``name``: wall time, epochs, θ, and the history's time split."""
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    result = METHODS[name](start, data)
    wall = time.perf_counter() - t0
    hist = result.history
    rec = {
        "wall_s": wall,
        "epochs": len(hist),
        "k": float(result.system.k),
        "c": float(result.system.c),
        "load_before": load,
        "load_after": os.getloadavg()[0],
    }
    if name == "joint_lm_noise_learn":
        rec["process_noise_std"] = float(np.ravel(result.system.process_noise.std())[0])
        rec["obs_noise_std"] = float(np.ravel(result.system.obs_noise.std())[0])
        rec["rounds"] = len(result.noise_rounds or ())
        rec["log_evidence"] = (result.noise_rounds or [{}])[-1].get("log_evidence")
    if name.startswith("laplace_em"):
        rec["smooth_s"] = float(sum(h.get("smooth_time", 0.0) for h in hist))
        rec["learn_s"] = float(sum(h.get("learn_time", 0.0) for h in hist))
        rec["process_noise_std"] = float(np.ravel(result.system.process_noise.std())[0])
        rec["obs_noise_std"] = float(np.ravel(result.system.obs_noise.std())[0])
        rec["log_evidence"] = hist[-1].get("log_evidence")
        rec["coarse"] = {k: v for k, v in hist[0].items() if k.startswith("coarse")}
    return rec


def run(T: int, reps: int) -> dict:
    """First (compiling) fit of each method, then ``reps`` steady-state fits, alternating."""
    start, data = problem(T)
    out: dict = {"T": T, "uptime_start": _uptime(), "first": {}, "steady": {m: [] for m in METHODS}}
    for name in ORDER:
        out["first"][name] = timed(name, start, data)
        print(T, name, "first", json.dumps(out["first"][name]), flush=True)
    for rep in range(reps):
        for name in ORDER:
            rec = timed(name, start, data)
            rec["uptime"] = _uptime()
            out["steady"][name].append(rec)
            print(T, name, rep, json.dumps(rec), flush=True)
    summary = {}
    for name in METHODS:
        walls = [r["wall_s"] for r in out["steady"][name]]
        med = statistics.median(walls)
        epochs = out["steady"][name][0]["epochs"]
        summary[name] = {
            "median_fit_s": med,
            "fit_s": walls,
            "epochs": epochs,
            "s_per_epoch": med / epochs,
            "first_fit_s": out["first"][name]["wall_s"],
            "compile_s_approx": out["first"][name]["wall_s"] - med,
        }
        if name.startswith("laplace_em"):
            summary[name]["median_smooth_s"] = statistics.median(
                r["smooth_s"] for r in out["steady"][name]
            )
            summary[name]["median_learn_s"] = statistics.median(
                r["learn_s"] for r in out["steady"][name]
            )
    joint = summary["joint_lm"]["median_fit_s"]
    summary["ratio_laplace_over_joint"] = summary["laplace_em"]["median_fit_s"] / joint
    summary["ratio_laplace_qn_over_joint"] = summary["laplace_em_qn"]["median_fit_s"] / joint
    summary["ratio_laplace_qn_whole_over_joint"] = (
        summary["laplace_em_qn_whole"]["median_fit_s"] / joint
    )
    summary["ratio_laplace_qn_over_squarem"] = (
        summary["laplace_em_qn"]["median_fit_s"] / summary["laplace_em"]["median_fit_s"]
    )
    summary["ratio_joint_noise_learn_over_joint"] = (
        summary["joint_lm_noise_learn"]["median_fit_s"] / joint
    )
    summary["ratio_laplace_fixed_noise_over_joint"] = (
        summary["laplace_em_fixed_noise"]["median_fit_s"] / joint
    )
    out["summary"] = summary
    out["uptime_end"] = _uptime()
    return out


# Subcommands: the pieces behind Laplace EM's defaults.

TRAINABLE = lambda s: (s.k, s.c, s.process_noise, s.obs_noise)  # noqa: E731


def _qn(start, data, coarse):
    """A quasi-Newton Laplace EM fit with the given ``coarse_start``."""
    solver = ceemx.LaplaceEM(acceleration="quasi_newton", coarse_start=coarse)
    return ceemx.fit(start, data, solver=solver, trainable=TRAINABLE)


def _median_time(f, reps=5):
    """Median wall time of ``f()`` (results blocked on) after one untimed call."""
    jax.block_until_ready(f())
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def gradient(T: int) -> None:
    """``gradient [T]``: the Laplace posterior and the θ-gradient of Q, timed."""
    from ceemx.identification.problem import FitProblem
    from ceemx.identification.solvers.laplace_qn import q_derivatives
    from ceemx.inference.posterior import E_STEP_SMOOTHER, gaussian_posterior

    start, data = problem(T)
    r = laplace_qn_fit(start, data, max_epochs=3)
    fp, theta = FitProblem.create(r.system, data, trainable=TRAINABLE)
    e = gaussian_posterior(E_STEP_SMOOTHER, fp.build(theta), r.states, data)
    post = _median_time(
        lambda: gaussian_posterior(E_STEP_SMOOTHER, fp.build(theta), r.states, data).states
    )
    grad = _median_time(lambda: q_derivatives(fp, theta, e, hessian=False)[1])
    print(f"T {T}: posterior {1e3 * post:.1f} ms, gradient of Q {1e3 * grad:.1f} ms")


def coarse(T: int, sizes: list[int]) -> None:
    """``coarse [T] [SIZE ...]``: the quasi-Newton fit by coarse size, and the coarse θ alone."""
    start, data = problem(T)
    for size in sizes:
        _qn(start, data, size)
        times, r = [], None
        for _ in range(3):
            t0 = time.perf_counter()
            r = _qn(start, data, size)
            times.append(time.perf_counter() - t0)
        first = {k: v for k, v in r.history[0].items() if k.startswith("coarse")}
        window = _qn(start, data.head(size), None)
        theta_only = _qn(window.system, data, None)
        print(
            f"coarse_start {size}: {statistics.median(times):.2f} s, {r.epochs} epochs "
            f"({first}); the coarse θ with EM's metric: {theta_only.epochs} epochs",
            flush=True,
        )


def escape() -> None:
    """``escape``: ``noise="learn"`` on the stiff model with and without the decade escape."""
    sys.path.insert(0, str(ROOT / "tests"))
    import stiff_model as sm

    import ceemx.identification.analysis.evidence_search as search
    import ceemx.identification.analysis.noise_estimate as noise

    _, data, _ = sm.simulate(jax.random.PRNGKey(0), B=2, T=1000)
    guess = sm.make(sm.perturbed(jax.random.PRNGKey(1)), process_std=sm.PROCESS_STD * 0.01)
    counting = noise.moments_prepared  # what each evidence evaluation calls
    calls = [0]

    def counted(*a, **k):
        calls[0] += 1
        return counting(*a, **k)

    for escapes in (3, 0, 3, 0):
        calls[0] = 0
        search._ESCAPES, noise.moments_prepared = escapes, counted
        t0 = time.perf_counter()
        r = ceemx.fit(guess, data, solver=ceemx.JointLM(), noise="learn", max_epochs=300)
        noise.moments_prepared = counting
        print(
            f"escapes {escapes}: {time.perf_counter() - t0:.1f} s, {calls[0]} evaluations, "
            f"log-evidence {r.noise_rounds[-1]['log_evidence']:.6f}",
            flush=True,
        )


def acceleration(argv: list[str]) -> None:
    """``acceleration``: plain EM, SQUAREM and quasi-Newton per seed on the Lorenz setting."""
    from ceemx.experiments import calibration as laplace
    from ceemx.experiments import common
    from ceemx.models import with_noise

    ap = argparse.ArgumentParser(prog="laplace_long_record.py acceleration")
    ap.add_argument("seeds", type=int, nargs="*", default=list(range(43, 53)))
    ap.add_argument("--acc", nargs="+", default=["plain", "squarem"])
    args = ap.parse_args(argv)
    true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, process_noise=0.1, obs_noise=0.5)
    for seed in args.seeds:
        p = common.lorenz_problem(seed, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False)
        start = with_noise(p.init_system, laplace.START_W, laplace.START_V)
        for name in args.acc:
            t0 = time.perf_counter()
            res = ceemx.fit(
                start,
                p.data,
                solver=ceemx.LaplaceEM(acceleration=None if name == "plain" else name),
                trainable=lambda s: (s.sigma, s.rho, s.beta, s.process_noise, s.obs_noise),
                max_epochs=600,
                progress=False,
            )
            s = res.system
            print(
                f"seed {seed} {name}: {res.epochs} epochs, "
                f"{time.perf_counter() - t0:.2f} s, converged {res.converged}; log-evidence "
                f"{res.history[-1]['log_evidence']:.6f}; σ_w "
                f"{float(s.process_noise.scale):.4f}, σ_v {float(s.obs_noise.scale):.4f}, σ "
                f"{float(s.sigma[0]):.3f}, ρ {float(s.rho[0]):.3f}, β {float(s.beta[0]):.4f}",
                flush=True,
            )


def subcommand(argv: list[str]) -> bool:
    """Run the subcommand ``argv[0]`` if it is one; whether it was."""
    if not argv or argv[0] not in ("gradient", "coarse", "escape", "acceleration"):
        return False
    mode = argv[0]
    if mode == "acceleration":
        acceleration(argv[1:])
        return True
    rest = [int(a) for a in argv[1:]]
    if mode == "gradient":
        gradient(rest[0] if rest else 100_000)
    elif mode == "coarse":
        coarse(rest[0] if rest else 100_000, rest[1:] or [10_000, 5_000, 2_500])
    else:
        escape()
    return True


def main() -> None:
    """Run the benchmark and write the JSON."""
    if subcommand(sys.argv[1:]):
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--T", type=int, nargs="+", default=[25_000, 100_000])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    Ts, reps = ([2000], 1) if args.smoke else (args.T, args.reps)
    from importlib import metadata

    result = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "versions": {p: metadata.version(p) for p in ("ceemx", "jax", "jaxlib")},
        "cpus": os.cpu_count(),
        "setting": {
            "system": "mass–spring–damper (docs/custom_systems.md), dt 0.1, foh, 2 RK4 substeps",
            "true": {"k": 4.0, "c": 0.5, "sigma_w": 1e-3, "sigma_v": 0.01},
            "start": {"k": 3.0, "c": 1.0, "sigma_w": 3e-3, "sigma_v": 0.03},
            "laplace_em": "LaplaceEM(), trainable (k, c, process_noise, obs_noise)",
            "laplace_em_qn": "LaplaceEM(acceleration='quasi_newton'), trainable as laplace_em",
            "laplace_em_qn_whole": "as laplace_em_qn with coarse_start=None (no coarse start)",
            "joint_lm": "JointLM(), trainable (k, c), noise fixed at the start",
            "laplace_em_fixed_noise": "LaplaceEM(), trainable (k, c), noise fixed at the start",
            "joint_lm_noise_learn": "JointLM(), trainable (k, c), noise='learn'",
            "max_epochs": 100,
            "reps": reps,
        },
        "runs": [],
    }
    out = args.out or (None if args.smoke else "benchmarks/results/laplace_long_record.json")
    for T in Ts:  # written after each T, so a long run interrupted keeps what it measured
        result["runs"].append(run(T, reps))
        if out:
            path = ROOT / out if not os.path.isabs(out) else pathlib.Path(out)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(result, indent=1))
    print(json.dumps([r["summary"] for r in result["runs"]], indent=1))


if __name__ == "__main__":
    main()
