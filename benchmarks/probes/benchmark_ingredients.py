"""What each ingredient of the real-benchmark fits contributes (one setting changed at a time).

    python benchmarks/probes/benchmark_ingredients.py noise silverbox   # fixed vs learned noise
    python benchmarks/probes/benchmark_ingredients.py process silverbox 1e-3   # the whole row
    python benchmarks/probes/benchmark_ingredients.py bounded-tanks 0.05
    python benchmarks/probes/benchmark_ingredients.py tanks [VARIANT ...] [--test | --test-only]

``noise NAME``: the physics model of ``ceemx experiment benchmarks`` fitted by JointLM with the
experiment's noise (``noise="fixed"``) and with ``noise="learn"`` (the Laplace evidence), both
scored by the official protocol. ``process NAME SCALE``: the experiment's row for one dataset
(physics, hybrid, learned alone, N4SID) with the model's process noise set to SCALE.
``bounded-tanks SCALE``: the tanks' physics model fitted with its levels bounded below by 0 from
the start (``ceemx.hybrid(physics, data, dynamics=False, lower=0.0)``).
``tanks [VARIANT ...] [--test | --test-only]``: the tanks' physics model with one ingredient
changed at a time (:data:`TANK_VARIANTS`; default all), fitted by JointLM on the experiment's fit
part of the training record and scored (official protocol) on its held-out tail — the validation
score that selects; with ``--test`` also fitted on the whole training record and scored on the
test record; each with the range of the hidden upper-tank level over the free run.

Backs: ``docs/results.md`` ("What each ingredient contributed": Silverbox 1.785 → 0.933 mV with
process noise 1e-3 → 1e-4, drives 0.297 / 0.739 → 0.229 / 0.388 with 0.02 → 0.002, learned noise
2.43 mV and 0.411 V, the bounded tanks fit 0.429 V — the tanks' figures with ``CascadedTanks``
before its lower overflow and pump dead zone, commit ccfd11e; "The tanks' structure": every
``tanks`` row).
"""

from __future__ import annotations

import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import ceemx  # noqa: E402
from ceemx import datasets  # noqa: E402
from ceemx.experiments import benchmarks as bm  # noqa: E402
from ceemx.models.constraints import param  # noqa: E402
from ceemx.systems.gray_box import _AbstractSISO, smooth_power, soft_min  # noqa: E402


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


class _Tanks(_AbstractSISO):
    """``CascadedTanks`` with its two new ingredients switchable (``CascadedTanks`` = both on)."""

    k1: jax.Array = param(positive=True)
    k2: jax.Array = param(positive=True)
    k3: jax.Array = param(positive=True)
    k4: jax.Array = param(positive=True)
    h: jax.Array = param(positive=True)
    phi: jax.Array = param(lower=0.0, upper=1.0)
    h2: jax.Array = param(positive=True)
    offset: jax.Array = param()
    u0: jax.Array = param()
    a1: jax.Array = param(lower=0.1, upper=1.0)
    a2: jax.Array = param(lower=0.1, upper=1.0)
    lower_overflow: bool = eqx.field(static=True, default=True)
    dead_zone: bool = eqx.field(static=True, default=True)

    @property
    def state_dim(self) -> int:
        return 2

    def vector_field(self, x, u, t):
        s1, s2 = smooth_power(x[0], self.a1), smooth_power(x[1], self.a2)
        inflow = self.k4 * (u[0] - self.u0)
        if self.dead_zone:
            inflow = self.k4 * jax.nn.softplus(5.0 * (u[0] - self.u0)) / 5.0
        gate = jax.nn.sigmoid(5.0 * (x[0] - self.h))
        into_lower = self.k2 * s1 + self.phi * inflow * gate
        if self.lower_overflow:
            into_lower = into_lower * (1 - jax.nn.sigmoid(10.0 * (x[1] + self.offset - self.h2)))
        return jnp.stack([inflow * (1 - gate) - self.k1 * s1, into_lower - self.k3 * s2])

    def observe(self, x, u, t):
        return soft_min(x[1:] + self.offset, 10.0, 10.0)


_PARAMS = ("k1", "k2", "k3", "k4", "h", "phi", "h2", "offset", "u0", "a1", "a2")

