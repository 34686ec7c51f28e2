"""Algorithm-1 epoch on the Figure-3 problem: where the time goes, and the M-/E-step bounds.

    python benchmarks/probes/algorithm1_epoch.py [--epochs 8] [--only NAME ...]
    python benchmarks/probes/algorithm1_epoch.py --epochs 0   # the components only

6 coupled Lorenz, B = 8, T = 128, seed 42, the paper's weighting, states started at truth +
N(0, 1) as ``ceemx experiment figure3``. Prints, then writes to
``benchmarks/results/algorithm1_epoch.json`` (``algorithm1_epoch_components.json`` with
``--epochs 0``), with the load before and after:

1. the components of an epoch, each compiled, then called in turn 5 times (medians), at the
   start point: the learner's Gauss–Newton build from chunks of the batch's θ-Jacobian rows (the
   default, ``LearningProblem.gauss_newton``) and as B per-trajectory products summed (the
   earlier form, ``AbstractLearningProblem.gauss_newton``), the θ-Jacobians alone, the
   learning objective's value, and one smoothing step (default bound, and ``max_steps=2``);
2. for each solver variant (learner and smoother bounds): median seconds per epoch, in
   smoothing and in learning (epochs 2–N; epoch 1 carries the compile), the learner's and the
   smoother's steps, and ε(θ) after each epoch.

Backs: ``benchmarks/README.md`` ("Figure-3 problem vs the authors' code", profile of the
Algorithm-1 epoch).
"""

import argparse
import json
import os
import pathlib
import sys
import time

import equinox as eqx
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
import ceemx  # noqa: E402
from ceemx.evaluation import metrics as ev  # noqa: E402
from ceemx.experiments import common, figure3  # noqa: E402
from ceemx.identification.learning.gauss_newton import theta_rows  # noqa: E402
from ceemx.identification.learning.learning_problem import (  # noqa: E402
    AbstractLearningProblem,
    make_problem,
)
from ceemx.inference import smoother as smoothing  # noqa: E402
from ceemx.models import with_noise  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from compare_reference_figure3 import figure3_problem  # noqa: E402

OUT = pathlib.Path(__file__).resolve().parents[1] / "results" / "algorithm1_epoch.json"


def timed(fs: dict, reps=5) -> dict:
    """Median seconds of each thunk, compiled first, then called in turn ``reps`` times (A/B)."""
    for f in fs.values():
        jax.block_until_ready(f())
    ts = {k: [] for k in fs}
    for _ in range(reps):
        for k, f in fs.items():
            t = time.perf_counter()
            jax.block_until_ready(f())
            ts[k].append(time.perf_counter() - t)
    return {k: float(np.median(v)) for k, v in ts.items()}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=8)
    ap.add_argument("--only", nargs="*", default=None)
    args = ap.parse_args()
    true, p, x_init = figure3_problem()
    pn, on, rho_x = figure3.fit_setup("paper")
    system = with_noise(p.init_system, pn, on)
    out = {"load_before": os.getloadavg()[0], "components_s": {}, "variants": {}}

    lp, th = make_problem(system, x_init, p.data, trainable=common.LORENZ_PARAMS_H)
    d = p.data
    comp = {
        "gauss_newton (the default: chunks of rows)": eqx.filter_jit(
            lambda lp, th: lp.gauss_newton(th)
        ),
        "gauss_newton (B per-trajectory products, earlier)": eqx.filter_jit(
            lambda lp, th: AbstractLearningProblem.gauss_newton(lp, th)
        ),
        "θ-Jacobian rows alone": eqx.filter_jit(
            lambda lp, th: jax.vmap(lambda x, y, u, m: theta_rows(lp.build, th, x, y, u, m)[2])(
                lp.states, d.y, d.u, d.mask
            )
        ),
        "learning objective's value": eqx.filter_jit(lambda lp, th: lp.value(th)),
    }
    thunks = {name: (lambda f=f: f(lp, th)) for name, f in comp.items()}
    for steps in (50, 2):
        sm = ceemx.LMSmoother(rho_x=rho_x, max_steps=steps)
        thunks[f"smoothing step (LMSmoother(max_steps={steps}), from the start states)"] = (
            lambda sm=sm: smoothing.smooth_batch(sm, system, x_init, d, False).states
        )
    out["components_s"] = timed(thunks)
    rows = comp["θ-Jacobian rows alone"](lp, th)
    out["rows_per_trajectory"] = int(rows.shape[1])
    out["rows_nonzero_fraction"] = float(np.mean(np.abs(np.asarray(rows)) > 0))
    print(
        f"  θ-Jacobian rows per trajectory {rows.shape[1]} × {rows.shape[2]}, "
        f"{out['rows_nonzero_fraction']:.1%} of the entries nonzero"
    )
    for k, v in out["components_s"].items():
        print(f"  {k:60s} {v * 1e3:8.1f} ms", flush=True)

    variants = {
        "exact M-step: LMLearner() (the default before)": (
            ceemx.LMSmoother(rho_x=rho_x),
            ceemx.LMLearner(),
        ),
        "GEM: LMLearner(max_accepted=1)": (
            ceemx.LMSmoother(rho_x=rho_x),
            ceemx.LMLearner(max_accepted=1),
        ),
        "LMLearner(max_steps=1)": (ceemx.LMSmoother(rho_x=rho_x), ceemx.LMLearner(max_steps=1)),
        "GEM + smoother max_steps=2": (
            ceemx.LMSmoother(rho_x=rho_x, max_steps=2),
            ceemx.LMLearner(max_accepted=1),
        ),
        "lbfgs (100 steps)": (ceemx.LMSmoother(rho_x=rho_x), figure3.make_learner("lbfgs")),
    }
    for name, (smoother, learner) in variants.items() if args.epochs > 0 else ():
        if args.only and not any(o in name for o in args.only):
            continue
        eps = ev.DynamicsErrorCallback(true)
        solver = ceemx.Alternating(smoother=smoother, learner=learner, rtol=0.0)
        res = ceemx.fit(
            system,
            p.data,
            x_init,
            solver=solver,
            trainable=common.LORENZ_PARAMS_H,
            max_epochs=args.epochs,
            progress=False,
            callbacks=[eps],
        )
        h = res.history[1:]
        keys = ("time", "smooth_time", "learn_time")
        med = {k: float(np.median([x[k] for x in h])) for k in keys}
        rec = {
            **{f"{k}_median_s": v for k, v in med.items()},
            "first_epoch_s": res.history[0]["time"],
            "learner_steps": [x["learner_steps"] for x in res.history],
            "smoother_steps": [x["smoother_steps"] for x in res.history],
            "eps": [x["eps"] for x in res.history],
        }
        out["variants"][name] = rec
        print(
            f"{name:48s} epoch {med['time']:.3f} s (smoothing {med['smooth_time']:.3f}, "
            f"learning {med['learn_time']:.3f}); steps (learner, smoother) "
            f"{rec['learner_steps']}, {rec['smoother_steps']}; "
            f"ε per epoch {[round(x, 4) for x in rec['eps']]}",
            flush=True,
        )
    out["load_after"] = os.getloadavg()[0]
    out["date"] = time.strftime("%Y-%m-%d %H:%M")
    print(f"load {out['load_before']:.2f} → {out['load_after']:.2f}")
    path = OUT if args.epochs > 0 else OUT.with_name("algorithm1_epoch_components.json")
    path.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
