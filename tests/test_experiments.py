"""Smoke runs of the experiments, the demo and the ``ceemx`` command (each well under a minute).

They check that every experiment writes its results, table and figure with finite numbers; the
paper-scale runs are ``ceemx experiment NAME`` without ``--smoke``.
"""

import json
import math
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx import cli
from ceemx.experiments import common, figure2, figure3, get, table1


def finite(values) -> bool:
    return bool(np.all(np.isfinite(np.asarray(values, dtype=float))))


def check_files(out, figure):
    for name in ("results.json", "table.md", figure):
        path = out / name
        assert path.exists() and path.stat().st_size > 0, name
    return json.loads((out / "results.json").read_text())


@pytest.mark.slow  # an experiment's wiring end to end (≈ 6 s)
def test_table1_smoke(tmp_path):
    """``ceemx experiment table1 --smoke`` in-process."""
    assert cli.main(["experiment", "table1", "--smoke", "--out", str(tmp_path)]) == 0
    saved = check_files(tmp_path, "table1.png")
    assert saved["seeds"] == [0, 1]
    assert set(saved["results"]) == {"likelihood", "paper"}
    for w in ("likelihood", "paper"):
        for setting in saved["results"][w].values():
            assert len(setting["fits"]) == 2
            for f in setting["fits"]:
                assert finite([f["sigma"], f["rho"], f["beta"], f["J"]])
                assert 1 <= f["epochs"] <= 3
                assert f["monotone"]
    assert "10.011 (0.012)" in saved["table"]  # the paper's numbers beside ours
    assert saved["paper"]["0.1/0.01"]["beta"] == {"mean": 2.676, "se": 0.004, "flagged": True}
    assert "σ ours" in (tmp_path / "table.md").read_text()


@pytest.mark.slow  # compiles Laplace EM on table1's problem (≈ 5 s); see the next-but-one test
def test_table1_laplace_smoke(tmp_path):
    """``ceemx experiment table1 --method laplace --smoke``: Laplace EM, likelihood weighting."""
    args = ["experiment", "table1", "--method", "laplace", "--smoke", "--out", str(tmp_path)]
    assert cli.main(args) == 0
    saved = check_files(tmp_path, "table1.png")
    assert saved["method"] == "laplace"
    assert set(saved["results"]) == {"likelihood"}  # the paper's weighting is not a likelihood
    for setting in saved["results"]["likelihood"].values():
        for f in setting["fits"]:
            assert finite([f["sigma"], f["rho"], f["beta"]])
            assert f["monotone"]  # the Laplace log-evidence never fell
            assert all(f["se"][p] > 0 for p in table1.PARAMS)
    assert "95 % CI covers" in saved["table"]


@pytest.mark.slow  # compiles the midpoint Lorenz and Nelder–Mead (≈ 3 s); see the next test
def test_table1_authors_protocol_smoke(tmp_path):
    """``--protocol authors``: explicit midpoint, x₁ spread 5, zero start, Nelder–Mead."""
    args = ["experiment", "table1", "--protocol", "authors", "--smoke", "--out", str(tmp_path)]
    assert cli.main(args) == 0
    saved = check_files(tmp_path, "table1.png")
    assert saved["protocol"] == "authors" and set(saved["results"]) == {"paper"}
    fits = [f for s in saved["results"]["paper"].values() for f in s["fits"]]
    assert all(finite([f["sigma"], f["rho"], f["beta"]]) for f in fits)
    with pytest.raises(SystemExit):
        cli.main(["experiment", "figure2", "--protocol", "authors", "--smoke"])


def test_table1_methods_and_protocols(capsys):
    """What the two smoke runs above configure, without compiling: Laplace EM keeps only the
    likelihood weighting (it maximises a likelihood); the authors' protocol is Algorithm 1 with the
    paper's weighting and their midpoint integrator; figure2 has no authors' protocol."""
    assert table1.resolve_methods("laplace", "both", "ours", verbose=True) == (
        "laplace",
        ["likelihood"],
    )
    assert "likelihood weighting only" in capsys.readouterr().out
    assert table1.resolve_methods("laplace", "likelihood", "ours", verbose=True)[1] == [
        "likelihood"
    ]
    assert table1.resolve_methods("joint", "both", "authors", verbose=False) == (
        "alternate",
        ["paper"],
    )
    assert table1.resolve_methods("alternate", "both", "ours", verbose=False) == (
        "alternate",
        ["likelihood", "paper"],
    )
    with pytest.raises(ValueError, match="protocol"):
        table1.resolve_methods("alternate", "both", "theirs", verbose=False)
    assert table1.true_system("authors").integrator == "midpoint"
    assert table1.true_system("ours").C.shape == (2, 3)
    with pytest.raises(SystemExit):
        cli.main(["experiment", "figure2", "--protocol", "authors", "--smoke"])


