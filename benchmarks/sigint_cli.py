"""20 SIGINTs of `ceemx experiment table1 --smoke` at random times in [0.2, 15] s (reliability).

Usage: python benchmarks/sigint_cli.py [SEED] [N]. Each run must exit 130 with one stderr line and
leave no results.json; prints one line per run and the count.
"""

import os
import random
import signal
import subprocess
import sys
import tempfile
import time

random.seed(int(sys.argv[1]) if len(sys.argv) > 1 else 0)
n = int(sys.argv[2]) if len(sys.argv) > 2 else 20
env = dict(os.environ, MPLBACKEND="Agg", CEEMX_COMPILATION_CACHE="0")
ok = 0
for i in range(n):
    d = round(random.uniform(0.2, 15.0), 2)
    out = tempfile.mkdtemp()
    p = subprocess.Popen(
        [sys.executable, "-m", "ceemx", "experiment", "table1", "--smoke", "--out", out],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=env,
        cwd="/tmp",
    )
    time.sleep(d)
    t0 = time.time()
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    lat = time.time() - t0
    lines = err.decode().splitlines()
    files = sorted(os.listdir(out))
    good = (
        p.returncode == 130 and len(lines) == 1 and lines[0].strip() and "results.json" not in files
    )
    ok += good
    verdict = "OK" if good else "FAIL: " + repr(err.decode()[:300])
    print(
        f"{i:2d} delay={d:5.2f}s rc={p.returncode} stderr_lines={len(lines)} "
        f"exit_after={lat:.2f}s files={files} {verdict}",
        flush=True,
    )
print(f"{ok}/{n} OK")
