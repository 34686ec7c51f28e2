"""The ``--smoke`` modes of ``benchmarks/scaling.py`` and ``benchmarks/k100.py`` run."""

import json
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run(script: str, out: pathlib.Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--smoke", "--out", str(out), *extra],
        capture_output=True,
        text=True,
        timeout=900,
    )


@pytest.mark.slow  # a fresh process per tiny smoothing case and one for the fits (≈ 1–2 min)
def test_scaling_smoke(tmp_path):
    out = tmp_path / "scaling.json"
    proc = _run("scaling.py", out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(out.read_text())
    assert res["peak"]["peak_gflops"] > 0
    sm = res["smoothing"]
    assert set(sm["slopes"]) == {"T", "B", "n"}
    for rows in sm["sweeps"].values():
        for r in rows:
            assert r["per_iter_s"] > 0 and len(r["steady_runs_s"]) >= 3
            assert len(r["loadavg_1min"]) == 2
    for r in sm["flop_rows"]:
        assert r["flop"]["ratio"] > 0 and r["flops_call"]["bound"] > r["flops_call"]["minimal"]
    assert "met" in sm["target_5x"]
    (fit,) = res["fit"]["rows"]
    assert set(fit["methods"]) == {"joint", "alternate_lm", "alternate_lbfgs"}
    for m in fit["methods"].values():
        assert m["epochs"] == 3 and m["steady_epoch_s"] > 0


@pytest.mark.slow  # three fresh processes per T, each compiling a fit (≈ 3–8 min under load)
def test_scaling_long_smoke(tmp_path):
    """``--only long``: one row per (T, method), log–log fits and the linearity verdict."""
    out = tmp_path / "long.json"
    proc = _run("scaling.py", out, "--only", "long")
    assert proc.returncode == 0, proc.stderr[-3000:]
    long = json.loads(out.read_text())["long"]
    assert {(r["method"], r["T"]) for r in long["rows"]} == {
        (m, T) for m in ("smooth", "joint_lm", "laplace_em_qn") for T in long["T"]
    }
    for r in long["rows"]:
        assert r["per_iter_s"] > 0 and len(r["steady_runs_s"]) >= 3
        assert r["peak_rss_mb"] >= r["baseline_rss_mb"] > 0
    for f in long["fits"].values():
        assert set(f["time_per_iteration"]) == {"slope", "intercept", "r2"}
    assert set(long["target"]["met"]) == set(long["fits"])


@pytest.mark.slow  # compiles one Algorithm-1 epoch with the L-BFGS learner (≈ 30 s)
def test_k100_smoke(tmp_path):
    out = tmp_path / "k100.json"
    proc = _run("k100.py", out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(out.read_text())
    assert res["config"]["K"] == 4 and res["eps_initial"] > 0
    assert len(res["epochs"]) == 2 and all(e["eps"] > 0 for e in res["epochs"])
    assert "target_met" in res


@pytest.mark.slow  # imports the benchmark module (cheap; kept with the other benchmark tests)
def test_smoother_flop_count():
    """The analytic count is cubic in n with the documented leading terms."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import scaling
    finally:
        sys.path.pop(0)
    f = scaling.smoother_flops(300, 298)
    assert f["cholesky"] == pytest.approx(300**3 * (3 + 1 / 3))
    assert f["iteration"] > f["minimal"] > 3 * 300**3
    c = scaling.call_flops(128, 2, 18, 16, 5)
    assert c["with_jacobians"] > c["bound"] > c["minimal"]
