"""The real-benchmark fits of ``ceemx experiment real_data``, one ingredient at a time.

    python benchmarks/real_data_ablations.py noise NAME              # fixed vs learned noise
    python benchmarks/real_data_ablations.py process NAME SCALE      # the row, process noise SCALE
    python benchmarks/real_data_ablations.py bounded-tanks SCALE
    python benchmarks/real_data_ablations.py drives [old] [start] [offsets] [full]
    python benchmarks/real_data_ablations.py hybrid DATASET [TARGETS] [WIDTH] [DEPTH] [PRIOR_STD]
        [--observation] [--patience N]
    python benchmarks/real_data_ablations.py neural-start [DATASET] [SIGMA_W] [EPOCHS] [WIDTH]
        [DEPTH]

NAME / DATASET: ``cascaded_tanks``, ``silverbox`` or ``coupled_electric_drives`` (data:
``CEEMX_DATA``). Scores follow the official protocol (initial state from the first ``n_init``
test outputs, free run, RMSE on the rest).

``noise NAME``: the experiment's physics model fitted by JointLM with its fixed noise and with
``noise="learn"`` (the Laplace evidence), both scored. ``process NAME SCALE``: the experiment's
row for one dataset (physics, hybrid, neural, N4SID) with the model's process noise set to SCALE.
``bounded-tanks SCALE``: the tanks' physics fitted with its levels bounded below by 0 from the
start (``ceemx.hybrid(physics, data, dynamics=False, lower=0.0)``).

``drives``: each row one change to the coupled drives' model (CE-EM, JointLM, process noise
0.002, both sets' training records together) — ``old``: the former model and guess, y = √(v² +
ε), no offsets, f₀ = 1 Hz, ζ = 0.3; ``start``: the same from f₀ = 3.5 Hz, ζ = 0.15; ``offsets``:
+ the input offset u₀ and the sensor offset y₀; ``full``: + the sensor exponent p (the library's
``CoupledDrives``). Selection is by validation only: every row is fitted on samples [0, 320) of
both training records and scored on [320, 400), then refitted on [0, 400) and scored on the
test records, each with the default initial-state start and with two starts (``(1.0, None)``,
the experiment's setting for the drives). Written to
``benchmarks/results/real_data_ablations_drives.json`` (with the 1-min load).

``hybrid``: the experiment's hybrid (physics + learned term, its start and early stopping) with
one choice changed — TARGETS the state equations the learned term enters (``all``, indices such
as ``0,1``, or ``none`` with ``--observation``: the observation term alone), WIDTH × DEPTH of the
MLP (16 × 1), PRIOR_STD the weight decay's σ (1), ``--observation`` a learned observation term
too, ``--patience`` early stopping's; prints the best epoch and the validation RMSE (the test
records are not scored).

``neural-start``: N4SID (``fit_affine_sid``), that model refined by CE-EM (the joint method on
A, B, C, D; process noise SIGMA_W × std(y), default the experiment's) and the neural state-space
model started from it (EPOCHS joint iterations at most, early stopping as in the experiment),
each scored on the test records.

Backs: ``docs/results.md`` (CE-EM on the real datasets: what each ingredient contributed, the
coupled drives' structure, hybrid variants, the neural state-space model's start).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import hand_tuned as fits  # noqa: E402  (the former hand-tuned procedure)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from hand_tuned import Plan, Settings  # noqa: E402

import ceemx  # noqa: E402
from ceemx import datasets  # noqa: E402
from ceemx.datasets import REGISTRY  # noqa: E402
from ceemx.experiments import real_data  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
RESULTS_DRIVES = HERE / "results" / "real_data_ablations_drives.json"


def _plan(name: str, settings: Settings | None = None, **chosen) -> Plan:
    """The experiment's plan of dataset ``name``, its hand-chosen settings changed by ``chosen``."""
    plan = fits.make_plan(name, Settings() if settings is None else settings)
    return dataclasses.replace(plan, chosen=dataclasses.replace(plan.chosen, **chosen))


def _guess(plan: Plan, **fields):
    """The dataset's gray-box model at its physical guess, as the experiment builds it."""
    model = plan.entry.model
    fields = {**model.options, "process_noise": plan.chosen.process_noise, **fields}
    return model.factory(dtype=jnp.float64, **fields)


def _scores(system, ds, guess) -> dict[str, float]:
    return {
        k: round(
            float(
                ceemx.benchmark_score(
                    system, fits.inputs_for(guess, v), ds.n_init, scale=ds.score_scale
                ).rmse[0, 0]
            ),
            4,
        )  # fmt: skip
        for k, v in ds.tests.items()
    }


