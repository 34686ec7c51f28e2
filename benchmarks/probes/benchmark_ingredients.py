"""What each ingredient of the real-benchmark fits contributes (one setting changed at a time).

    python benchmarks/probes/benchmark_ingredients.py noise silverbox   # fixed vs learned noise
    python benchmarks/probes/benchmark_ingredients.py process silverbox 1e-3   # the whole row
    python benchmarks/probes/benchmark_ingredients.py bounded-tanks 0.05

``noise NAME``: the physics model of ``ceemx experiment benchmarks`` fitted by JointLM with the
experiment's noise (``noise="fixed"``) and with ``noise="learn"`` (the Laplace evidence), both
scored by the official protocol. ``process NAME SCALE``: the experiment's row for one dataset
(physics, hybrid, learned alone, N4SID) with the model's process noise set to SCALE.
``bounded-tanks SCALE``: the tanks' physics model fitted with its levels bounded below by 0 from
the start (``ceemx.hybrid(physics, data, dynamics=False, lower=0.0)``).

Backs: ``docs/results.md`` ("What each ingredient contributed": Silverbox 1.785 → 0.933 mV with
process noise 1e-3 → 1e-4, drives 0.297 / 0.739 → 0.229 / 0.388 with 0.02 → 0.002, learned noise
2.43 mV and 0.411 V, the bounded tanks fit 0.429 V).
"""

from __future__ import annotations

import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import ceemx  # noqa: E402
from ceemx import datasets  # noqa: E402
from ceemx.experiments import benchmarks as bm  # noqa: E402


def _scores(system, ds, guess) -> dict[str, float]:
    return {
        k: round(
            float(
                ceemx.benchmark_score(
                    system, bm._inputs_for(guess, v), ds.n_init, scale=ds.score_scale
                ).rmse[0, 0]
            ),
            4,
        )  # fmt: skip
        for k, v in ds.tests.items()
    }


def noise(name: str) -> None:
    """Physics fits at the experiment's fixed noise and with the noise learned."""
    ds = getattr(datasets, name)()
    train = bm._training_data(name, ds, bm.Settings())
    guess = bm._model(name)(dtype=jnp.float64, **bm.MODEL_OPTIONS[name])
    data = bm._inputs_for(guess, train)
    for mode in ("fixed", "learn"):
        t0 = time.perf_counter()
        res = ceemx.fit(guess, data, solver=ceemx.JointLM(), max_epochs=200, noise=mode)
        print(name, mode, f"{time.perf_counter() - t0:.1f} s", _scores(res.system, ds, guess))


def process(name: str, scale: float) -> None:
    """The experiment's row for one dataset with the process noise set to ``scale``."""
    bm.MODEL_OPTIONS[name] = {**bm.MODEL_OPTIONS[name], "process_noise": scale}
    result = bm.run_dataset(name, settings=bm.Settings(), method="joint", verbose=True)
    for row in result["rows"]:
        print(row[:6])


def bounded_tanks(scale: float) -> None:
    """The tanks' physics with its levels ≥ 0 from the start of the fit."""
    ds = datasets.cascaded_tanks()
    guess = bm._model("cascaded_tanks")(dtype=jnp.float64, process_noise=scale)
    model = ceemx.hybrid(guess, ds.train, dynamics=False, lower=0.0)
    res = ceemx.fit(
        model,
        ds.train,
        solver=ceemx.JointLM(),
        max_epochs=200,
        trainable=model.trainable("physics"),
    )
    score = ceemx.benchmark_score(res.system, ds.tests["test"], ds.n_init)
    print(f"process noise {scale}: test RMSE {float(score.rmse[0, 0]):.4f} V, lowest hidden "
          f"level {float(score.x_sim[..., 0].min()):.3g} V")  # fmt: skip


if __name__ == "__main__":
    warnings.simplefilter("ignore")
    mode, *args = sys.argv[1:]
    if mode == "noise":
        noise(args[0])
    elif mode == "process":
        process(args[0], float(args[1]))
    elif mode == "bounded-tanks":
        bounded_tanks(float(args[0]))
    else:
        raise SystemExit(__doc__)
