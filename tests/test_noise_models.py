"""The extension points of the noise models: what the library asks of a noise model, with the
answers of the built-in ones against closed forms, and a new model's defaults (work where the
answer follows from the density's interface, refuse naming the class where it does not)."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array

import ceemx
from ceemx.models.noise import SecondMoments

R = np.array([[2.0, 0.6, -0.3], [0.6, 1.0, 0.2], [-0.3, 0.2, 0.5]])


class FactorGaussian(ceemx.AbstractGaussianNoise):
    """A Gaussian given by nothing but its Cholesky factor (a new model's least)."""

    L: Array

    def cholesky(self):
        return self.L


def _moments(full, present=None):
    diagonal = np.diagonal(full)
    return SecondMoments(jnp.asarray(full), jnp.asarray(diagonal), jnp.mean(diagonal), present)


def test_masked_fill_completes_a_consistent_moment_exactly():
    # The present part's second moment equal to R's: the filled moment is R itself.
    mask = np.array([True, False, True])
    S = np.where(mask[:, None] & mask[None, :], R, 0.0)
    full = ceemx.CholeskyGaussian(cov=R)
    np.testing.assert_allclose(full.masked_fill(jnp.asarray(S), jnp.asarray(mask)), R, atol=1e-12)
    # independent components are taken one by one: nothing to fill
    diag = ceemx.DiagonalGaussian(jnp.ones(3), 3)
    assert not diag.full_covariance and full.full_covariance
    np.testing.assert_array_equal(diag.masked_fill(jnp.asarray(S), jnp.asarray(mask)), S)


def test_variance_ratios_are_the_whitened_diagonal():
    S = R + np.diag([0.3, 0.1, 0.2])
    L = np.linalg.cholesky(R)
    W = np.linalg.inv(L) @ S @ np.linalg.inv(L).T
    np.testing.assert_allclose(ceemx.CholeskyGaussian(cov=R).variance_ratios(S), np.diag(W))
    scale = np.array([0.5, 1.0, 2.0])
    ratios = ceemx.DiagonalGaussian(jnp.asarray(scale), 3).variance_ratios(S)
    np.testing.assert_allclose(ratios, np.diag(S) / scale**2)
    assert np.all(np.isnan(ceemx.StudentT(1.0, 4.0, 3).variance_ratios(S)))


def test_covariance_update_is_the_gaussian_m_step():
    S = R
    full = ceemx.CholeskyGaussian(cov=np.eye(3)).covariance_update(_moments(S))
    np.testing.assert_allclose(full.covariance(), S, atol=1e-12)
    pooled = ceemx.DiagonalGaussian(jnp.asarray(1.0), 3).covariance_update(_moments(S))
    assert pooled.scale.shape == ()
    assert float(pooled.scale) == pytest.approx(np.sqrt(np.trace(S) / 3))
    present = jnp.asarray([True, False, True])
    old = jnp.asarray([7.0, 8.0, 9.0])
    each = ceemx.DiagonalGaussian(old, 3).covariance_update(_moments(S, present))
    np.testing.assert_allclose(each.scale, [np.sqrt(S[0, 0]), 8.0, np.sqrt(S[2, 2])])


def test_scales_keep_the_class_and_the_leaf_shapes():
    diag = ceemx.DiagonalGaussian(jnp.asarray([0.5, 1.0]), 2)
    assert diag.scale_parameters() is diag.scale
    twice = diag.scaled(2.0)
    assert type(twice) is ceemx.DiagonalGaussian
    np.testing.assert_allclose(twice.scale, [1.0, 2.0])
    np.testing.assert_allclose(diag.with_scale_parameters(jnp.asarray([3.0, 4.0])).std(), [3, 4])
    chol = ceemx.CholeskyGaussian(cov=R).scaled(3.0)
    np.testing.assert_allclose(chol.covariance(), 9.0 * R, atol=1e-12)
    assert ceemx.CholeskyGaussian(cov=R).scale_parameters() is None


def test_describe_names_the_values_a_summary_shows():
    assert set(ceemx.DiagonalGaussian(0.1, 2).describe()) == {"std"}
    assert set(ceemx.StudentT(0.1, 4.0, 2).describe()) == {"scale", "df"}
    marginal = ceemx.CholeskyGaussian(cov=R).describe()["marginal std"]
    np.testing.assert_allclose(marginal, np.sqrt(np.diag(R)))


def test_a_gaussian_given_by_its_factor_works_where_the_factor_suffices():
    new = FactorGaussian(jnp.asarray(np.linalg.cholesky(R)))
    reference = ceemx.CholeskyGaussian(cov=R)
    S = R + 0.1 * np.eye(3)
    mask = jnp.asarray([True, True, False])
    np.testing.assert_allclose(new.variance_ratios(S), reference.variance_ratios(S))
    np.testing.assert_allclose(
        new.masked_fill(jnp.asarray(S), mask), reference.masked_fill(jnp.asarray(S), mask)
    )
    np.testing.assert_allclose(new.describe()["marginal std"], np.sqrt(np.diag(R)))
    new.check_dimension("noise", 3, "state_dim")
    with pytest.raises(ValueError, match=r"`noise` has a covariance of shape \(3, 3\)"):
        new.check_dimension("noise", 2, "state_dim")


@pytest.mark.parametrize(
    "noise", [FactorGaussian(jnp.eye(2)), ceemx.StudentT(1.0, 4.0, 2)], ids=["factor", "student_t"]
)
def test_what_a_model_does_not_implement_is_refused_by_name(noise):
    name = type(noise).__name__
    assert not noise.learnable_in_closed_form
    with pytest.raises(TypeError, match=f"{name} has no closed-form covariance update"):
        noise.covariance_update(_moments(np.eye(2)))
    with pytest.raises(TypeError, match=f"{name} cannot be scaled"):
        noise.scaled(2.0)
    with pytest.raises(TypeError, match=f"{name} has no `scale_parameters"):
        noise.with_scale_parameters(jnp.ones(2))


def test_a_system_checks_a_new_models_dimension():
    A, C = jnp.eye(2), jnp.ones((1, 2))
    wrong = FactorGaussian(jnp.eye(3))
    with pytest.raises(ValueError, match="`system.process_noise` has a covariance of shape"):
        ceemx.systems.LinearSystem(A, C, process_noise=wrong)
    system = ceemx.systems.LinearSystem(A, C, process_noise=FactorGaussian(jnp.eye(2)))
    assert eqx.tree_equal(system.process_noise, FactorGaussian(jnp.eye(2)))


def test_noise_models_and_systems_print_their_values():
    """``print`` shows scales and parameters (not ``f64[]``); big or traced arrays stay short."""
    import jax

    f64 = jnp.float64
    assert repr(ceemx.DiagonalGaussian(jnp.asarray(0.05, f64), 1)) == (
        "DiagonalGaussian(scale=0.05, dim=1)"
    )
    assert "scale=[0.1, 0.002]" in repr(ceemx.DiagonalGaussian(jnp.array([0.1, 2e-3], f64), 2))
    system = ceemx.systems.LinearSystem(
        jnp.full((6, 6), 0.5, f64), jnp.eye(6, dtype=f64)[:1], process_noise=0.01, obs_noise=0.2
    )
    text = repr(system)
    assert "A=f64[6,6]" in text and "C=[[1, 0, 0, 0, 0, 0]]" in text  # 36 entries: the shape
    assert "obs_noise=DiagonalGaussian(scale=0.2, dim=1)" in text

    @jax.jit
    def traced(noise):
        assert repr(noise).startswith("DiagonalGaussian(scale=f64[]")
        return noise.scale

    traced(ceemx.DiagonalGaussian(jnp.asarray(0.05, f64), 1))