def noise(name: str) -> None:
    """Physics fits at the experiment's fixed noise and with the noise learned."""
    plan = _plan(name)
    ds = plan.data
    guess = _guess(plan)
    data = fits.inputs_for(guess, fits.training_data(plan))
    for mode in ("fixed", "learn"):
        t0 = time.perf_counter()
        res = ceemx.fit(guess, data, solver=ceemx.JointLM(), max_epochs=200, noise=mode)
        print(name, mode, f"{time.perf_counter() - t0:.1f} s", _scores(res.system, ds, guess))


def process(name: str, scale: float) -> None:
    """The experiment's row for one dataset with the process noise fixed at ``scale``.

    One candidate of the selection: the factor ``scale`` / the model's default noise (the
    neural model's linear noise is scaled by the same factor).
    """
    from ceemx.experiments.real_data_fits import Settings as RunSettings

    model = REGISTRY[name].model
    default = model.factory(dtype=jnp.float64, **model.options).process_noise.scale
    factor = scale / float(np.max(np.asarray(default)))
    settings = RunSettings(noise_factors=(factor,))
    result = real_data.run_dataset(name, settings=settings, method="joint", verbose=True)
    for row in result["rows"]:
        print(row[:6])


def bounded_tanks(scale: float) -> None:
    """The tanks' physics with its levels ≥ 0 from the start of the fit."""
    plan = _plan("cascaded_tanks")
    ds = plan.data
    guess = _guess(plan, process_noise=scale)
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


# ``drives``: the coupled drives' model, one change per row.

DRIVES_NAMES = ("a", "f0", "zeta", "gain", "u0", "y0", "power")
DRIVES_OLD = {"f0": 1.0, "zeta": 0.3}
#: row → (initial-guess overrides, parameters held at their defaults)
DRIVES_ROWS = {
    "old": (DRIVES_OLD, ("u0", "y0", "power")),
    "start": ({}, ("u0", "y0", "power")),
    "offsets": ({}, ("power",)),
    "full": ({}, ()),
}
DRIVES_STARTS = {"default": 1.0, "two": (1.0, None)}


def _drives_scores(system, records, n_init: int) -> dict[str, list[float]]:
    return {
        k: [
            round(float(r), 4)
            for r in np.asarray(
                ceemx.benchmark_score(system, records, n_init, warm_process_noise=w).rmse[:, 0]
            )
        ]
        for k, w in DRIVES_STARTS.items()
    }


def _drives_row(name: str, ds) -> dict:
    """Fit on [0, 320) → validation scores; refit on [0, 400) → test scores."""
    from ceemx.systems import CoupledDrives

    overrides, held = DRIVES_ROWS[name]
    n = ds.n_init
    train = ds.train
    out: dict = {"row": name, "held": list(held), "guess": overrides}
    for tag, data in (("validation", train[:, :320]), ("test", train)):
        guess = CoupledDrives.default(dtype=jnp.float64, process_noise=0.002, **overrides)
        t0 = time.perf_counter()
        res = ceemx.fit(
            guess,
            data,
            solver=ceemx.JointLM(),
            trainable=lambda s: tuple(getattr(s, k) for k in DRIVES_NAMES if k not in held),
            max_epochs=200,
            diagnose=False,
        )
        s = res.system
        out[f"{tag}_fit_s"] = round(time.perf_counter() - t0, 1)
        out[f"{tag}_epochs"] = len(res.history)
        out[f"{tag}_params"] = {k: round(float(getattr(s, k)), 4) for k in DRIVES_NAMES}
        if tag == "validation":
            out["validation"] = _drives_scores(s, train[:, 320 - n :], n)
        else:
            tests = [ds.tests["set1_low"], ds.tests["set2_high"]]
            per = [_drives_scores(s, t, n) for t in tests]
            out["test"] = {k: [p[k][0] for p in per] for k in DRIVES_STARTS}
    return out


