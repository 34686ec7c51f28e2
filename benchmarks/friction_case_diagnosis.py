"""The friction case's stages one at a time (``friction_case.py``): what ``fit_hybrid`` weighs.

Stage 1 in full: the physics continuation over every default noise factor (no patience), each
fit's validation-tail and test free-run RMSE [mm] and parameters. Stage 2 at chosen factors:
the learned term (``fit_hybrid``'s: width 16, weight decay, ``JointLM``) trained for a fixed
number of iterations with no early stop, its validation RMSE every iteration, its test RMSE
every 10 and J — how long the term takes to leave its zero start (why ``fit_hybrid``'s patience
is long), how sharp its best is (why the refit watches its own free run), and whether the
validation tail follows the test record on the way.

Usage: ``python benchmarks/friction_case_diagnosis.py N_TRAIN PROCESS_NOISE TERM_AT ITERS``,
e.g. ``python benchmarks/friction_case_diagnosis.py 20000 1e-5 4,6 200`` (PROCESS_NOISE: the
guess's, a Python literal: ``1e-5`` or ``"(1e-8, 1e-5)"``; TERM_AT: indices into the factors).
Prints text (``benchmarks/results/friction_case_diagnosis.txt`` holds a run).
"""

from __future__ import annotations

import ast
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import ceemx  # noqa: E402
from ceemx.datasets import friction_sim  # noqa: E402
from ceemx.evaluation.hybrid_selection import NOISE_FACTORS, split_tail  # noqa: E402


def main() -> None:
    n_train, noise = int(sys.argv[1]), ast.literal_eval(sys.argv[2])
    term_at, iters = [int(k) for k in sys.argv[3].split(",")], int(sys.argv[4])
    rec = friction_sim.friction_positioning(0, n_train, 5000)
    guess = friction_sim.ViscousMass.guess(process_noise=noise)
    fit_part, val = split_tail(rec.train, rec.n_init)
    judge = ceemx.EarlyStopping(val, rec.n_init)

    def mm(m):
        return 1000 * float(ceemx.benchmark_score(m, rec.test, rec.n_init).rmse[0, 0])

    last, fits = None, []
    for k, f in enumerate(NOISE_FACTORS):
        start = guess if last is None else last.system
        model = ceemx.with_noise(start, process_noise=guess.process_noise.scaled(f))
        x0 = None if last is None else last.states
        res = ceemx.fit(model, fit_part, x0, solver=ceemx.JointLM(), max_epochs=200, diagnose=False)
        last = res
        fits.append(res)
        params = {p: round(float(getattr(res.system, p)), 3) for p in ("mass", "viscous", "offset")}
        print(
            f"k={k} f={f:.3g} val {1000 * judge.score(res.system):.3f} test {mm(res.system):.3f}"
            f" iters {len(res.history)} {params}",
            flush=True,
        )
    for k in term_at:
        physics, t0 = fits[k], time.perf_counter()
        stop = ceemx.EarlyStopping(val, rec.n_init, patience=10**6)
        tests = []

        def every_ten(info, tests=tests):
            if info.epoch % 10 == 0:
                tests.append((info.epoch, round(mm(info.system), 2)))
            return {}

        model = ceemx.hybrid(physics.system, fit_part, states=physics.states, dynamics=(1,))
        res = ceemx.fit(
            model, fit_part, physics.states, solver=ceemx.JointLM(),
            trainable=model.trainable("both"), log_prior=ceemx.weight_decay, max_epochs=iters,
            callbacks=[stop, every_ten], diagnose=False,
        )  # fmt: skip
        print(
            f"TERM at k={k}: {len(res.history)} iters, converged {res.converged}, "
            f"{time.perf_counter() - t0:.0f}s; best val it {stop.best_epoch} "
            f"{1000 * stop.best_rmse:.3f}"
        )
        best = stop.best_epoch
        print("  val", [(e, round(1000 * r, 2)) for e, r in stop.scores if e % 5 == 0 or e == best])
        print("  test", tests)
        print(
            "  J", [(h["epoch"], round(float(h["J"]))) for h in res.history if h["epoch"] % 10 == 0]
        )


if __name__ == "__main__":
    main()