#: name → (process noise, switches of ``_Tanks``, fields kept at their default, fields fixed in a
#: first stage): "before" is the model and setting before the lower overflow and the pump's dead
#: zone; "chosen" the library's CascadedTanks with the experiment's setting (best validation).
_LINEAR = dict(dead_zone=False)
TANK_VARIANTS: dict[str, tuple[float, dict, tuple[str, ...], tuple[str, ...]]] = {
    "before": (0.05, dict(lower_overflow=False, dead_zone=False), ("h2",), ()),
    "lower-overflow": (0.05, _LINEAR, (), ()),
    "lower-overflow-torricelli": (0.05, _LINEAR, ("a1", "a2"), ()),
    "lower-overflow-no-offset": (0.05, _LINEAR, ("offset",), ()),
    "lower-overflow-h10": (0.05, _LINEAR, ("h",), ()),
    "lower-overflow-0.02": (0.02, _LINEAR, (), ()),
    "lower-overflow-0.01": (0.01, _LINEAR, (), ()),
    "lower-overflow-0.005": (0.005, _LINEAR, (), ()),
    "lower-overflow-0.002": (0.002, _LINEAR, (), ()),
    "lower-overflow-torricelli-0.005": (0.005, _LINEAR, ("a1", "a2"), ()),
    "no-lower-overflow-0.005": (0.005, dict(lower_overflow=False, dead_zone=False), ("h2",), ()),
    "dead-zone-0.005": (0.005, {}, (), ()),
    "dead-zone-0.005-staged": (0.005, {}, (), ("a1", "a2")),
    "dead-zone-0.002": (0.002, {}, (), ()),
    "chosen": (0.001, {}, (), ()),
}


def _tanks_guess(scale, switches):
    lib = bm._model("cascaded_tanks")(dtype=jnp.float64, process_noise=scale)
    guess = _Tanks(
        **{k: getattr(lib, k) for k in _PARAMS},
        **switches,
        dt=lib.dt,
        substeps=lib.substeps,
        process_noise=lib.process_noise,
        obs_noise=lib.obs_noise,
    )
    if switches == {}:  # the probe's model is the library's
        x, u = jnp.array([9.0, 9.9]), jnp.array([3.0])
        assert jnp.allclose(guess.vector_field(x, u, 0), lib.vector_field(x, u, 0), rtol=1e-12)
    return guess


def tanks(names: list[str], test: bool, validation: bool = True) -> None:
    """Validation (fit part → held-out tail) and, with ``test``, test (whole record → test)."""
    from ceemx.identification.problem import trainable_mask

    ds = datasets.cascaded_tanks()
    fit_data, val = bm._split("cascaded_tanks", ds, bm.Settings())
    runs = [("validation", fit_data, val)] * validation
    runs += [("test", ds.train, ds.tests["test"])] * test

    def fit(guess, data, fixed):
        free = eqx.tree_at(
            lambda m: [getattr(m, n) for n in fixed], trainable_mask(guess), [False] * len(fixed)
        )
        return ceemx.fit(guess, data, solver=ceemx.JointLM(), max_epochs=200, trainable=free)

    for name in names or list(TANK_VARIANTS):
        scale, switches, fixed, staged = TANK_VARIANTS[name]
        guess = _tanks_guess(scale, switches)
        for part, data, record in runs:
            t0 = time.perf_counter()
            start = fit(guess, data, (*fixed, *staged)).system if staged else guess
            system = fit(start, data, fixed).system
            s = ceemx.benchmark_score(system, record, ds.n_init)
            params = {k: round(float(getattr(system, k)), 4) for k in _PARAMS}
            print(
                f"{name} {part}: {float(s.rmse[0, 0]):.4f} V, hidden level in "
                f"[{float(s.x_sim[..., 0].min()):.3g}, {float(s.x_sim[..., 0].max()):.3g}] V, "
                f"fit {time.perf_counter() - t0:.0f} s; {params}",
                flush=True,
            )


if __name__ == "__main__":
    warnings.simplefilter("ignore")
    mode, *args = sys.argv[1:]
    if mode == "noise":
        noise(args[0])
    elif mode == "process":
        process(args[0], float(args[1]))
    elif mode == "bounded-tanks":
        bounded_tanks(float(args[0]))
    elif mode == "tanks":
        ceemx.enable_compilation_cache()  # one compilation per model structure and record length
        flags = {"--test", "--test-only"}
        only = "--test-only" in args
        tanks([a for a in args if a not in flags], "--test" in args or only, not only)
    else:
        raise SystemExit(__doc__)