def drives(rows: list[str]) -> None:
    """``drives [ROW ...]``: validation and test of each row, written to the JSON as it ends."""
    for r in rows:
        if r not in DRIVES_ROWS:
            raise SystemExit(f"unknown row {r!r}; choose from {', '.join(DRIVES_ROWS)}")
    ds = datasets.coupled_electric_drives()
    for r in rows:
        load0 = os.getloadavg()[0]
        entry = _drives_row(r, ds)
        entry["load_1min"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
        print(json.dumps(entry), flush=True)
        path = RESULTS_DRIVES
        saved = json.loads(path.read_text()) if path.exists() else {}  # rows run in parallel
        saved[r] = entry
        path.write_text(json.dumps(saved, indent=1) + "\n")


# ``hybrid``: variants of the experiment's hybrid, validation only.


def hybrid(argv: list[str]) -> None:
    """``hybrid DATASET [TARGETS] [WIDTH] [DEPTH] [PRIOR_STD] [--observation] [--patience N]``."""
    p = argparse.ArgumentParser(prog="real_data_ablations.py hybrid")
    p.add_argument("dataset", choices=real_data.DATASETS)
    p.add_argument("targets", nargs="?", default="all")
    p.add_argument("width", nargs="?", type=int, default=16)
    p.add_argument("depth", nargs="?", type=int, default=1)
    p.add_argument("prior_std", nargs="?", type=float, default=1.0)
    p.add_argument("--observation", action="store_true")
    p.add_argument("--patience", type=int, default=Settings().patience)
    a = p.parse_args(argv)
    special = {"all": True, "none": False}
    if a.targets in special:
        targets = special[a.targets]
    else:
        targets = tuple(int(c) for c in a.targets.split(","))
    settings = Settings(patience=a.patience)
    plan = _plan(a.dataset, settings, width=a.width, depth=a.depth, prior_std=a.prior_std)
    model = dataclasses.replace(plan.entry.model, targets=targets)
    plan = dataclasses.replace(plan, entry=dataclasses.replace(plan.entry, model=model))
    physics = None
    if plan.windowing is not None:  # its start is the full fit (its validation samples after it)
        physics, _ = fits.fit_graybox(plan, fits.training_data(plan), "joint", jnp.float64)
    start, _ = fits.learned_starts(plan, "joint", physics, None)
    _, info = fits.fit_learned(
        plan, start.system, start.states, neural=False, observation=a.observation
    )
    print(
        f"{a.dataset} targets {a.targets} {a.width}×{a.depth} σ {a.prior_std:g} observation "
        f"{a.observation} patience {a.patience}: best epoch {info['best_epoch']} of "
        f"{info['epochs']}, validation RMSE {info['validation_rmse']:.4g}",
        flush=True,
    )


# ``neural-start``: the linear baselines and the neural state-space model alone.


def neural_start(args: list[str]) -> None:
    """``neural-start [DATASET] [SIGMA_W] [EPOCHS] [WIDTH] [DEPTH]``."""
    from ceemx.baselines import fit_affine_sid

    name = args[0] if len(args) > 0 else "cascaded_tanks"
    plan = _plan(name)
    chosen = plan.chosen
    sigma_w = float(args[1]) if len(args) > 1 else chosen.linear_noise[0]
    plan = _plan(
        name,
        linear_noise=(sigma_w, chosen.linear_noise[1]),
        hybrid_epochs=int(args[2]) if len(args) > 2 else chosen.hybrid_epochs,
        width=int(args[3]) if len(args) > 3 else chosen.width,
        depth=int(args[4]) if len(args) > 4 else chosen.depth,
    )
    ds = plan.data
    train = fits.training_data(plan)
    tests = fits.test_records(plan)
    options = dict(plan.chosen.score_options)

    def score(model) -> dict:
        return {
            t: round(
                float(fits.score(model, test, ds.n_init, ds.score_scale, options)[0].rmse[0, 0]), 4
            )
            for t, test in tests.items()
        }

    t0 = time.perf_counter()
    n4sid = fit_affine_sid(train, state_dim=_guess(plan).state_dim)
    print(f"N4SID {score(n4sid)} ({time.perf_counter() - t0:.1f} s)", flush=True)
    refined, info = fits.refine_linear(n4sid, train, plan)
    print(f"linear CE-EM (σ_w {sigma_w:g}·std y) {score(refined.system)} {info}", flush=True)
    # the neural model starts from the linear fit of the fit part (the validation tail unseen),
    # as in the experiment's learned_starts; a record fitted in windows has its validation samples
    # after the fitted ones
    if plan.windowing is None:
        part = fits.split(plan)[0]
        refined, _ = fits.refine_linear(fit_affine_sid(part, state_dim=n4sid.state_dim), part, plan)
    neural, info = fits.fit_learned(plan, refined.system, refined.states, neural=True)
    print(f"neural state space {score(neural)} {info}", flush=True)


def main(argv: list[str]) -> None:
    """Run the subcommand ``argv[0]`` with the rest of ``argv``."""
    if not argv:
        raise SystemExit(__doc__)
    mode, args = argv[0], argv[1:]
    if mode == "noise":
        warnings.simplefilter("ignore")
        noise(args[0])
    elif mode == "process":
        warnings.simplefilter("ignore")
        process(args[0], float(args[1]))
    elif mode == "bounded-tanks":
        warnings.simplefilter("ignore")
        bounded_tanks(float(args[0]))
    elif mode == "drives":
        warnings.filterwarnings("ignore", category=UserWarning)
        drives(args or list(DRIVES_ROWS))
    elif mode == "hybrid":
        hybrid(args)
    elif mode == "neural-start":
        neural_start(args)
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
