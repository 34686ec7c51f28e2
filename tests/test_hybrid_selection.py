"""`ceemx.fit_hybrid`: the one selection procedure, the real-data experiment through it, and the
learned term's convergence rule (``identification.fitting.term_progress``)."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import math
import re

import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.datasets import REGISTRY
from ceemx.datasets import registry as registry_module
from ceemx.evaluation import hybrid_selection
from ceemx.experiments import real_data, real_data_fits, real_data_report
from ceemx.identification.fitting import epochs, term_progress
from ceemx.systems import LinearSystem

# ---------------------------------------------------------------- no per-dataset constants


def _code_words(module) -> set[str]:
    """Every identifier and string constant of ``module``'s code (docstrings left out)."""
    tree = ast.parse(inspect.getsource(module))
    docstrings = {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }
    words: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            if id(node) not in docstrings:
                words.add(node.value)
        elif isinstance(node, ast.Name):
            words.add(node.id)
        elif isinstance(node, ast.Attribute):
            words.add(node.attr)
        elif isinstance(node, ast.keyword) and node.arg:
            words.add(node.arg)
    return words


#: Words naming a dataset or its system (a constant keyed on them is a per-dataset constant).
_DATASET_WORDS = re.compile(
    "|".join([*REGISTRY, "tank", "silverbox", "duffing", "drive", "belt", "wiener"]), re.I
)


@pytest.mark.parametrize(
    "module",
    [real_data, real_data_fits, real_data_report, hybrid_selection],
    ids=lambda m: m.__name__.rsplit(".", 1)[-1],
)
def test_experiment_code_names_no_dataset(module):
    """No identifier or string in the experiment's code (or the selection's) names a dataset:
    no setting can depend on which dataset is fitted."""
    named = sorted(w for w in _code_words(module) if _DATASET_WORDS.search(w))
    assert named == [], f"{module.__name__} names datasets: {named}"


def test_registry_holds_the_protocol_and_the_physics_only():
    """An entry's fields are the protocol, the published results and the user's physics model;
    the fitting settings (noise, epochs, width, windows, scoring start) are not there."""
    protocol = {
        "name", "source", "columns", "train", "tests", "dt", "n_init", "units", "output_names",
        "output_units", "input_names", "input_units", "citation", "score_unit", "score_scale",
        "published", "window_length", "window_stride",
        "valid_fraction", "default_tests", "test_names", "model",
    }  # fmt: skip
    assert {f.name for f in dataclasses.fields(registry_module.DatasetEntry)} == protocol
    physics = {"factory", "hidden", "options", "bounds", "targets"}
    assert {f.name for f in dataclasses.fields(registry_module.GrayBox)} == physics
    assert not hasattr(registry_module, "HandChosen")
    for e in REGISTRY.values():  # the physics options are structure, not fitting settings
        assert set(e.model.options) <= {"hold"}
        assert "process_noise" not in e.model.options


def test_settings_are_one_for_every_dataset():
    """The run's settings are plain values (no mapping keyed by a dataset)."""
    s = real_data_fits.Settings()
    for f in dataclasses.fields(s):
        value = getattr(s, f.name)
        keys = set(value) if isinstance(value, dict) else set()
        assert not any(_DATASET_WORDS.search(str(k)) for k in keys), f.name


# ---------------------------------------------------------------- fit_hybrid's inputs


def _tiny():
    """A 2-state linear model and a 60-sample record (no fit: nothing compiles)."""
    system = LinearSystem(
        jnp.array([[0.9, 0.1], [0.0, 0.8]]),
        jnp.array([[1.0, 0.0]]),
        jnp.array([[0.0], [1.0]]),
        process_noise=0.1,
        obs_noise=0.1,
    )
    t = np.arange(60, dtype=float)
    y = np.sin(0.3 * t)[None, :, None]
    u = np.cos(0.2 * t)[None, :, None]
    return system, ceemx.Trajectories(jnp.asarray(y), jnp.asarray(u))


