import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.evaluation.prediction import (
    AbstractPredictor,
    BestValidation,
    ResidualPredictor,
    StateSpacePredictor,
    as_predictor,
    one_step_predictions,
    prediction_rmse,
    residual_data,
)
from ceemx.systems import LinearSystem, NeuralObservationSystem


class InputEcho(AbstractPredictor):
    """ŷ_t = k·u_t (a regressor for the tests)."""

    k: float = 1.0

    def predict(self, data):
        return self.k * data.u[..., : data.y.shape[-1]]


def _data(B=3, T=12, m=2, p=2, seed=0):
    rng = np.random.default_rng(seed)
    return ceemx.Trajectories(rng.normal(size=(B, T, m)), rng.normal(size=(B, T, p)))


def test_prediction_rmse_is_the_authors_formula():
    data = _data()
    pred = np.asarray(data.y) + 0.1
    pred[:, :5] += 100.0  # before `start`: not scored
    scale = np.array([2.0, 3.0])
    got = prediction_rmse(pred, data, start=5, scale=scale)
    # compute_rms: sqrt(sum over t ≥ start and j of ((y − ŷ)·s_j)² / (T' m))
    want = np.sqrt(((0.1 * scale) ** 2).sum() / 2) * np.ones(3)
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_prediction_rmse_respects_the_mask():
    rng = np.random.default_rng(1)
    y = rng.normal(size=(2, 10, 2))
    mask = np.ones((2, 10, 2), bool)
    mask[0, 6:, 1] = False
    data = ceemx.Trajectories(y, None, mask)
    pred = np.asarray(data.y).copy()
    pred[0, 6:, 1] += 1e6  # masked: ignored
    pred[1] += 1.0
    got = prediction_rmse(pred, data, start=2)
    np.testing.assert_allclose(got, [0.0, 1.0], atol=1e-12)
    with pytest.raises(ValueError, match="start"):
        prediction_rmse(pred, data, start=10)
    with pytest.raises(ValueError, match="predictions"):
        prediction_rmse(pred[:, :5], data)


def test_residual_predictor_adds_the_residual_models_prediction():
    data = _data()
    base = InputEcho(1.0)
    res = ResidualPredictor(base, InputEcho(0.5))
    np.testing.assert_allclose(res.predict(data), 1.5 * np.asarray(data.u), rtol=1e-12)
    r = residual_data(data, base.predict(data))
    np.testing.assert_allclose(r.y, np.asarray(data.y) - np.asarray(data.u), rtol=1e-12)


def test_as_predictor_wraps_systems_and_rejects_others():
    sys = LinearSystem(0.5 * jnp.eye(2), jnp.eye(2))
    assert isinstance(as_predictor(sys), StateSpacePredictor)
    echo = InputEcho()
    assert as_predictor(echo) is echo
    with pytest.raises(TypeError, match="model"):
        as_predictor(3.0)
    with pytest.raises(TypeError, match="data"):
        one_step_predictions(sys, np.zeros((1, 3, 2)))


def test_state_space_predictor_of_a_linear_system_is_causal():
    sys = LinearSystem(0.8 * jnp.eye(2), jnp.eye(2), B=jnp.eye(2), D=0.1 * jnp.eye(2))
    data = _data()
    pred = one_step_predictions(sys, data)
    y2 = np.asarray(data.y).copy()
    y2[:, 7] += 5.0
    pred2 = one_step_predictions(sys, ceemx.Trajectories(y2, data.u))
    np.testing.assert_array_equal(np.asarray(pred)[:, :8], np.asarray(pred2)[:, :8])
    assert not np.allclose(np.asarray(pred)[:, 8:], np.asarray(pred2)[:, 8:])


def test_best_validation_keeps_the_best_epoch():
    data = _data()
    good = LinearSystem(0.0 * jnp.eye(2), jnp.eye(2), B=jnp.eye(2), D=jnp.zeros((2, 2)))
    bad = LinearSystem(0.0 * jnp.eye(2), jnp.eye(2), B=jnp.eye(2), D=5 * jnp.eye(2))
    cb = BestValidation(data, start=2, initial_system=bad)
    assert cb.best_epoch == 0

    class Info:
        def __init__(self, epoch, system):
            self.epoch, self.system = epoch, system

    assert "val_rmse" in cb(Info(1, good))
    cb(Info(2, bad))
    assert cb.best_epoch == 1 and cb.best_system is good
    assert cb.rmse[0] < cb.rmse[1]


def _neural_matrices():
    return 0.9 * jnp.eye(3), jnp.ones((3, 2)), jnp.ones((4, 3)), jnp.zeros((4, 2))


def test_neural_observation_system_is_eq17_and_validates():
    key = jax.random.PRNGKey(0)
    A, B, C, D = _neural_matrices()
    s = NeuralObservationSystem(A, B, C, D, key=key, gain=0.1)
    x, u = jnp.arange(3.0), jnp.ones(2)
    np.testing.assert_allclose(s.dynamics(x, u, 0), A @ x + B @ u)
    nn = s.observe(x, u, 0) - (C @ x + D @ u)
    np.testing.assert_allclose(nn, s.net(jnp.concatenate([x, u])), rtol=1e-12)
    assert 0 < float(jnp.max(jnp.abs(nn))) < 1.0  # gain 0.1: a small correction at the start
    # `gain` scales the last layer only: Equinox draws a Linear layer's weight and bias from
    # U(±1/√in), so the last layer's (128 + 4 entries) lie within 0.1/√32 and its largest beyond
    # half of that (a gain of 1 or 0 fails), while a hidden layer's largest is beyond 0.5/√32.
    last, hidden = s.net.layers[-1], s.net.layers[-2]
    bound = 1 / np.sqrt(32)
    top = max(float(jnp.max(jnp.abs(last.weight))), float(jnp.max(jnp.abs(last.bias))))
    assert 0.05 * bound < top <= 0.1 * bound, top / bound
    assert float(jnp.max(jnp.abs(hidden.weight))) > 0.5 * bound
    assert (s.state_dim, s.obs_dim, s.input_dim) == (3, 4, 2)
    with pytest.raises(ValueError, match="`D`"):
        NeuralObservationSystem(A, B, C, jnp.zeros((4, 3)), key=key)
    with pytest.raises(ValueError, match="`C`"):
        NeuralObservationSystem(A, B, jnp.ones((4, 2)), D, key=key)


# A second oracle of the gain (checked above by the last layer's range; the zero output of
# init_mlp with gain 0 by test_hybrid's zero-initialised hybrid): gain = 0.0 compiles the network's
# initialisation again (the gain is a static argument of `_init_mlp`, ≈ 3 s).
@pytest.mark.slow
def test_neural_observation_system_with_zero_gain_is_linear():
    A, B, C, D = _neural_matrices()
    s0 = NeuralObservationSystem(A, B, C, D, key=jax.random.PRNGKey(0), gain=0.0)
    x, u = jnp.arange(3.0), jnp.ones(2)
    np.testing.assert_allclose(s0.observe(x, u, 0), C @ x + D @ u, atol=1e-14)
