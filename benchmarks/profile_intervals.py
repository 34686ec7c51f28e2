"""Wald against profile-likelihood intervals on the mass–spring–damper of the default-fit bank.

The model and data of ``benchmarks/default_fit_bank.py`` (k = 4, c = 0.5, dt 0.05, two records
of 2,000 samples, observation noise 0.01, process noise ``--noise``), fitted from k = 3, c = 0.8
with the true noise given by three paths: ``fit(model, data)`` (the library default),
``solver=JointLM()`` and ``solver=LaplaceEM()`` learning both noise scales. Per path and
parameter: the estimate, its standard error, the Wald interval the summary prints, the
profile-likelihood interval (``FitResult.profile``) with how each end was found, the refits it
took and its time (the first profile of a path compiles its refits); and the time
``summary()`` takes with ``intervals="wald"`` and ``"auto"`` (which intervals the rule profiled).

Usage::

    python benchmarks/profile_intervals.py [--noise 1e-2] [--seed 0]

Writes ``benchmarks/results/profile_intervals[_<noise>].json`` and prints a Markdown table.
Backs: the profile-likelihood intervals of issue 40's item 2 (``docs/guarantees.md``).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import sys
import time
import warnings

import jax

import ceemx

jax.config.update("jax_enable_x64", True)

ROOT = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
import default_fit_bank as bank  # noqa: E402  (the bank's models and data, not a copy)


def _fit(path: str, cfg, system, data):
    if path == "default":
        return ceemx.fit(system, data)
    if path == "jointlm":
        return ceemx.fit(system, data, solver=ceemx.JointLM())
    return ceemx.fit(
        system, data, solver=ceemx.LaplaceEM(), trainable=bank._with_noise(cfg), max_epochs=100
    )


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, default=1e-2, help="process noise std")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    name = {1e-3: "msd-1e-3", 1e-2: "msd-1e-2", 1e-1: "msd-1e-1"}[args.noise]
    cfg = bank.CONFIGS[name]
    key = jax.random.fold_in(jax.random.PRNGKey(args.seed), cfg.salt)
    data = cfg.data(key, cfg.system(cfg.true))
    start = cfg.system({"k": 3.0, "c": 0.8})
    records = []
    load = os.getloadavg()[0]
    for path in ("default", "jointlm", "laplace-learn"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result, fit_s = _timed(lambda p=path: _fit(p, cfg, start, data))
            _, wald_s = _timed(lambda r=result: r.summary(intervals="wald"))
            text, auto_s = _timed(lambda r=result: r.summary())
            estimates = result.parameter_estimates()
            for param in ("k", "c"):
                p, prof_s = _timed(lambda r=result, q=param: r.profile(q))
                records.append({
                    "path": path, "solver": type(result.solver).__name__,
                    "converged": result.converged, "epochs": result.epochs,
                    "fit_s": fit_s, "summary_wald_s": wald_s, "summary_auto_s": auto_s,
                    "summary_profiled": [line.split()[0] for line in str(text).splitlines()
                                         if " profile" in line and "[" in line],
                    "parameter": param, "true": cfg.true[param],
                    "estimate": p.estimate, "se": estimates[param][1],
                    "wald": list(p.wald), "profile": [p.lower, p.upper],
                    "ends": [p.lower_end, p.upper_end], "objective": p.objective,
                    "refits": p.evaluations, "profile_s": prof_s, "notes": list(p.notes),
                })  # fmt: skip
    out = ROOT / "results" / f"profile_intervals{'' if args.noise == 1e-2 else '_' + name}.json"
    meta = {
        "command": " ".join(sys.argv),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "load_before": load,
        "load_after": os.getloadavg()[0],
        "config": name,
        "seed": args.seed,
    }
    out.write_text(json.dumps({"meta": meta, "rows": records}, indent=1))
    print(f"{name}, seed {args.seed}; load {load:.1f} → {meta['load_after']:.1f}; {out}")
    print(
        "| path | param | estimate ± SE | Wald 95 % | profile 95 % | refits, s "
        "| summary wald/auto s |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in records:
        print(
            f"| {r['path']} ({'conv.' if r['converged'] else 'NOT conv.'}) | {r['parameter']} | "
            f"{r['estimate']:.4f} ± {r['se']:.4f} | [{r['wald'][0]:.4f}, {r['wald'][1]:.4f}] | "
            f"[{r['profile'][0]:.4f}, {r['profile'][1]:.4f}] | {r['refits']}, "
            f"{r['profile_s']:.1f} | {r['summary_wald_s']:.2f} / {r['summary_auto_s']:.2f} "
            f"(profiled: {', '.join(r['summary_profiled']) or 'none'}) |"
        )


if __name__ == "__main__":
    main()