@pytest.mark.slow  # an experiment's wiring end to end (table1's smoke stays in the default suite)
def test_calibration_experiment_smoke(tmp_path):
    """``ceemx experiment calibration --smoke``: learned noise and interval coverage."""
    assert cli.main(["experiment", "calibration", "--smoke", "--out", str(tmp_path)]) == 0
    saved = check_files(tmp_path, "calibration.png")
    assert len(saved["runs"]) == 2
    for run in saved["runs"]:
        lap = run["laplace"]
        assert finite(list(lap["estimate"].values()))
        assert set(lap["se"]) == {"sigma", "rho", "beta", "sigma_w", "sigma_v"}
        assert finite(list(run["ce-joint"]["estimate"].values()))
    table = (tmp_path / "table.md").read_text()
    assert "Coverage of the nominal 95 % intervals" in table


def test_table1_paper_cells():
    assert table1.paper_cell((0.001, 0.01), 0) == "10.011 (0.012)"
    assert table1.paper_cell((0.1, 0.01), 2) == "**2.676 (0.004)**†"  # flagged by the paper
    assert table1.paper_cell((0.5, 0.5), 1) == "–"


def test_table1_weightings():
    assert table1.fit_noise("likelihood", 0.001, 0.01) == (0.001, 0.01)
    pn, on = table1.fit_noise("paper", 0.001, 0.01)
    # Dynamics term (σ_w/σ_v)·½‖r‖², observations ½‖r‖².
    assert on == 1.0 and math.isclose(1.0 / pn**2, 0.1)
    with pytest.raises(ValueError):
        table1.fit_noise("other", 0.1, 0.1)


@pytest.mark.slow  # an experiment's wiring end to end (table1's smoke stays in the default suite)
def test_figure3_smoke(tmp_path):
    with pytest.warns(ceemx.NoiseCheckWarning, match="too loose"):  # three epochs from the start
        res = figure3.run(smoke=True, out=tmp_path, method="alternate", verbose=False)
    check_files(tmp_path, "figure3.png")
    (run,) = res["runs"]
    assert run["B"] == 2 and run["epochs"] == 3
    assert len(run["eps"]) == 4 and finite(run["eps"])
    assert run["eps"][-1] < run["eps"][0]
    assert run["monotone"]
    assert finite([run["first_epoch_s"], run["per_epoch_s"]])
    assert "authors' code" in (tmp_path / "table.md").read_text()


@pytest.mark.slow  # an experiment's wiring end to end (table1's smoke stays in the default suite)
def test_figure2_smoke(tmp_path):
    """``ceemx experiment figure2 --smoke``: CE-EM (both solvers) and Particle EM side by side."""
    assert cli.main(["experiment", "figure2", "--smoke", "--out", str(tmp_path)]) == 0
    res = check_files(tmp_path, "figure2.png")
    (run,) = res["runs"]
    for method in figure2.METHODS:
        rec = run[method]
        assert rec["epochs"] == 3 and len(rec["params"]) == 3
        assert finite(rec["params"]) and finite(rec["epoch_s"])
    pem = run["particle-em"]
    assert finite(pem["pf_log_likelihood"]) and len(pem["e_step_s"]) == 3
    # Burn-in 1 epoch, then γ = (k − 1)^(−0.7): γ₂ = 1 empties the older slot, so a memory of 2
    # epochs still holds all of Q̂ at epoch 3 (weights γ₃ and 1 − γ₃).
    assert np.allclose(pem["saem_mass"], 1.0)
    table = (tmp_path / "table.md").read_text()
    assert "Particle EM / CE-EM" in table and "47×" in table


@pytest.mark.slow  # compiles a K = 2 Particle EM with an L-BFGS M-step (≈ 35 s)
def test_figure3_particle_smoke(tmp_path):
    with pytest.warns(ceemx.NoiseCheckWarning, match="too tight"):  # three epochs from the start
        res = figure3.run(smoke=True, out=tmp_path, method="particle", verbose=False)
    check_files(tmp_path, "figure3.png")
    (run,) = res["runs"]
    assert run["epochs"] == 3 and finite(run["eps"])
    assert "Particle EM" in (tmp_path / "table.md").read_text()


def test_figure3_setup():
    assert figure3.fit_setup("paper") == (1.0, 1.0, 5e-5)
    assert figure3.fit_setup("likelihood")[1] == 0.01
    assert type(figure3.make_learner("lbfgs")).__name__ == "LBFGSLearner"


