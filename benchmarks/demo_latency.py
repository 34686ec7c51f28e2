"""`ceemx demo` wall time, cold and with a warm compilation cache, this tree against an earlier one.

    python benchmarks/demo_latency.py [--reps 3] [--before-src /tmp/before/src] [--out FILE]

Each repetition runs, for this tree and then (with ``--before-src``) the earlier tree on
``PYTHONPATH``: an empty persistent compilation cache folder, ``python -m ceemx demo`` twice —
the first run compiles everything and fills the cache (cold), the second reads it (warm). The
wall time of each whole process (imports, compilation, identification, plot) and the 1-min load
before it are recorded; medians over the repetitions. ``MPLBACKEND=Agg``.

Backs: ``benchmarks/README.md`` ("Issue 23 on a quiet machine": the demo row).
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


def main() -> None:
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
