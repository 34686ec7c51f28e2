"""Checkpoints under contention and on full disks: nothing lost.

    python benchmarks/checkpoint_contention.py [--runs 20] [--disk-runs 12] [--no-lock]

**Concurrent writers.** Each run starts two processes that fit the same small problem (a
2-state linear system, B = 2, T = 40, ``Alternating``, 150 epochs, one save per epoch) into the
same checkpoint folder at the same instant (both compile first, then wait for a common start
time). Expected: one fit finishes, the other is refused at once with a ``CheckpointError`` that
names the first's pid; the folder then holds a checkpoint that loads (sha256, fingerprint,
finiteness) and equals the finished fit (θ bitwise, 150 epochs); a third fit from the folder
resumes it and returns that θ. ``--no-lock`` replaces the lock by nothing, to show the failure it
prevents (crashed writers, as before the lock).

**Full disks, for real.** Each run fits uninterrupted in this process (T = 400: a 13 kB state
file, 12 epochs), then fits in a subprocess with a checkpoint whose save at epoch k fails
part-way for real: either the process's file-size limit drops (``RLIMIT_FSIZE`` to 300…10300
bytes, SIGXFSZ ignored: the write takes what fits and the next fails with EFBIG), or — where a
tmpfs can be mounted (root) — a 256 kB file system holding the checkpoint is filled by another
file to within 0, 1 or 2 pages (ENOSPC). The cuts fall in the state file and in
``latest.json``, at the first save (k = 1) and later ones. The fit must fail with a
``CheckpointError`` naming the reason ("File too large", "No space left on device"; never
"errno None"), leave exactly ``latest.json`` and ``state-<k-1>.eqx`` (nothing at k = 1; no
temporaries), and a resume once there is room must end bitwise equal to the uninterrupted fit.

Prints one line per run and a summary; exit status 1 when anything was lost. Backs
``docs/guarantees.md`` ("Checkpoints": "Two writers" and "Full disks").
"""

from __future__ import annotations

import argparse
import contextlib
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


def problem(T: int = 40):
    """A 2-state linear system and T steps of its data: cheap to compile and to step."""
    import jax
    import numpy as np

    import ceemx
    from ceemx.systems import LinearSystem

    a = np.array([[0.9, 0.1], [-0.1, 0.9]])
    b, c, d = np.ones((2, 1)), np.eye(2)[:1], np.zeros((1, 1))
    true = LinearSystem(a, c, b, d, process_noise=0.1, obs_noise=0.1)
    u = np.random.default_rng(1).standard_normal((2, T, 1))
    _, data = ceemx.simulate(true, jax.random.PRNGKey(0), np.zeros((2, 2)), T, u)
    guess = LinearSystem(0.8 * a, c, b, d, process_noise=0.1, obs_noise=0.1)
    return guess, data, np.zeros((2, T, 2))


def worker_source(worker: str = _WORKER) -> str:
    import inspect

    return (
        "def PROBLEM(T=40):\n"
        + "\n".join("    " + line for line in inspect.getsource(problem).splitlines()[1:])
        + "\n"
        + worker
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


_DISK_WORKER = r"""
import json, os, resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # past the limit a write fails with EFBIG
import jax
jax.config.update("jax_enable_x64", True)
import ceemx

folder, mode, disk = sys.argv[1], sys.argv[2], sys.argv[5]
k, amount = int(sys.argv[3]), int(sys.argv[4])
system, data, x0 = PROBLEM(DISK_T)


def fault(info):  # runs before epoch `info.epoch` is saved
    if info.epoch != k:
        return
    if mode == "fsize":
        resource.setrlimit(resource.RLIMIT_FSIZE, (amount, resource.RLIM_INFINITY))
    else:  # fill the small file system to within `amount` bytes
        fs = os.statvfs(disk)
        with open(os.path.join(disk, "filler"), "wb") as f:
            f.write(b"\0" * max(0, fs.f_bavail * fs.f_frsize - amount))


try:
    ceemx.fit(system, data, x0, solver=ceemx.Alternating(rtol=0.0, atol=0.0), max_epochs=EPOCHS,
              progress=False, diagnose=False, checkpoint=folder, callbacks=[fault])
    print(json.dumps({"error": None}))
except Exception as err:
    print(json.dumps({"error": f"{type(err).__name__}: {err}"}))
"""

DISK_EPOCHS = 12
#: steps of the full-disk runs' records: a 13 kB state file, whose (2, T, 2) states NumPy writes
#: in one piece — the write a limit or a full disk cuts part-way
DISK_T = 400


def _mount_small_fs(path: str) -> str | None:
    """Mount a 256 kB tmpfs at ``path``; the reason when that is not possible."""
    if not sys.platform.startswith("linux") or os.geteuid() != 0:
        return "mounting a tmpfs needs Linux and root"
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", path],
        capture_output=True,
        text=True,
        check=False,
    )
    return None if done.returncode == 0 else f"mount refused: {done.stderr.strip()}"