def test_seeds_one_meaning_everywhere():
    assert common.parse_seeds("3") == 3
    assert common.parse_seeds("42,44") == (42, 44)
    assert common.parse_seeds("42,") == (42,)
    with pytest.raises(ValueError):
        common.parse_seeds("-1")
    # N = the first N of the experiment's sequence; lists and strings as given.
    assert common.seed_list(None, first=0, default=2) == [0, 1]
    assert common.seed_list(3, first=42, default=4) == [42, 43, 44]
    assert common.seed_list("2", first=42, default=4) == [42, 43]
    assert common.seed_list("42,44", first=0, default=4) == [42, 44]
    assert common.seed_list([5, 1], first=0, default=4) == [5, 1]


def test_make_solver():
    joint = common.make_solver("joint", rho_x=0.5, rtol=1e-6)
    assert isinstance(joint, ceemx.JointLM) and (joint.rho_x, joint.rtol) == (0.5, 1e-6)
    alt = common.make_solver("alternate", rho_x=0.5, learner=ceemx.LBFGSLearner(), rtol=0.0)
    assert isinstance(alt, ceemx.Alternating)
    assert alt.smoother.rho_x == 0.5 and alt.rtol == 0.0
    assert isinstance(alt.learner, ceemx.LBFGSLearner)
    assert isinstance(common.make_solver("alternate").learner, ceemx.LMLearner)
    prior = common.lorenz_initial_prior(1)
    pem = common.make_solver("particle", initial=prior, particle_options={"memory": 3})
    assert isinstance(pem, ceemx.ParticleEM) and pem.memory == 3 and pem.initial is prior
    with pytest.raises(ValueError):
        common.make_solver("other")


@pytest.mark.slow  # an experiment's wiring end to end (table1's smoke stays in the default suite)
def test_cli_demo_smoke(tmp_path, capsys):
    """``ceemx demo --smoke`` in-process (the demo's only smoke run; the slowest test here)."""
    out = tmp_path / "demo"
    assert cli.main(["demo", "--smoke", "--out", str(out)]) == 0
    assert "ε(θ)" in capsys.readouterr().out
    saved = check_files(out, "demo.png")
    assert finite(saved["eps"]) and saved["eps"][-1] < saved["eps"][0]
    assert finite(saved["learned"]["sigma"])


def test_python_m_ceemx():
    proc = subprocess.run(
        [sys.executable, "-m", "ceemx", "--version"], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0 and proc.stdout.startswith("ceemx "), proc.stderr


def test_cli_parser_and_version(capsys):
    args = cli.build_parser().parse_args(
        [
            "experiment",
            "figure3",
            "--smoke",
            "--seeds",
            "43,45",
            "--method",
            "alternate",
            "--max-epochs",
            "5",
        ]
    )
    assert (args.name, args.smoke, args.seeds, args.method, args.max_epochs) == (
        "figure3",
        True,
        (43, 45),
        "alternate",
        5,
    )
    assert cli.build_parser().parse_args(["experiment", "table1", "--seeds", "3"]).seeds == 3
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["experiment", "table1", "--seeds", "x"])
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("ceemx ")
    assert cli.main([]) == 2
    with pytest.raises(ValueError):
        get("nope")


def test_perturb_lorenz():
    import jax

    true = common.true_lorenz(2)
    guess = common.perturb_lorenz(jax.random.PRNGKey(0), true)
    for p in ("sigma", "rho", "beta", "H"):
        a, b = np.asarray(getattr(guess, p)), np.asarray(getattr(true, p))
        assert np.all(np.abs(a - b) <= 0.1 * np.abs(b) + 1e-15)
        assert not np.allclose(a, b)
    np.testing.assert_array_equal(np.asarray(guess.C), np.asarray(true.C))  # C stays known
    no_h = common.perturb_lorenz(jax.random.PRNGKey(0), true, coupling=False)
    np.testing.assert_array_equal(np.asarray(no_h.H), np.asarray(true.H))