def test_split_tail_holds_out_the_end_with_the_initial_window():
    """The fit part is the head; the tail starts n_init samples before the cut, so the samples
    it scores (after its first n_init) are exactly the ones the fit part lacks."""
    _, data = _tiny()
    fit_part, tail = hybrid_selection.split_tail(data, n_init=5, fraction=0.2)
    assert fit_part.num_steps == 48 and tail.num_steps == 17
    y = np.asarray(data.y)
    np.testing.assert_array_equal(np.asarray(fit_part.y), y[:, :48])
    np.testing.assert_array_equal(np.asarray(tail.y), y[:, 43:])
    with pytest.raises(ValueError, match="too short"):
        hybrid_selection.split_tail(data, n_init=20, fraction=0.2)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"noise_factors": ()}, "noise_factors"),
        ({"noise_factors": (1.0, -0.1)}, "noise_factors"),
        ({"validation_fraction": 1.0}, "validation_fraction"),
        ({"score_options": {"nope": 1}}, "score_options"),
        ({"n_init": 0}, "n_init"),
        ({"patience": 0}, "patience"),
        ({"level": 1.0}, "level"),
        ({"level": 0.0}, "level"),
    ],
)
def test_fit_hybrid_refuses_bad_options_before_any_fit(kwargs, match):
    system, data = _tiny()
    kwargs = {"n_init": 5, **kwargs}
    with pytest.raises((ValueError, TypeError), match=match):
        ceemx.fit_hybrid(system, data, **kwargs)


def test_fit_hybrid_is_in_the_facade():
    assert ceemx.fit_hybrid is hybrid_selection.fit_hybrid
    assert ceemx.HybridFit is hybrid_selection.HybridFit
    assert hybrid_selection.NOISE_FACTORS[0] == 1.0
    assert all(
        a > b
        for a, b in zip(
            hybrid_selection.NOISE_FACTORS[:-1], hybrid_selection.NOISE_FACTORS[1:], strict=True
        )
    )


# ---------------------------------------------------------------- the learned term's convergence


def test_term_settles_only_when_J_and_the_weights_stop_over_the_window():
    """One epoch of no change is not enough; a window without a J rise above one epoch's
    tolerance and with weights still is; weights shrinking toward zero (the prior's mode) are
    not settled even when J is flat."""
    W = term_progress.TERM_WINDOW
    w = np.ones(10)
    flat = [100.0] * (W + 1)
    assert term_progress.settled(flat, [w] * (W + 1), tolerance=1e-3)
    assert not term_progress.settled(flat[:W], [w] * W, tolerance=1e-3)  # too few epochs
    rising = [100.0 + 0.01 * k for k in range(W + 1)]  # 0.01 per epoch: each under 0.02
    assert not term_progress.settled(rising, [w] * (W + 1), tolerance=0.02)
    shrinking = [w * 0.5**k for k in range(W + 1)]
    assert not term_progress.settled(flat, shrinking, tolerance=1e-3)


class _Solver:
    rtol, atol = 1e-2, 0.0


class _Problem:
    pass


def test_term_rule_keeps_a_converged_solver_going_until_the_term_settled(monkeypatch):
    """The solver's one-epoch "converged" (the regression: a hybrid "converged after 5 epochs"
    with the term unmoved) goes on, reported not converged, until the window settles; a stop
    for another reason still stops."""
    monkeypatch.setattr(epochs, "objective_scale", lambda problem, state: 1.0)
    weights = iter([np.full(4, 1.0 + 0.1 * k) for k in range(3)] + [np.full(4, 1.2)] * 10)
    monkeypatch.setattr(term_progress, "term_weights", lambda system: next(weights))
    term = term_progress.TermProgress.of(object(), 0.0)
    assert term is not None
    decisions = []
    for k in range(8):
        info = ceemx.EpochInfo(k + 1, None, None, {"J": 1.0})
        decisions.append(epochs._term_rule(term, _Solver(), _Problem(), None, info, True, True))
    # the weights move until epoch 2, then stay: settled once a whole window is still
    assert decisions[:6] == [(False, False)] * 6
    assert decisions[6:] == [(True, True)] * 2
    info = ceemx.EpochInfo(9, None, None, {"J": 1.0})
    assert epochs._term_rule(term, _Solver(), _Problem(), None, info, True, False) == (True, False)


def test_a_refused_continuation_start_restarts_that_weighting_from_the_guess(monkeypatch):
    """The second weighting's fit refuses the first's end (e.g. a parameter pinned at its
    bound): that weighting is fitted from the guess, the selection goes on; a refused guess
    still raises."""
    from ceemx.identification.fitting import driver

    physics = LinearSystem(np.eye(1) * 0.5, np.eye(1), process_noise=0.1, obs_noise=0.1)
    calls = []

    def fake_fit(model, data, x0=None, **options):
        calls.append((float(model.A[0, 0]), x0 is not None))
        if x0 is not None:
            raise ValueError("`A` lies at its bound")
        return type("R", (), {"system": model, "states": "x", "history": [0, 1], "converged": True})

    monkeypatch.setattr(driver, "fit", fake_fit)
    judge = type("J", (), {"score": staticmethod(lambda system: 1.0)})
    said = []
    candidates, fits = hybrid_selection._physics_path(
        physics, None, judge, [1.0, 0.1], 1.0, 5, said.append
    )
    assert [c.factor for c in candidates] == [1.0, 0.1] and len(fits) == 2
    assert calls == [(0.5, False), (0.5, True), (0.5, False)]
    assert any("refused as a start" in line and "from the guess" in line for line in said)

    def refuse(model, data, x0=None, **options):
        raise ValueError("the guess refused")

    monkeypatch.setattr(driver, "fit", refuse)
    with pytest.raises(ValueError, match="the guess refused"):
        hybrid_selection._physics_path(physics, None, judge, [1.0], 1.0, 5, said.append)


