"""Coupled drives: what each ingredient of CoupledDrives contributes, chosen by validation.

    python benchmarks/probes/drives_structure.py old start offsets full   # any subset of rows

Each row is one change to the model of ``ceemx experiment benchmarks`` (CE-EM, JointLM, process
noise 0.002, both sets' training records together):

- ``old``: the former model and guess — y = √(v² + ε), no offsets, f₀ = 1 Hz, ζ = 0.3;
- ``start``: the same model from the lightly damped guess f₀ = 3.5 Hz, ζ = 0.15;
- ``offsets``: + the input offset u₀ and the sensor offset y₀ (learned);
- ``full``: + the sensor exponent p, y = y₀ + (v² + ε)^{p/2} (the library default).

Selection is by **validation only**: every row is fitted on samples [0, 320) of both training
records and scored (official protocol, 10 outputs for the initial state) on [320, 400) (the
experiment's ``_split``); it is then refitted on [0, 400) and scored on the test records
[400, 500). Both scores are given with the default initial-state start
(``warm_process_noise=1.0``) and with two starts (``(1.0, None)``, the experiment's setting for
the drives). Writes ``benchmarks/results/drives_structure.json`` (with the 1-min load).
"""

from __future__ import annotations

import json
import os
import sys
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx import datasets  # noqa: E402
from ceemx.systems import CoupledDrives  # noqa: E402

NAMES = ("a", "f0", "zeta", "gain", "u0", "y0", "power")
OLD = {"f0": 1.0, "zeta": 0.3}
#: row → (initial-guess overrides, parameters held at their defaults)
ROWS = {
    "old": (OLD, ("u0", "y0", "power")),
    "start": ({}, ("u0", "y0", "power")),
    "offsets": ({}, ("power",)),
    "full": ({}, ()),
}
STARTS = {"default": 1.0, "two": (1.0, None)}


def _scores(system, records, n_init: int) -> dict[str, list[float]]:
    return {
        k: [
            round(float(r), 4)
            for r in np.asarray(
                ceemx.benchmark_score(system, records, n_init, warm_process_noise=w).rmse[:, 0]
            )
        ]
        for k, w in STARTS.items()
    }


def row(name: str, ds) -> dict:
    """Fit on [0, 320) → validation scores; refit on [0, 400) → test scores."""
    overrides, held = ROWS[name]
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
            trainable=lambda s: tuple(getattr(s, k) for k in NAMES if k not in held),
            max_epochs=200,
            diagnose=False,
        )
        s = res.system
        out[f"{tag}_fit_s"] = round(time.perf_counter() - t0, 1)
        out[f"{tag}_epochs"] = len(res.history)
        out[f"{tag}_params"] = {k: round(float(getattr(s, k)), 4) for k in NAMES}
        if tag == "validation":
            out["validation"] = _scores(s, train[:, 320 - n :], n)
        else:
            tests = [ds.tests["set1_low"], ds.tests["set2_high"]]
            per = [_scores(s, t, n) for t in tests]
            out["test"] = {k: [p[k][0] for p in per] for k in STARTS}
    return out


def main(rows: list[str]) -> None:
    for r in rows:
        if r not in ROWS:
            raise SystemExit(f"unknown row {r!r}; choose from {', '.join(ROWS)}")
    warnings.filterwarnings("ignore", category=UserWarning)
    ds = datasets.coupled_electric_drives()
    path = Path(__file__).resolve().parents[1] / "results" / "drives_structure.json"
    for r in rows:
        load0 = os.getloadavg()[0]
        entry = row(r, ds)
        entry["load_1min"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
        print(json.dumps(entry), flush=True)
        saved = json.loads(path.read_text()) if path.exists() else {}  # rows run in parallel
        saved[r] = entry
        path.write_text(json.dumps(saved, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:] or list(ROWS))
