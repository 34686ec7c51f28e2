"""Laplace EM on one long record beside a JointLM fit of the same model (issue 21).

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

Backs: ``docs/known_issues.md`` ("LAPACK deadlock") and ``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
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


def main() -> None:
    """Run the benchmark and write the JSON."""
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
