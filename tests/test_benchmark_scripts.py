"""The benchmark scripts' ``--smoke`` modes run, so they cannot rot (issue 12).

A peer or the reference implementation whose environment is absent is skipped by the script
itself with a message (the reference: ``benchmarks/reference/setup.sh``).
"""

import json
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow  # two fresh processes compile two fit solvers (≈ 30–60 s)
def test_compare_reference_smoke(tmp_path):
    out = tmp_path / "cr.json"
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "compare_reference.py"),
            "--smoke",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(out.read_text())
    summary = res["summary"]
    for method in ("joint", "alternate"):
        assert summary[method]["first_fit_s_median"] > 0
        assert summary[method]["max_rel_error"] < 0.2
    if (ROOT / "benchmarks" / "reference" / ".venv" / "bin" / "python").exists():
        assert summary["reference"]["fit_s_median"] > 0
    else:
        assert "reference environment absent" in proc.stdout
