"""`ceemx demo` wall time, cold and with a warm compilation cache; its joint iterations alone.

    python benchmarks/demo_latency.py [--reps 3] [--before-src /tmp/before/src] [--out FILE]
    python benchmarks/demo_latency.py iterations     # the demo's joint iterations, wall/CPU

Each repetition runs, for this tree and then (with ``--before-src``) the earlier tree on
``PYTHONPATH``: an empty persistent compilation cache folder, ``python -m ceemx demo`` twice —
the first run compiles everything and fills the cache (cold), the second reads it (warm). The
wall time of each whole process (imports, compilation, identification, plot) and the 1-min load
before it are recorded; medians over the repetitions. ``MPLBACKEND=Agg``. Writes
``benchmarks/results/demo_latency.json``.

``iterations``: the demo problem (6 coupled Lorenz, B = 4, T = 128, warm start), 7 JointLM
iterations called directly (the first compiles), wall and process CPU seconds of each. Run it on
an idle machine and beside CPU hogs (``yes > /dev/null &`` once per core), with all CPUs and
pinned (``taskset -c 0``, as ``ceemx --threads 1``): XLA's thread hand-offs stall when the cores
are oversubscribed.

Backs: ``benchmarks/README.md`` (the demo rows, busy machines).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent


def run_demo(cache: pathlib.Path, out: pathlib.Path, src: str | None) -> dict:
    env = dict(os.environ, CEEMX_COMPILATION_CACHE=str(cache), MPLBACKEND="Agg")
    if src:
        env["PYTHONPATH"] = src
    else:
        env.pop("PYTHONPATH", None)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "ceemx", "demo", "--out", str(out)],
        env=env,
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-2000:])
    return {"s": time.perf_counter() - t0, "load": load}


def iterations() -> None:
    """``iterations``: the demo's joint iterations, wall/CPU seconds each."""
    import resource

    import jax

    jax.config.update("jax_enable_x64", True)
    import ceemx
    from ceemx.experiments import common
    from ceemx.identification.initialize import warm_start
    from ceemx.identification.problem import FitProblem
    from ceemx.lib.tree import trace_numbers
    from ceemx.models import with_noise

    def cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    true = common.true_lorenz(6, key=jax.random.PRNGKey(4), obs_noise=0.01)
    pr = common.lorenz_problem(0, true, B=4, T=128, sigma_w=0.0, sigma_v=0.01, coupling=True)
    system = with_noise(pr.init_system, 0.01, 0.01)
    x0 = warm_start(system, pr.data)
    solver = trace_numbers(ceemx.JointLM(), x0.dtype)
    problem, theta = FitProblem.create(system, pr.data, trainable=common.LORENZ_PARAMS_H)
    state = solver.init(problem, theta, x0, jax.random.PRNGKey(0))
    out = []
    for _ in range(7):
        t0, c0 = time.perf_counter(), cpu()
        state, _ = solver.step(problem, state)
        jax.block_until_ready(state.states)
        out.append(f"{time.perf_counter() - t0:.2f}/{cpu() - c0:.2f}")
    print("wall/cpu per iteration (s):", " ".join(out))


def main() -> None:
    if sys.argv[1:2] == ["iterations"]:
        iterations()
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--before-src", default=None)
    ap.add_argument("--out", default=str(HERE / "results" / "demo_latency.json"))
    args = ap.parse_args()
    trees = [("after", None)] + ([("before", args.before_src)] if args.before_src else [])
    runs: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.reps):
            for name, src in trees:
                cache = pathlib.Path(tmp) / f"cache_{name}"
                shutil.rmtree(cache, ignore_errors=True)
                out = pathlib.Path(tmp) / f"demo_{name}"
                rec = {"rep": rep, "tree": name}
                for kind in ("cold", "warm"):
                    rec[kind] = run_demo(cache, out, src)
                runs.append(rec)
                print(rec, flush=True)
    summary = {
        name: {
            kind: statistics.median(r[kind]["s"] for r in runs if r["tree"] == name)
            for kind in ("cold", "warm")
        }
        for name, _ in trees
    }
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "before_src": args.before_src,
        "summary": summary,
        "runs": runs,
    }
    path = pathlib.Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