def _disk_cases(n: int, disk_ok: bool) -> list[tuple[str, int, int]]:
    """(mode, epoch k at whose save the fault strikes, bytes left), alternating the two modes.

    Limits of 300, 4300 and 8300 bytes cut the state file part-way; 0 bytes of disk left fail
    its first write, 4096 cut it part-way, 16384 let it be written and cut ``latest.json``. The
    first save (k = 1) is struck in both modes.
    """
    cases = []
    for i in range(n):
        j = i // 2
        if disk_ok and i % 2:
            cases.append(
                ("disk", 1 + (2 * j + 1) % DISK_EPOCHS if j else 1, (4096, 16384, 0)[j % 3])
            )
        else:
            cases.append(("fsize", 1 + (2 * j) % DISK_EPOCHS, (300, 4300, 8300)[j % 3]))
    return cases


def disk_runs(n: int) -> list[tuple[bool, str]]:
    """Fits whose checkpoint writes fail for real part-way (see the module notes)."""
    import numpy as np

    import ceemx

    system, data, x0 = problem(DISK_T)
    solver = ceemx.Alternating(rtol=0.0, atol=0.0)

    def run(**kwargs):
        return ceemx.fit(
            system,
            data,
            x0,
            solver=solver,
            max_epochs=DISK_EPOCHS,
            progress=False,
            diagnose=False,
            **kwargs,
        )

    full = run()
    script = f"EPOCHS, DISK_T = {DISK_EPOCHS}, {DISK_T}\n" + worker_source(_DISK_WORKER)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        disk = os.path.join(tmp, "disk")
        os.makedirs(disk)
        no_disk = _mount_small_fs(disk)
        if no_disk:
            print(f"full-disk runs use the file-size limit only: {no_disk}", flush=True)
        try:
            for i, (mode, k, amount) in enumerate(_disk_cases(n, no_disk is None)):
                folder = os.path.join(disk if mode == "disk" else tmp, f"ckpt-{i}")
                done = subprocess.run(
                    [sys.executable, "-c", script, folder, mode, str(k), str(amount), disk],
                    capture_output=True,
                    text=True,
                    timeout=600,
                    check=False,
                )
                lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
                error = json.loads(lines[-1])["error"] if lines else done.stderr[-300:]
                names = sorted(os.listdir(folder)) if os.path.isdir(folder) else []
                if os.path.exists(os.path.join(disk, "filler")):
                    os.remove(os.path.join(disk, "filler"))
                problems = []
                reason = "No space left on device" if mode == "disk" else "File too large"
                if error is None:
                    problems.append("no error")
                elif reason not in error or "errno None" in error:
                    problems.append(f"message: {error[:200]}")
                want = [] if k == 1 else ["latest.json", f"state-{k - 1}.eqx"]
                if names != want:
                    problems.append(f"folder holds {names}, expected {want}")
                res = run(checkpoint=folder)
                if not np.array_equal(np.asarray(res.theta), np.asarray(full.theta)):
                    problems.append("resume differs from the uninterrupted fit")
                if len(res.history) != len(full.history):
                    problems.append("history length differs")
                where = f"{mode} {amount} B left" if mode == "disk" else f"ulimit -f {amount} B"
                line = f"disk run {i + 1} ({where}, at the save of epoch {k}): "
                said = (error or "").split("': ", 1)[-1].split(";", 1)[0]  # the reason
                out.append((not problems, line + ("; ".join(problems) or f"ok [{said}]")))
                print(out[-1][1], flush=True)
        finally:
            if no_disk is None:
                subprocess.run(["umount", disk], check=False)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").strip().splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--disk-runs", type=int, default=12)
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
        results.extend(disk_runs(args.disk_runs))
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