def test_patience_from_improvement_waits_for_the_first_real_improvement(monkeypatch):
    """``patience_from="improvement"``: a score that sits within min_delta of the start does
    not run the patience down (the default does: it stops after ``patience`` epochs); once
    the score has improved by min_delta, the patience runs as usual."""
    system, data = _tiny()
    sitting = [1.0 - 1e-5 * k for k in range(1, 11)]  # under min_delta in all
    falling = [0.99, 0.98] + [0.98] * 6
    for mode, expected_stop in (("start", 3), ("improvement", 15)):
        scores = iter([1.0, *sitting, *falling])  # the start's, then epochs 1, 2, …
        monkeypatch.setattr(ceemx.EarlyStopping, "score", lambda self, system, s=scores: next(s))
        stop = ceemx.EarlyStopping(data, n_init=5, patience=3, start=system, patience_from=mode)
        out = [stop(ceemx.EpochInfo(k, k, None, {})) for k in range(1, 19)]
        assert out.index(False) + 1 == expected_stop, mode
        assert stop.stopped
    assert stop.best_epoch == 12  # the last real improvement (0.98); the patience ran from it
    with pytest.raises(ValueError, match="patience_from"):
        ceemx.EarlyStopping(data, n_init=5, patience_from="never")


def test_a_term_that_sits_at_its_start_is_not_stopped_there(monkeypatch):
    """The selection's term training on a validation path that sits within 0.1 % of the
    physics' score for 150 iterations, then falls 0.5 % an iteration for 60, then rises (the
    Bouc–Wen case's term at a tight weighting): the training ends by the patience after the
    best (iteration 210), not 30 iterations into the plateau (the regression: "iteration 30 of
    30", the term never left its start)."""
    from dataclasses import dataclass, field

    start, data = _tiny()

    def path(model) -> float:  # the model of an iteration is its number; the start's 0
        epoch = 0 if model is start else model
        sit = 1.0 - 5e-6 * min(epoch, 150)
        return sit * 0.995 ** min(max(epoch - 150, 0), 60) * (1 + 1e-3 * max(epoch - 210, 0))

    @dataclass
    class Result:
        history: list = field(default_factory=list)
        system: object = None
        theta: object = None
        problem: object = None

    def fake_fit(model, data, states, epochs, callbacks=()):
        res = Result()
        for e in range(1, epochs + 1):
            info = ceemx.EpochInfo(e, e, None, {"epoch": e})
            res.history.append(info.record)
            if any(cb(info) is False for cb in callbacks):
                break
        return res

    monkeypatch.setattr(hybrid_selection, "_fit_term", fake_fit)
    monkeypatch.setattr(ceemx.EarlyStopping, "score", lambda self, system: path(system))
    held = type("Physics", (), {"system": start, "states": None})
    stopper, best, run, why = hybrid_selection._train_term(
        lambda system, data, states: system, held, data, data, 5, 30, {}, 400
    )
    assert why["stopped_by"] == "patience"
    assert stopper.best_epoch == best == 210 and run == 240


# ---------------------------------------------------------------- the procedure on a simulated case


