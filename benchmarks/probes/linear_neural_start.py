"""The linear baselines and the neural state-space model of ``ceemx experiment benchmarks``, alone.

    python benchmarks/probes/linear_neural_start.py [DATASET] [SIGMA_W] [EPOCHS] [WIDTH] [DEPTH]

DATASET one of ``cascaded_tanks`` (default), ``silverbox``, ``coupled_electric_drives``. Prints
the test scores (official protocol) of N4SID (``fit_affine_sid``), of that model refined by CE-EM
(the joint method on A, B, C, D; process noise SIGMA_W × std(y), default 1e-3, observation noise
0.05 × std(y)) and of the neural state-space model started from it (an MLP of WIDTH × DEPTH,
default 16 × 1, in the transition; ``EPOCHS`` joint iterations at most, default 200, early
stopping on the training record's tail and its start fitted without that tail, as in the
experiment). Backs the iteration and noise-ratio
figures of docs/results.md ("CE-EM on real benchmarks", "What changed").
"""

import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import dataclasses  # noqa: E402

from ceemx import datasets  # noqa: E402
from ceemx.baselines import fit_affine_sid  # noqa: E402
from ceemx.experiments import benchmarks as bm  # noqa: E402

args = sys.argv[1:]
name = args[0] if len(args) > 0 else "cascaded_tanks"
sigma_w = float(args[1]) if len(args) > 1 else bm.LINEAR_NOISE[0]
settings = dataclasses.replace(
    bm.Settings(),
    hybrid_epochs=int(args[2]) if len(args) > 2 else bm.Settings().hybrid_epochs,
    width=int(args[3]) if len(args) > 3 else bm.Settings().width,
    depth=int(args[4]) if len(args) > 4 else bm.Settings().depth,
)
bm.LINEAR_NOISE = (sigma_w, bm.LINEAR_NOISE[1])
ds = getattr(datasets, name)()
train = bm._training_data(name, ds, settings)
tests = bm._test_records(ds, settings)


def score(model) -> dict:
    return {
        t: round(
            float(
                bm._score(model, test, ds.n_init, ds.score_scale, bm.SCORE_OPTIONS[name])[0].rmse[
                    0, 0
                ]
            ),
            4,
        )
        for t, test in tests.items()
    }


t0 = time.perf_counter()
n4sid = fit_affine_sid(train, state_dim=bm._model(name)().state_dim)
print(f"N4SID {score(n4sid)} ({time.perf_counter() - t0:.1f} s)", flush=True)
refined, info = bm._refine_linear(n4sid, train, settings)
print(f"linear CE-EM (σ_w {sigma_w:g}·std y) {score(refined.system)} {info}", flush=True)
# the neural model starts from the linear fit of the fit part (the validation tail unseen), as in
# the experiment's _learned_starts; Silverbox's validation samples lie after its fitted ones
if name != "silverbox":
    part = bm._split(name, ds, settings)[0]
    refined, _ = bm._refine_linear(fit_affine_sid(part, state_dim=n4sid.state_dim), part, settings)
neural, info = bm._fit_learned(name, refined.system, refined.states, ds, settings, neural=True)
print(f"neural state space {score(neural)} {info}", flush=True)
