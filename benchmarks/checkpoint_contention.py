"""Checkpoints under contention and on full disks: nothing lost.

    python benchmarks/checkpoint_contention.py [--runs 20] [--disk-runs 10] [--no-lock]

**Concurrent writers.** Each run starts two processes that fit the same small problem (a
2-state linear system, B = 2, T = 40, ``Alternating``, 150 epochs, one save per epoch) into the
same checkpoint folder at the same instant (both compile first, then wait for a common start
time). Expected: one fit finishes, the other is refused at once with a ``CheckpointError`` that
names the first's pid; the folder then holds a checkpoint that loads (sha256, fingerprint,
finiteness) and equals the finished fit (θ bitwise, 150 epochs); a third fit from the folder
resumes it and returns that θ. ``--no-lock`` replaces the lock by nothing, to show the failure it
prevents (crashed writers, as before the lock).

**Full disks.** Each run fits uninterrupted, then fits with a checkpoint while the disk "fills" at
epoch k = 2..11 (``os.fdopen`` returning a file whose writes raise ``ENOSPC``, as in
``tests/test_reliability.py``): the fit must fail with a ``CheckpointError`` saying "No space
left on device", leave exactly ``latest.json`` and ``state-<k-1>.eqx`` (no temporaries), and a
resume once the disk has space must end bitwise equal to the uninterrupted fit.

Prints one line per run and a summary; exit status 1 when anything was lost. Backs
``docs/guarantees.md`` ("Checkpoints": "Two writers" and "Full disks").
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import subprocess
import sys
import tempfile
import time

_WORKER = r"""
EPOCHS = 150
import contextlib, json, os, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import ceemx
from ceemx.infra import checkpoint as ckpt

folder, start_at, no_lock = sys.argv[1], float(sys.argv[2]), sys.argv[3] == "1"
if no_lock:
    ckpt.lock = lambda folder: contextlib.nullcontext()
system, data, x0 = PROBLEM()
solver = ceemx.Alternating(rtol=0.0, atol=0.0)
ceemx.fit(system, data, x0, solver=solver, max_epochs=2, progress=False, diagnose=False)
time.sleep(max(0.0, start_at - time.time()))
try:
    res = ceemx.fit(system, data, x0, solver=solver, max_epochs=EPOCHS, progress=False,
                    diagnose=False, checkpoint=folder)
    print(json.dumps({"ok": True, "pid": os.getpid(), "theta": np.asarray(res.theta).tolist(),
                      "epochs": len(res.history)}))
except Exception as err:
    print(json.dumps({"ok": False, "pid": os.getpid(), "error": f"{type(err).__name__}: {err}"}))