@pytest.mark.slow  # an experiment's wiring end to end (table1's smoke stays in the default suite)
def test_figure4_smoke(tmp_path):
    """``ceemx experiment figure4 --smoke``: five models trained and scored on the generator."""
    assert cli.main(["experiment", "figure4", "--smoke", "--out", str(tmp_path)]) == 0
    saved = check_files(tmp_path, "figure4a.png")
    assert (tmp_path / "figure4b.png").stat().st_size > 0
    assert set(saved["mean"]) == {"naive", "LSTM", "H25", "SID", "NL"}
    n_test = saved["sizes"][2]
    for model, values in saved["rmse"].items():
        assert len(values) == n_test and finite(values), model
    assert saved["nl"]["epochs"] == 2 and saved["nl"]["best_epoch"] in (0, 1, 2)
    assert set(saved["nl_better_on"]) == {"naive", "LSTM", "H25", "SID"}
    assert "0.615" in saved["table"] and isinstance(saved["paper_ordering"], bool)


def test_figure4_helpers():
    from ceemx.experiments import figure4, figure4_report

    means = {"NL": 0.6, "SID": 0.8, "H25": 0.9, "LSTM": 1.3, "naive": 2.7}
    assert figure4_report.paper_ordering(means)
    assert not figure4_report.paper_ordering({**means, "NL": 0.85})
    rmse = {"NL": np.array([1.0, 2.0, 3.0]), "H25": np.array([2.0, 1.0, 4.0])}
    assert figure4_report.win_counts(rmse) == {"H25": 2}
    with pytest.raises(ValueError, match="dataset"):
        figure4.load_splits(data=None, dataset="nope", smoke=True, seed=0)
    with pytest.raises(SystemExit):
        cli.main(["experiment", "table1", "--dataset", "silverbox"])


def test_figure4_group_learning_rates():
    """Per-parameter rates: dynamics (A, B) at one rate, the observation model at the other."""
    from jax.flatten_util import ravel_pytree

    from ceemx.experiments import figure4_models
    from ceemx.identification.problem import split_system
    from ceemx.systems import NeuralObservationSystem

    n, m, p = 3, 2, 1
    A, B = jnp.eye(n) * 0.9, jnp.ones((n, p))
    C, D = jnp.ones((m, n)), jnp.zeros((m, p))
    system = NeuralObservationSystem(A, B, C, D, key=jax.random.PRNGKey(0), width=4, depth=1)
    rates = np.asarray(figure4_models.group_learning_rates(system, 1e-3, 5e-4))
    theta, params, _ = split_system(system)
    assert rates.shape == theta.shape
    # Mark A and B in a copy of θ's template: those positions must carry the dynamics rate.
    marked = eqx.tree_at(
        lambda s: (s.A, s.B), params, (jnp.full_like(A, np.inf), jnp.full_like(B, np.inf))
    )
    is_dyn = np.isinf(np.asarray(ravel_pytree(marked)[0]))
    assert is_dyn.sum() == n * n + n * p
    np.testing.assert_array_equal(rates[is_dyn], 1e-3)
    np.testing.assert_array_equal(rates[~is_dyn], 5e-4)


@pytest.mark.slow
def test_real_data_smoke(tmp_path):
    """`ceemx experiment real_data --smoke`: three gray-box fits, official-protocol scores."""
    from ceemx.datasets import data_root

    try:
        data_root()
    except FileNotFoundError as e:
        pytest.skip(f"real data absent: {e}")
    args = ["experiment", "real_data", "--smoke", "--out", str(tmp_path)]
    assert cli.main(args) == 0
    saved = json.loads((tmp_path / "results.json").read_text())
    assert (tmp_path / "real_data.png").exists()
    assert {d["dataset"] for d in saved["datasets"]} == {
        "cascaded_tanks",
        "silverbox",
        "coupled_electric_drives",
    }
    for d in saved["datasets"]:
        for entry in d["tests"].values():
            for key in ("graybox", "hybrid", "neural", "linear_ceem", "linear"):
                assert math.isfinite(entry[f"{key}_rmse"]) and entry[f"{key}_rmse"] > 0, key
                every = entry[f"{key}_rmse_every_sample"]  # the n_init outputs scored too
                assert math.isfinite(every) and every > 0, key
        assert set(d["learned"]) == {"hybrid", "neural"}
        assert d["learned"]["hybrid"]["weights"] > 0
    with pytest.raises(SystemExit):
        cli.main(["experiment", "real_data", "--method", "particle"])


def test_table1_uses_a_known_two_row_C(monkeypatch, tmp_path):
    """Paper §4.1.1: y = C x + v with C ∈ R^{2×3} (it used to be 1×3, the K = 1 default)."""
    seen = []

    def stop(seed, true_system, **kwargs):
        seen.append(true_system.C.shape)
        raise RuntimeError("stop")

    monkeypatch.setattr(common, "lorenz_problem", stop)
    with pytest.raises(RuntimeError, match="stop"):
        table1.run(smoke=True, out=tmp_path, verbose=False)
    assert seen == [(2, 3)]
