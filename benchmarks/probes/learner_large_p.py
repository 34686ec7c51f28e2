"""The learning step alone at large P: GaussNewtonCGLearner against LBFGSLearner (issue 23 item 3).

Coupled Lorenz at K attractors (``k100.py``'s protocol: n = 3K, P = 3K + 9K², T = 256, B = 16,
θ at ±10 %); the states are fixed at the truth plus N(0, ``--state-noise``²) — what an E-step
hands the learner. Each learner runs ``--repeats`` times, alternating, in one process: the first
call includes compilation, the others are steady. Reported: time, the learning objective less
its constants (½‖whitened residuals‖²) and ε(θ) (Eq. 14) after the step.

Usage::

    python benchmarks/probes/learner_large_p.py --K 20 --out /tmp/learner_k20.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)


import ceemx  # noqa: E402
from ceemx.evaluation import metrics as ev  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.identification.learning import make_problem  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from k100 import setup  # noqa: E402


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--K", type=int, default=20)
    p.add_argument("--T", type=int, default=256)
    p.add_argument("--B", type=int, default=16)
    p.add_argument("--state-noise", type=float, default=0.01)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out", type=str, default=None)
    args = p.parse_args(argv)
    true, prob, system, _ = setup(args.K, args.T, args.B, 42)
    key = jax.random.PRNGKey(7)
    states = prob.states + args.state_noise * jax.random.normal(key, prob.states.shape)
    eps_cb = ev.DynamicsErrorCallback(true)
    trainable = common.LORENZ_PARAMS_H
    problem, theta = make_problem(system, states, prob.data, trainable=trainable)
    offset = float(problem.offset(theta))
    learners = {
        "lbfgs-100": ceemx.LBFGSLearner(max_steps=100),
        "gncg-10x50-diagonal": ceemx.GaussNewtonCGLearner(max_steps=10, cg_max_steps=50),
        "gncg-10x50-identity": ceemx.GaussNewtonCGLearner(
            max_steps=10, cg_max_steps=50, scaling="identity"
        ),
    }
    out: dict = {
        "config": vars(args) | {"P": int(theta.shape[0]), "n": 3 * args.K},
        "eps_initial": eps_cb.error(system),
        "objective_initial": float(problem.value(theta)) - offset,
        "runs": [],
    }
    for rep in range(args.repeats):
        for name, learner in learners.items():
            load = os.getloadavg()[0]
            t = time.perf_counter()
            new, _, info = ceemx.learn(system, states, prob.data, learner, trainable=trainable)
            jax.block_until_ready(new)
            dt = time.perf_counter() - t
            run = {
                "learner": name,
                "call": rep,
                "time_s": dt,
                "objective": float(info.value_after) - offset,
                "eps": eps_cb.error(new),
                "steps": int(info.steps),
                "load": load,
            }
            out["runs"].append(run)
            print(json.dumps(run), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=2)
    return out


if __name__ == "__main__":
    main()
