"""Smoke runs of the experiments, the demo and the ``ceemx`` command (each well under a minute).

They check that every experiment writes its results, table and figure with finite numbers; the
paper-scale runs are ``ceemx experiment NAME`` without ``--smoke``.
"""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from ceemx import cli
from ceemx.experiments import common, demo, figure3, get, table1


def finite(values) -> bool:
    return bool(np.all(np.isfinite(np.asarray(values, dtype=float))))


def check_files(out, figure):
    for name in ("results.json", "table.md", figure):
        path = out / name
        assert path.exists() and path.stat().st_size > 0, name
    return json.loads((out / "results.json").read_text())


def test_table1_smoke(tmp_path):
    res = table1.run(smoke=True, out=tmp_path, verbose=False)
    saved = check_files(tmp_path, "table1.png")
    assert set(res["results"]) == {"likelihood", "paper"}
    for w in ("likelihood", "paper"):
        for setting in res["results"][w].values():
            assert len(setting["fits"]) == 2
            for f in setting["fits"]:
                assert finite([f["sigma"], f["rho"], f["beta"], f["J"]])
                assert 1 <= f["epochs"] <= 3
                assert f["monotone"]
    assert "10.011 (0.012)" in saved["table"]  # the paper's numbers beside ours
    assert "σ ours" in (tmp_path / "table.md").read_text()


def test_table1_weightings():
    assert table1.fit_noise("likelihood", 0.001, 0.01) == (0.001, 0.01)
    pn, on = table1.fit_noise("paper", 0.001, 0.01)
    # Dynamics term (σ_w/σ_v)·½‖r‖², observations ½‖r‖².
    assert on == 1.0 and math.isclose(1.0 / pn**2, 0.1)
    with pytest.raises(ValueError):
        table1.fit_noise("other", 0.1, 0.1)


def test_figure3_smoke(tmp_path):
    res = figure3.run(smoke=True, out=tmp_path, method="alternate", verbose=False)
    check_files(tmp_path, "figure3.png")
    (run,) = res["runs"]
    assert run["B"] == 2 and run["epochs"] == 3
    assert len(run["eps"]) == 4 and finite(run["eps"])
    assert run["eps"][-1] < run["eps"][0]
    assert run["monotone"]
    assert finite([run["first_epoch_s"], run["per_epoch_s"]])
    assert "authors' code" in (tmp_path / "table.md").read_text()


def test_figure3_setup():
    assert figure3.fit_setup("paper") == (1.0, 1.0, 5e-5)
    assert figure3.fit_setup("likelihood")[1] == 0.01
    assert type(figure3.make_learner("lbfgs")).__name__ == "LBFGSLearner"


def test_demo_smoke(tmp_path):
    res = demo.run(smoke=True, out=tmp_path, verbose=False)
    check_files(tmp_path, "demo.png")
    assert finite(res["eps"]) and res["eps"][-1] < res["eps"][0]
    assert finite(res["learned"]["sigma"])


def test_cli_demo_smoke(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "ceemx", "demo", "--smoke", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "ε(θ)" in proc.stdout
    check_files(out, "demo.png")


def test_cli_parser_and_version(capsys):
    args = cli.build_parser().parse_args(
        [
            "experiment",
            "figure3",
            "--smoke",
            "--seeds",
            "2",
            "--method",
            "alternate",
            "--max-epochs",
            "5",
        ]
    )
    assert (args.name, args.smoke, args.seeds, args.method, args.max_epochs) == (
        "figure3",
        True,
        2,
        "alternate",
        5,
    )
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("ceemx ")
    assert cli.main([]) == 2
    with pytest.raises(ValueError):
        get("nope")


def test_perturb_and_monotone():
    import jax

    true = common.true_lorenz(2)
    guess = common.perturb_lorenz(jax.random.PRNGKey(0), true)
    for p in ("sigma", "rho", "beta", "H"):
        a, b = np.asarray(getattr(guess, p)), np.asarray(getattr(true, p))
        assert np.all(np.abs(a - b) <= 0.1 * np.abs(b) + 1e-15)
        assert not np.allclose(a, b)
    np.testing.assert_array_equal(np.asarray(guess.C), np.asarray(true.C))  # C stays known
    assert common.is_monotone(1.0, [{"J": 2.0}, {"J": 2.0}, {"J": 3.0}])
    assert not common.is_monotone(1.0, [{"J": 2.0}, {"J": 1.5}])