"""


EPOCHS = 150


def problem():
    """A 2-state linear system and its data: cheap to compile and to step."""
    import jax
    import numpy as np

    import ceemx
    from ceemx.systems import LinearSystem

    a = np.array([[0.9, 0.1], [-0.1, 0.9]])
    b, c, d = np.ones((2, 1)), np.eye(2)[:1], np.zeros((1, 1))
    true = LinearSystem(a, c, b, d, process_noise=0.1, obs_noise=0.1)
    u = np.random.default_rng(1).standard_normal((2, 40, 1))
    _, data = ceemx.simulate(true, jax.random.PRNGKey(0), np.zeros((2, 2)), 40, u)
    guess = LinearSystem(0.8 * a, c, b, d, process_noise=0.1, obs_noise=0.1)
    return guess, data, np.zeros((2, 40, 2))


def worker_source() -> str:
    import inspect

    return (
        "def PROBLEM():\n"
        + "\n".join("    " + line for line in inspect.getsource(problem).splitlines()[1:])
        + "\n"
        + _WORKER
    )


def contention_run(i: int, no_lock: bool) -> tuple[bool, str]:
    from ceemx.infra import checkpoint as ckpt

    with tempfile.TemporaryDirectory() as tmp:
        folder = os.path.join(tmp, "ckpt")
        start_at = time.time() + 12.0  # both compile first (≈ 4–8 s each on 2 busy cores)
        procs = [
            subprocess.Popen(
                [sys.executable, "-c", worker_source(), folder, str(start_at), str(int(no_lock))],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for _ in range(2)
        ]
        outs = []
        for p in procs:
            out, err = p.communicate(timeout=300)
            lines = [line for line in out.splitlines() if line.startswith("{")]
            outs.append(json.loads(lines[-1]) if lines else {"ok": False, "error": err[-300:]})
        done = [o for o in outs if o["ok"]]
        refused = [o for o in outs if not o["ok"]]
        problems = []
        if len(done) != 1:
            problems.append(f"{len(done)} fits finished")
        for o in refused:
            if "is in use by another fit" not in o["error"] or (
                done and f"pid {done[0]['pid']} " not in o["error"]
            ):
                problems.append(f"refusal: {o['error'][:160]}")
        if done:
            meta = json.loads(open(os.path.join(folder, "latest.json")).read())
            if meta["epoch"] != done[0]["epochs"]:
                problems.append(f"checkpoint epoch {meta['epoch']} != {done[0]['epochs']}")
            import numpy as np

            import ceemx

            system, data, x0 = problem()
            solver = ceemx.Alternating(rtol=0.0, atol=0.0)
            res = ceemx.fit(
                system,
                data,
                x0,
                solver=solver,
                max_epochs=EPOCHS,
                progress=False,
                diagnose=False,
                checkpoint=folder,
            )  # resumes the finished checkpoint: loads, checks, runs no epoch
            if not np.array_equal(np.asarray(res.theta), np.asarray(done[0]["theta"])):
                problems.append("resumed θ differs from the finished fit's")
            stray = [
                n for n in os.listdir(folder) if n not in ("latest.json", f"state-{EPOCHS}.eqx")
            ]
            if stray:
                problems.append(f"stray files {stray}")
        del ckpt
        summary = "; ".join(o.get("error", "finished")[:100] for o in outs)
        return not problems, f"run {i + 1}: " + ("; ".join(problems) or "ok") + f" [{summary}]"


class _DiskFull:
    def __init__(self, f):
        self.f = f

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __getattr__(self, name):
        return getattr(self.f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


def disk_runs(n: int) -> list[tuple[bool, str]]:
    import numpy as np

    import ceemx
    from ceemx.infra import checkpoint as ckpt

    system, data, x0 = problem()
    solver = ceemx.Alternating(rtol=0.0, atol=0.0)

    def run(**kwargs):
        return ceemx.fit(
            system, data, x0, solver=solver, max_epochs=12, progress=False, diagnose=False, **kwargs
        )

    full = run()
    real = os.fdopen
    out = []
    for i in range(n):
        k = 2 + i  # the disk fills while epoch k is saved
        problems = []
        with tempfile.TemporaryDirectory() as folder:

            def fill(info, k=k):
                if info.epoch == k:
                    os.fdopen = lambda *a, **kw: _DiskFull(real(*a, **kw))

            try:
                run(checkpoint=folder, callbacks=[fill])
                problems.append("no error")
            except ckpt.CheckpointError as err:
                if "No space left on device" not in str(err):
                    problems.append(f"message: {err}")
            except Exception as err:  # noqa: BLE001 - reported
                problems.append(f"{type(err).__name__}: {err}")
            finally:
                os.fdopen = real
            names = sorted(os.listdir(folder))
            if names != ["latest.json", f"state-{k - 1}.eqx"]:
                problems.append(f"folder holds {names}")
            res = run(checkpoint=folder)
            if not np.array_equal(np.asarray(res.theta), np.asarray(full.theta)):
                problems.append("resume differs from the uninterrupted fit")
            if len(res.history) != len(full.history):
                problems.append("history length differs")
        out.append(
            (
                not problems,
                f"disk run {i + 1} (full at epoch {k}): " + ("; ".join(problems) or "ok"),
            )
        )
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").strip().splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--disk-runs", type=int, default=10)
    parser.add_argument("--no-lock", action="store_true")
    args = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    results = []
    t0 = time.perf_counter()
    for i in range(args.runs):
        results.append(contention_run(i, args.no_lock))
        print(results[-1][1], flush=True)
    if args.disk_runs:
        for r in disk_runs(args.disk_runs):
            results.append(r)
            print(r[1], flush=True)
    good = sum(ok for ok, _ in results)
    print(
        f"{good}/{len(results)} runs lost nothing ({args.runs} concurrent-writer, "
        f"{args.disk_runs} full-disk{', no lock' if args.no_lock else ''}); "
        f"{time.perf_counter() - t0:.0f} s; load {os.getloadavg()[0]:.1f}"
    )
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    return 0 if good == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