@pytest.mark.slow  # three physics fits, a term's training and the refit (≈ 1–2 min)
def test_fit_hybrid_selects_on_the_training_record_and_beats_the_physics():
    """The Duffing oscillator against its linear physics (tests/test_hybrid.py's case): the
    selection's record is complete, the final model uses every sample, and the hybrid free-runs
    a held-out multisine better than the physics the procedure also returns."""
    import jax
    from tests.test_hybrid import DT, Oscillator, simulate

    true = Oscillator(1.0, 0.3, 1.0, dt=DT, process_noise=1e-3, obs_noise=0.01)
    guess = Oscillator(1.5, 0.5, 0.0, dt=DT, process_noise=1e-2, obs_noise=0.01)
    t = jnp.arange(600, dtype=jnp.float64) * DT
    u = 2 * (jnp.sin(0.7 * t) + 0.6 * jnp.sin(1.9 * t + 1.0) + 0.4 * jnp.sin(3.1 * t + 2.0))
    x = simulate(true, u[None, :, None])
    y = x[..., :1] + 0.01 * jax.random.normal(jax.random.PRNGKey(0), x[..., :1].shape)
    data = ceemx.Trajectories(y, u[None, :, None])
    sel = ceemx.fit_hybrid(
        guess, data, n_init=20, dynamics=(1,), noise_factors=(1.0, 0.1, 0.01), max_epochs=60,
        term_epochs=60, score_options={"warm_process_noise": (1.0, None)},
    )  # fmt: skip
    record = sel.record()
    assert [c["factor"] for c in record["candidates"]] == [1.0, 0.1, 0.01]
    alone = min(record["candidates"], key=lambda c: c["validation_rmse"])
    trained = [c for c in record["candidates"] if c["hybrid_rmse"] is not None]
    assert alone in trained  # the term is trained at the physics' best weighting at least
    chosen = min(trained, key=lambda c: c["hybrid_rmse"])
    assert sel.factor == chosen["factor"] and sel.physics_factor == alone["factor"]
    assert record["best_epoch"] > 0
    assert record["validation_rmse"]["hybrid"] == chosen["hybrid_rmse"] < alone["validation_rmse"]
    assert record["samples"]["total"] == 600 and sel.refit and sel.term_result is not None
    assert sel.term_result.history and len(sel.term_result.history) <= sel.best_epoch + 30
    assert 0 < sel.refit_epoch <= len(sel.term_result.history)
    t2 = jnp.arange(400, dtype=jnp.float64) * DT
    u2 = (1.8 * (jnp.sin(0.5 * t2) + 0.7 * jnp.sin(2.3 * t2 + 0.5)))[None, :, None]
    x2 = simulate(true, u2)
    test = ceemx.Trajectories(x2[..., :1], u2)
    scores = {
        k: float(ceemx.benchmark_score(m, test, 20).rmse[0, 0])
        for k, m in (
            ("physics", sel.physics.system),
            ("hybrid", sel.system),
            ("tail", sel.held_out),
        )
    }
    assert math.isfinite(scores["hybrid"]) and scores["hybrid"] < 0.5 * scores["physics"], scores
    assert "noise weighting" in sel.summary()


@pytest.mark.parametrize(
    ("best", "expected"),
    [
        (0, [1.0, 0.1, 0.01, 0.001]),  # the loosest best: every decade tighter
        (6, [0.001, 0.01, 0.1, 1.0]),  # the tightest best: every decade looser
        (3, [10**-1.5, 10**-2.5, 10**-0.5]),  # nearest first, the tighter before the looser
    ],
)
def test_the_term_is_tried_at_every_decade_from_the_physics_best(best, expected):
    """The physics' score does not decide the weighting (it can be best where the term cannot
    learn): the term is trained at its best factor and at every whole decade from it."""
    cands = [
        hybrid_selection.NoiseCandidate(f, f, 0.5 if k == best else 1.0, 1, True, 0.0)
        for k, f in enumerate(hybrid_selection.NOISE_FACTORS)
    ]
    order = [cands[i].factor for i in hybrid_selection._term_candidates(cands)]
    np.testing.assert_allclose(order, expected)
    cands[2] = dataclasses.replace(cands[2], validation_rmse=math.nan)  # a diverged fit: skipped
    assert 2 not in hybrid_selection._term_candidates(cands)


def test_early_stopping_counts_a_slow_steady_improvement(monkeypatch):
    """Each epoch 0.05 % better (under min_delta = 0.1 %): the patience resets once the steps
    add up to min_delta, so the training goes on; a flat score still stops after `patience`."""
    _, data = _tiny()
    stop = ceemx.EarlyStopping(data, n_init=5, patience=3, min_delta=1e-3)
    scores = iter([1.0 * (1 - 5e-4) ** k for k in range(12)] + [0.99] * 10)
    monkeypatch.setattr(stop, "score", lambda system: next(scores))
    out = [stop(ceemx.EpochInfo(k, None, None, {})) for k in range(1, 13)]
    assert False not in out  # twelve slowly improving epochs: never stopped
    assert stop.best_epoch == 12
    assert not stop.stopped
    flat = [stop(ceemx.EpochInfo(k, None, None, {})) for k in range(13, 23)]
    assert flat.index(False) <= 3  # no real improvement since the last reset: stops
    assert stop.stopped
