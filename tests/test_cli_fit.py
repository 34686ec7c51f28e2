"""``ceemx fit`` and the per-command parsers: refusals are one line and exit 2, records and
models load as documented, and (slow tier) a whole run writes what it says.

The refusals run the command in-process up to the refusal (no fit is compiled); the end-to-end
runs fit a two-parameter tank to two CSV records of 60 and 40 samples.
"""

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from ceemx import cli, experiment_command, fit_command, fit_records
from ceemx.experiments import EXPERIMENTS

TANK = '''
import jax.numpy as jnp
from jaxtyping import Array

import ceemx


class Tank(ceemx.AbstractSystem):
    """x_{t+1} = a x_t + b u_t; y_t = x_t."""

    a: Array = ceemx.param(lower=0.0, upper=1.0)
    b: Array = ceemx.param()

    @property
    def state_dim(self):
        return 1

    @property
    def obs_dim(self):
        return 1

    @property
    def input_dim(self):
        return 1

    def dynamics(self, x, u, t):
        return self.a * x + self.b * u

    def observe(self, x, u, t):
        return x


def make(a=0.5, b=0.3):
    return Tank(a, b, process_noise=0.01, obs_noise=0.01)
'''


def write_record(path, T, seed, *, dt=4.0, a=0.9, b=0.1):
    """A CSV record of the tank (time, pump, level) with measurement noise 0.01."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.0, 1.0, T)
    x = np.zeros(T)
    for t in range(T - 1):
        x[t + 1] = a * x[t] + b * u[t]
    y = x + 0.01 * rng.standard_normal(T)
    lines = ["time,pump,level"] + [f"{dt * t},{float(u[t])!r},{float(y[t])!r}" for t in range(T)]
    path.write_text("\n".join(lines) + "\n")
    return u, y


@pytest.fixture
def folder(tmp_path):
    """A model file and three records (60, 40 and 50 samples) in one folder."""
    (tmp_path / "tank_cli_model.py").write_text(TANK)
    write_record(tmp_path / "run1.csv", 60, 0)
    write_record(tmp_path / "run2.csv", 40, 1)
    write_record(tmp_path / "test.csv", 50, 2)
    return tmp_path


def refused(capsys, argv) -> str:
    """The one stderr line of a refused command (exit status 2)."""
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "error" in lines[0], lines
    return lines[0]


def fit_args(folder, *extra):
    return [
        "fit",
        str(folder / "tank_cli_model.py:make"),
        str(folder / "run1.csv"),
        "--inputs",
        "pump",
        "--outputs",
        "level",
        "--out",
        str(folder / "out"),
        *extra,
    ]


# ----------------------------------------------------------------------------------------------
# Refusals: one line, exit 2, nothing written
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("extra", "says"),
    [
        (["--max-epochs", "-3"], "--max-epochs: must be an integer >= 1; got '-3'"),
        (["--max-epochs", "0"], "--max-epochs"),
        (["--dt", "-4"], "--dt: must be a positive number"),
        (["--n-init", "60"], "--n-init 60: must be below the shortest record's 60 samples"),
        (["--start", "3=1"], "--start: expected NAME=VALUE"),
        (["--solver", "newton"], "invalid choice: 'newton'"),
        (["--dt", "4", "--time", "time"], "give --dt or --time, not both"),
        (["--test", "nowhere.csv"], "nowhere.csv: no such file"),
        (["--seeds", "3"], "--seeds: not an option of fit"),
    ],
)
def test_fit_refusals_before_jax(capsys, folder, extra, says):
    line = refused(capsys, fit_args(folder, *extra))
    assert says in line and line.startswith("ceemx fit: error:"), line
    assert not (folder / "out").exists() or not list((folder / "out").iterdir())


def test_missing_column_and_file(capsys, folder):
    args = fit_args(folder)
    args[args.index("pump")] = "pmp"
    line = refused(capsys, args)
    assert "run1.csv: no column 'pmp' (it has: time, pump, level)" in line
    args = fit_args(folder)
    args[2] = str(folder / "run9.csv")
    assert "run9.csv: no such file" in refused(capsys, args)
    args = fit_args(folder)
    args[1] = str(folder / "nope.py")
    assert "nope.py: no such model file" in refused(capsys, args)


def test_bad_cells_and_time_column(capsys, folder):
    bad = folder / "bad.csv"
    bad.write_text("time,pump,level\n0,1,0.5\n4,abc,0.6\n")
    args = fit_args(folder)
    args[2] = str(bad)
    assert "bad.csv line 3, column 'pump': 'abc' is not a number" in refused(capsys, args)
    uneven = folder / "uneven.csv"
    uneven.write_text("time,pump,level\n0,1,0.5\n4,1,0.6\n9,1,0.7\n")
    args[2] = str(uneven)
    assert "not uniformly sampled" in refused(capsys, [*args, "--time", "time"])


def test_model_refusals_are_one_line(capsys, folder):
    (folder / "broken_model.py").write_text("import ceemx\nraise RuntimeError('oops here')\n")
    (folder / "syntax_model.py").write_text("def f(:\n")
    (folder / "two_models.py").write_text(
        TANK.replace("def make", "class Other(Tank):\n    pass\n\n\ndef make")
    )
    for spec, says in [
        ("broken_model.py", "the model does not import: RuntimeError: oops here"),
        ("syntax_model.py", "the model does not import: SyntaxError"),
        ("tank_cli_model.py:Nope", "tank_cli_model has no 'Nope'"),
        ("two_models.py", "name the model as FILE.py:NAME (no `model` in the file; system "),
    ]:
        args = fit_args(folder, "--dt", "4")
        args[1] = str(folder / spec)
        assert says in refused(capsys, args), spec
    args = fit_args(folder, "--dt", "4", "--start", "c=3")
    assert "building the model with c: make() got an unexpected keyword" in refused(capsys, args)
    args = fit_args(folder, "--dt", "4")
    args[args.index("--inputs") : args.index("--inputs") + 2] = []
    assert "the fit refused: `data.u` has p = 0 but the system takes p = 1" in refused(capsys, args)


# ----------------------------------------------------------------------------------------------
# Records and models
# ----------------------------------------------------------------------------------------------


def test_read_records_csv_and_npz(tmp_path):
    u, y = write_record(tmp_path / "a.csv", 30, 0, dt=0.5)
    text = (tmp_path / "a.csv").read_text().splitlines()
    text[5] = text[5].rsplit(",", 1)[0] + ","  # an empty output cell: a missing sample
    (tmp_path / "a.csv").write_text("\n".join(text) + "\n")
    np.savez(tmp_path / "b.npz", pump=u[:20], level=y[:20], time=0.5 * np.arange(20))
    records = fit_records.read_records(
        [str(tmp_path / "a.csv"), str(tmp_path / "b.npz")], ["level"], ["pump"], time="time"
    )
    assert records.dt == 0.5 and records.shortest == 20
    assert [r.shape for r in records.ys] == [(30, 1), (20, 1)]
    assert records.us is not None
    np.testing.assert_array_equal(records.us[0][:, 0], u)
    assert np.isnan(records.ys[0][4, 0])  # line 6 of the file is sample 4
    np.testing.assert_array_equal(records.ys[1][:, 0], y[:20])
    np.savez(tmp_path / "c.npz", pump=u, level=y, time=0.25 * np.arange(30))
    with pytest.raises(fit_records.Refused, match="sample time 0.25"):
        fit_records.read_records(
            [str(tmp_path / "b.npz"), str(tmp_path / "c.npz")], ["level"], ["pump"], time="time"
        )


def test_load_model_forms(tmp_path, monkeypatch):
    """A class with start values, a function, an instance (``model``) with a start value
    changed, and ``module:NAME``: each the system the file describes."""
    (tmp_path / "tank_forms.py").write_text(TANK + "\nmodel = make(0.25, 0.5)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    path = str(tmp_path / "tank_forms.py")
    m = fit_command.load_model(path + ":Tank", [("a", 0.7), ("b", [0.2])])
    assert float(m.a) == 0.7 and np.asarray(m.b).tolist() == [0.2]
    m = fit_command.load_model(path)  # the file's `model`
    assert (float(m.a), float(m.b)) == (0.25, 0.5)
    m = fit_command.load_model(path, [("a", 0.125)])
    assert (float(m.a), float(m.b)) == (0.125, 0.5)
    m = fit_command.load_model("tank_forms:make", [("b", 0.75)])
    assert (float(m.a), float(m.b)) == (0.5, 0.75)
    with pytest.raises(fit_command.Refused, match="has no field 'c'"):
        fit_command.load_model(path, [("c", 1.0)])


# ----------------------------------------------------------------------------------------------
# Experiments: per-experiment help and refusals
# ----------------------------------------------------------------------------------------------


def test_experiment_help_lists_only_its_options(capsys):
    takes = {
        "table1": {"--seeds", "--method", "--weighting", "--protocol", "--max-epochs"},
        "figure2": {"--seeds", "--max-epochs"},
        "figure3": {"--seeds", "--method", "--weighting", "--learner", "--max-epochs"},
        "figure4": {"--seeds", "--method", "--max-epochs", "--data", "--dataset"},
        "real_data": {"--seeds", "--method", "--max-epochs", "--dataset"},
        "calibration": {"--seeds", "--max-epochs"},
    }
    every = set().union(*takes.values())
    assert set(takes) == set(EXPERIMENTS)
    for name, options in takes.items():
        with pytest.raises(SystemExit) as e:
            cli.main(["experiment", name, "--help"])
        assert e.value.code == 0
        shown = capsys.readouterr().out
        for option in every:
            assert (f"[{option} " in shown) == (option in options), (name, option)
        for option in every - options:
            line = refused(capsys, ["experiment", name, option, "1"])
            assert f"{option}: not an option of experiment {name}" in line, line


def test_experiment_values_refused(capsys, tmp_path):
    line = refused(capsys, ["experiment", "table1", "--max-epochs", "-3"])
    assert "--max-epochs: must be an integer >= 1; got '-3'" in line
    line = refused(capsys, ["experiment", "figure4", "--data", str(tmp_path / "none")])
    assert "--data: no such folder" in line
    line = refused(capsys, ["experiment", "figure3", "--weighting", "both"])
    assert "invalid choice: 'both'" in line
    line = refused(capsys, ["demo", "--max-epochs", "-1"])
    assert "--max-epochs" in line
    args = cli.build_parser().parse_args(["experiment", "figure3", "--smoke", "--learner", "lbfgs"])
    assert experiment_command.experiment_kwargs(args) == {
        "smoke": True,
        "out": None,
        "seeds": None,
        "method": None,
        "learner": "lbfgs",
        "max_epochs": None,
    }


# ----------------------------------------------------------------------------------------------
# End to end (slow: a fit compiles)
# ----------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_fit_command_end_to_end(folder):
    """Two records and a test record: the files it says, the fit's outcome on stderr, the saved
    model loading in a fresh process, and the scores of the recovered tank (a = 0.9, b = 0.1)."""
    out = folder / "out"
    args = [
        *fit_args(folder, "--time", "time", "--output-units", "V", "--start", "a=0.5"),
        str(folder / "run2.csv"),
        "--test",
        str(folder / "test.csv"),
        "--solver",
        "joint",
        "--noise",
        "fixed",
        "--max-epochs",
        "50",
    ]
    proc = subprocess.run(
        [sys.executable, "-m", "ceemx", *args], capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr
    files = {p.name for p in out.iterdir()}
    assert files == {
        "summary.txt",
        "scores.txt",
        "results.json",
        "fit.png",
        "test.png",
        "residuals.png",
        "model.ceemx",
    }
    results = json.loads((out / "results.json").read_text())
    epochs = results["epochs"]
    outcome = f"converged at {epochs}/50 epochs" if results["converged"] else "not converged"
    assert f"ceemx: JointLM: {outcome}" in proc.stderr, proc.stderr
    assert results["parameters"]["a"]["estimate"] == pytest.approx(0.9, abs=0.02)
    assert results["parameters"]["b"]["estimate"] == pytest.approx(0.1, abs=0.02)
    test_rmse = results["scores"]["test records"]["rmse"][0][0]
    assert 0.005 < test_rmse < 0.02  # the measurement noise, 0.01
    assert "level [V]" in (out / "scores.txt").read_text()
    assert "Fit summary: JointLM" in proc.stdout
    load = textwrap.dedent(
        f"""
        import sys, jax
        jax.config.update("jax_enable_x64", True)
        sys.path.insert(0, {str(folder)!r})
        import ceemx
        m, info = ceemx.load({str(out / "model.ceemx")!r}, with_info=True)
        print(type(m).__name__, float(m.a), *info.data.output_labels(1), info.data.dt, sep="|")
        """
    )
    loaded = subprocess.run(
        [sys.executable, "-c", load], capture_output=True, text=True, timeout=300
    )
    assert loaded.returncode == 0, loaded.stderr
    name, a, label, dt = loaded.stdout.strip().split("|")
    assert name == "Tank" and float(a) == pytest.approx(results["parameters"]["a"]["estimate"])
    assert (label, dt) == ("level [V]", "4.0")
