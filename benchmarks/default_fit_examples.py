"""The default fitting path on the repository's examples, against the solver each one names.

``ceemx.fit(model, data)`` (the library's choice) beside the fit as the example writes it, on:

- ``custom_systems``: the mass–spring–damper of ``docs/custom_systems.md`` (4 records of 100
  samples, dt 0.1, σ_w 1e-3, σ_v 0.01, start k = 1, c = 2; ``JointLM``, ``max_epochs=50``);
- ``issue_msd``: the same model as issue 40 quotes it (2 records of 2 000 samples, dt 0.05,
  σ_w 1e-2, σ_v 0.01 given as they are, start k = 3, c = 0.8) against Algorithm 1
  (``Alternating``, what ``fit(model, data)`` ran before the default path);
- ``readme``: the README's coupled-Lorenz example (``JointLM``, its ``trainable`` and start
  states; simulated without process noise);
- ``hybrid_physics``: the physics stage of ``examples/hybrid_duffing.py`` (``JointLM``,
  ``max_epochs=50``), scored by the free-run RMSE on its held-out record;
- ``silverbox``: ``examples/graybox_from_csv.py`` (windows of the Silverbox estimation record,
  ``JointLM``, 30 iterations), scored by the official multisine-test free-run RMSE (needs the
  Silverbox CSV: ``CEEMX_DATA`` or ``../shared/data``; skipped without it).

Per fit: the estimates with their standard errors and 95 % intervals (the summary's rows), whether
each interval holds the truth (where one is known), ``converged``, the solver line of the summary,
the wall time (the first fit of each model compiles: every case runs the named fit first, then the
default, then both again; the second pair's times are the steady ones) and the score.

Usage: ``python benchmarks/default_fit_examples.py [--cases ...] [--out
benchmarks/results/default_fit_examples.json]``.

Backs: issue 40, "the default path on examples/ and the docs' examples: the same or better
answers, timings beside".
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time
import warnings

import jax
import jax.numpy as jnp

import ceemx
from ceemx.identification.analysis.summary import parameter_rows

jax.config.update("jax_enable_x64", True)
ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples"))


def _rows(result) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rows, _ = parameter_rows(result)
    return {r.name: [r.estimate, r.se, r.lower, r.upper] for r in rows}


def _record(result, wall: float, truth: dict | None, score: float | None) -> dict:
    rows = _rows(result)
    head = [line for line in str(result.summary(uncertainty=False)).splitlines()]
    solver = next((line for line in head if line.startswith(("solver", "  "))), "")
    rec = {
        "rows": rows,
        "converged": bool(result.converged),
        "wall_s": wall,
        "title": head[0],
        "solver_line": solver.strip(),
        "score": score,
    }
    if getattr(result, "choice", None) is not None:
        rec["stages"] = [
            [type(s.solver).__name__, s.noise, s.epochs, s.converged, s.seconds]
            for s in result.choice.stages
        ]
    if truth:
        rec["covers"] = {p: bool(rows[p][2] <= v <= rows[p][3]) for p, v in truth.items()}
    return rec


def _timed(run):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        result = run()
        return result, time.perf_counter() - t0


# --- cases: each returns (named fit, default fit, truth or None, score function or None) --------


def _msd(dt, B, T, pn, on, start, seed=0):
    import default_fit_bank as bank

    def build(k, c):
        return bank.MassSpringDamper(
            k=k, c=c, dt=dt, hold="foh", substeps=2, process_noise=pn, obs_noise=on
        )

    true = build(4.0, 0.5)
    force = jax.random.normal(jax.random.PRNGKey(seed), (B, T, 1))
    u = ceemx.data.trajectories.foh_inputs(force)
    _, data = ceemx.simulate(true, jax.random.PRNGKey(seed + 1), jnp.zeros((B, 2)), T, u)
    return build(*start), data


def custom_systems():
    guess, data = _msd(0.1, 4, 100, 1e-3, 0.01, (1.0, 2.0))
    return (
        lambda: ceemx.fit(guess, data, solver=ceemx.JointLM(), max_epochs=50),
        lambda: ceemx.fit(guess, data, max_epochs=50),
        {"k": 4.0, "c": 0.5},
        None,
    )


def issue_msd():
    guess, data = _msd(0.05, 2, 2000, 1e-2, 0.01, (3.0, 0.8))
    return (
        lambda: ceemx.fit(guess, data, solver=ceemx.Alternating()),
        lambda: ceemx.fit(guess, data),
        {"k": 4.0, "c": 0.5},
        None,
    )


def readme():
    from ceemx.systems import (
        CoupledLorenz,
        initial_states,
        random_coupling,
        random_observation_matrix,
    )

    K = 2
    kH, kC, kx, ky, kg = jax.random.split(jax.random.PRNGKey(0), 5)
    C = random_observation_matrix(kC, K)
    H = random_coupling(kH, K)
    true = CoupledLorenz(jnp.full(K, 10.0), jnp.full(K, 28.0), jnp.full(K, 8 / 3), C, H=H)
    x_true, data = ceemx.simulate(true, ky, initial_states(kx, 4, K), 128, process_noise=False)
    guess = CoupledLorenz(true.sigma * 1.05, true.rho * 0.95, true.beta * 1.05, C, H=true.H * 0.9)
    x0 = x_true + jax.random.normal(kg, x_true.shape)

    def where(s):
        return (s.sigma, s.rho, s.beta, s.H)

    truth = {
        f"{p}[{i}]": float(getattr(true, p)[i]) for p in ("sigma", "rho", "beta") for i in (0, 1)
    }
    return (
        lambda: ceemx.fit(guess, data, x0, solver=ceemx.JointLM(), trainable=where),
        lambda: ceemx.fit(guess, data, x0, trainable=where),
        truth,
        None,
    )


def hybrid_physics():
    import hybrid_duffing as ex

    truth_sys = ex.Oscillator(1.0, 0.3, 1.0, dt=ex.DT, process_noise=1e-3, obs_noise=0.01)
    key_train, key_test = jax.random.split(jax.random.PRNGKey(0))
    train, _ = ex.record(truth_sys, key_train, 1200, (0.5, 0.9, 1.7, 2.9), 3.0)
    test, _ = ex.record(truth_sys, key_test, 600, (0.6, 1.3, 2.3), 2.5)
    guess = ex.Oscillator(1.3, 0.2, 0.0, dt=ex.DT, process_noise=1e-3, obs_noise=0.01)

    def score(result):
        return float(ceemx.benchmark_score(result.system, test, 20).rmse[0, 0])

    return (
        lambda: ceemx.fit(guess, train, solver=ceemx.JointLM(), max_epochs=50, diagnose=False),
        lambda: ceemx.fit(guess, train, max_epochs=50, diagnose=False),
        None,
        score,
    )


def silverbox():
    import graybox_from_csv as ex

    path = ex.find_csv(None)
    u, y = ex.read_csv(path)
    seg = slice(ex.ESTIMATION[0], ex.ESTIMATION[0] + 4096)
    train = ceemx.data.trajectories.foh_inputs(ceemx.Trajectories.from_arrays(y[seg], u[seg]))
    windows = train.windows(512, 256)
    guess = ex.initial_guess(y[seg], u[seg])
    model = ex.Silverbox(
        *(jnp.asarray(guess[name]) for name in ("m", "d", "k1", "k3", "u0")),
        dt=1.0,
        hold="foh",
        substeps=2,
        process_noise=jnp.array([1e-4, 1e-4]),
        obs_noise=1e-3,
    )
    test_slice = slice(ex.TEST[0], ex.TEST[1])
    test = ceemx.data.trajectories.foh_inputs(
        ceemx.Trajectories.from_arrays(y[test_slice], u[test_slice])
    )

    def score(result):
        return float(
            ceemx.benchmark_score(result.system, test, ex.N_INIT, scale=1000.0).rmse_overall[0]
        )

    return (
        lambda: ceemx.fit(model, windows, solver=ceemx.JointLM(), max_epochs=30),
        lambda: ceemx.fit(model, windows, max_epochs=30),
        None,
        score,
    )


CASES = {
    "custom_systems": custom_systems,
    "issue_msd": issue_msd,
    "readme": readme,
    "hybrid_physics": hybrid_physics,
    "silverbox": silverbox,
}


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def main() -> None:
    """Run the cases and write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--out", default="benchmarks/results/default_fit_examples.json")
    args = ap.parse_args()
    path = ROOT / args.out
    out = json.loads(path.read_text()) if path.exists() else {}
    out["cpus"] = os.cpu_count()
    for name in args.cases:
        try:
            named, default, truth, score = CASES[name]()
        except FileNotFoundError as e:
            print(f"{name}: skipped ({e})", flush=True)
            continue
        case: dict = {"date": time.strftime("%Y-%m-%d %H:%M"), "uptime": _uptime()}
        for rep in ("first", "steady"):
            for label, run in (("named", named), ("default", default)):
                result, wall = _timed(run)
                rec = _record(result, wall, truth, score(result) if score else None)
                rec["load"] = os.getloadavg()[0]
                case[f"{label}_{rep}"] = rec
                print(name, label, rep, json.dumps(rec, default=float)[:600], flush=True)
        out[name] = case
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()
