"""The scripts in examples/ run end to end (their --smoke versions) in a subprocess."""

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ceemx import datasets

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _silverbox_csv() -> Path | None:
    try:
        path = datasets.data_root() / datasets.REGISTRY["silverbox"].file
    except FileNotFoundError:
        return None
    return path if path.is_file() else None


@pytest.mark.skipif(
    _silverbox_csv() is None,
    reason="Silverbox data (silverbox/SNLS80mV.csv) not found: set CEEMX_DATA or ../shared/data",
)
@pytest.mark.slow  # a subprocess fit of the Silverbox example (≈ 10 s)
def test_graybox_from_csv_smoke(tmp_path):
    csv = _silverbox_csv()
    env = {**os.environ, "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [
            sys.executable,
            str(EXAMPLES / "graybox_from_csv.py"),
            "--smoke",
            "--data",
            str(csv),
            "--out",
            str(tmp_path),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (tmp_path / "silverbox_graybox.png").is_file()
    match = re.search(r"RMSE = ([^\s]+) mV", proc.stdout)
    assert match is not None, proc.stdout
    rmse = float(match.group(1))
    assert math.isfinite(rmse) and rmse > 0
    assert "published deep-encoder" in proc.stdout
    for name in ("m", "d", "k1", "k3", "u0 [mV]"):
        assert re.search(rf"^{re.escape(name)}\s", proc.stdout, re.MULTILINE), proc.stdout


@pytest.mark.slow  # two small JointLM fits (≈ 30 s with compilation)
def test_hybrid_duffing_smoke(tmp_path):
    """examples/hybrid_duffing.py --smoke runs, writes its figure and prints both test scores."""
    env = {**os.environ, "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / "hybrid_duffing.py"), "--smoke", "--out", str(tmp_path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (tmp_path / "hybrid_duffing.png").is_file()
    match = re.search(r"test free-run RMSE: physics ([^\s,]+), hybrid ([^\s]+)", proc.stdout)
    assert match is not None, proc.stdout
    assert all(math.isfinite(float(v)) for v in match.groups())
