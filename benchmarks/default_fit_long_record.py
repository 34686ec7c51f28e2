"""Candidate default paths on one long record, against a JointLM fit of the same model.

The rule for ``ceemx.fit``'s default must stay fast where records are long: at most 3× a
``JointLM`` fit on one 100,000-sample record. The problem is that of
``benchmarks/laplace_long_record.py`` (imported: the mass–spring–damper at dt 0.1, k = 4,
c = 0.5, σ_w = 1e-3, σ_v = 0.01; start k = 3, c = 1, σ_w = 3e-3, σ_v = 0.03; ``--noise-factor``
multiplies the start's two noise scales further, e.g. 33 for a guess 100× off), so the ratios
compare with the ones quoted there. Methods (``--methods``):

- ``joint_lm``: ``JointLM()``, noise fixed at the start (the reference);
- ``laplace_em`` / ``laplace_em_qn``: ``LaplaceEM()`` (SQUAREM) / ``acceleration="quasi_newton"``,
  learning (k, c, σ_w, σ_v);
- ``laplace_fixed`` / ``laplace_fixed_qn``: the same with the noise fixed at the start;
- ``joint_then_laplace`` / ``joint_then_laplace_qn``: a JointLM fit, then Laplace EM learning
  the noise from its θ and states (the two fits' time together);
- ``joint_lm_learn``: JointLM with ``noise="learn"``; ``joint_learn_then_laplace_fixed``: that,
  then Laplace EM (SQUAREM) in θ alone at the noise it learned;
- ``auto``: ``ceemx.fit(model, data)``, the path the library chooses (on this record: JointLM
  learning the noise on the first 2 500 steps, then Laplace EM in θ at that noise on all of them
  by quasi-Newton steps); each stage's epochs and seconds are recorded (``stages``).

Timing as in ``laplace_long_record.py``: the first fit of each method in the process includes
compilation (``first_fit_s``), then ``--reps`` steady-state fits cycling the methods; ``uptime``
and the 1-min load recorded. ``max_epochs`` 100 for every fit.

Usage: ``python benchmarks/default_fit_long_record.py [--T 100000] [--reps 2] [--methods ...]
[--noise-factor 1] [--out benchmarks/results/default_fit_long_record.json]``; the default path
against JointLM, the noise guessed 100× off: ``--methods joint_lm auto --noise-factor 33.3
--reps 5 --out benchmarks/results/default_fit_long_record_auto.json``.

Backs: issue 40, "the default path must stay fast where records are long".
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

import numpy as np

import ceemx

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import laplace_long_record as llr  # noqa: E402  (the problem and its model, one definition)

ROOT = pathlib.Path(__file__).resolve().parent.parent
NOISE = lambda s: (s.k, s.c, s.process_noise, s.obs_noise)  # noqa: E731


def _laplace(start, data, x_init=None, learn=True, **options):
    return ceemx.fit(
        start,
        data,
        x_init,
        solver=ceemx.LaplaceEM(**options),
        trainable=NOISE if learn else None,
        max_epochs=100,
    )


def _joint(start, data):
    return ceemx.fit(start, data, solver=ceemx.JointLM(), max_epochs=100)


def _two_stage(**options):
    def run(start, data):
        first = _joint(start, data)
        return _laplace(first.system, data, first.states, **options), first

    return run


def _joint_learn(start, data):
    return ceemx.fit(start, data, solver=ceemx.JointLM(), noise="learn", max_epochs=100)


def _joint_learn_then_laplace_fixed(start, data):
    first = _joint_learn(start, data)
    return _laplace(first.system, data, first.states, learn=False), first


METHODS = {
    "auto": lambda s, d: (ceemx.fit(s, d, max_epochs=100), None),
    "joint_lm": lambda s, d: (_joint(s, d), None),
    "joint_lm_learn": lambda s, d: (_joint_learn(s, d), None),
    "joint_learn_then_laplace_fixed": _joint_learn_then_laplace_fixed,
    "laplace_em": lambda s, d: (_laplace(s, d), None),
    "laplace_em_qn": lambda s, d: (_laplace(s, d, acceleration="quasi_newton"), None),
    "laplace_fixed": lambda s, d: (_laplace(s, d, learn=False), None),
    "laplace_fixed_qn": lambda s, d: (
        _laplace(s, d, learn=False, acceleration="quasi_newton"),
        None,
    ),
    "joint_then_laplace": _two_stage(),
    "joint_then_laplace_qn": _two_stage(acceleration="quasi_newton"),
}


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def timed(name: str, start, data) -> dict:
    """One fit of ``name``: wall time, epochs, converged, θ and the learned noise."""
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    result, first = METHODS[name](start, data)
    wall = time.perf_counter() - t0
    rec = {
        "wall_s": wall,
        "epochs": result.epochs + (first.epochs if first is not None else 0),
        "converged": bool(result.converged) and (first is None or bool(first.converged)),
        "k": float(result.system.k),
        "c": float(result.system.c),
        "process_noise_std": float(np.ravel(result.system.process_noise.std())[0]),
        "obs_noise_std": float(np.ravel(result.system.obs_noise.std())[0]),
        "log_evidence": result.history[-1].get("log_evidence") if result.history else None,
        "load_before": load,
        "load_after": os.getloadavg()[0],
    }
    if first is not None:
        rec["first_stage_s"] = float(sum(h["time"] for h in first.history))
    choice = getattr(result, "choice", None)
    if choice is not None and choice.by == "library":
        rec["epochs"] = sum(int(s.epochs or 0) for s in choice.stages)
        rec["stages"] = [
            {
                "solver": type(s.solver).__name__,
                "noise": s.noise,
                "part": s.part,
                "epochs": s.epochs,
                "converged": s.converged,
                "seconds": s.seconds,
            }
            for s in choice.stages
        ]
    return rec


def main() -> None:
    """Time the methods and write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--T", type=int, default=100_000)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    ap.add_argument("--noise-factor", type=float, default=1.0)
    ap.add_argument("--out", default="benchmarks/results/default_fit_long_record.json")
    args = ap.parse_args()
    start, data = llr.problem(args.T)
    pn = np.asarray(start.process_noise.std()) * args.noise_factor
    on = np.asarray(start.obs_noise.std()) * args.noise_factor
    start = llr.MassSpringDamper(k=3.0, c=1.0, process_noise=pn[0], obs_noise=on[0], **llr.OPTIONS)
    out: dict = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "cpus": os.cpu_count(),
        "T": args.T,
        "noise_factor": args.noise_factor,
        "uptime_start": _uptime(),
        "first": {},
        "steady": {m: [] for m in args.methods},
    }
    path = ROOT / args.out

    def save():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=1))

    for name in args.methods:
        out["first"][name] = timed(name, start, data)
        print(name, "first", json.dumps(out["first"][name]), flush=True)
        save()
    for rep in range(args.reps):
        for name in args.methods:
            rec = timed(name, start, data)
            out["steady"][name].append(rec)
            print(name, rep, json.dumps(rec), flush=True)
            save()
    joint = statistics.median(r["wall_s"] for r in out["steady"].get("joint_lm", [])) or None
    out["summary"] = {
        name: {
            "median_fit_s": statistics.median(r["wall_s"] for r in recs),
            "first_fit_s": out["first"][name]["wall_s"],
            "epochs": recs[0]["epochs"],
            "converged": recs[0]["converged"],
            "ratio_to_joint_lm": (statistics.median(r["wall_s"] for r in recs) / joint)
            if joint
            else None,
        }
        for name, recs in out["steady"].items()
        if recs
    }
    out["uptime_end"] = _uptime()
    save()
    print(json.dumps(out["summary"], indent=1))


if __name__ == "__main__":
    main()
