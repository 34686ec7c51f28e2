"""`converged` means converged: no ``converged=True`` from a fit that could not move or judge.

Each test failed on the tree before its fix, where the fit reported ``converged=True`` (or
crashed deep inside): a start at an absurd scale (a positive parameter at 1e-300, one at 1e100,
an interval parameter at 1 + 1e-12) "converged" with θ never moving; data with no observation
"converged" after one epoch; tolerances that cannot fail (rtol = 1e300, atol = 1e300,
ρ_θ = 1e300, damping = 1e300 or 0, iteration bounds that wrap in int32) and options changed with
``eqx.tree_at`` (never checked) were accepted; a model with a NaN region froze the states of
Algorithm 1 and "converged"; a start with a non-finite gradient returned J = 0.0; Laplace EM
"converged" while its own status said "no step decreases the objective", recorded J = 0.0 for an
epoch whose E-step failed, and its quasi-Newton acceleration raised LAPACK's LinAlgError.

One tiny model serves every test (y = c·√x: NaN for x < 0, an infinite derivative at 0); most
refusals come before any compute, and the two fits share their compiled programs.
"""

import warnings

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array

import ceemx
from ceemx.identification.fitting.finish import end_status
from ceemx.identification.fitting.start import refuse_failed_start
from ceemx.identification.solvers import laplace_qn
from ceemx.identification.solvers.base import FitState, total_J
from ceemx.lib.results import RESULTS, codes, messages, select


class Root(ceemx.AbstractSystem):
    """x' = a·x + w, y = c·√x + v (NaN for x < 0); d a one-sided parameter the model ignores."""

    a: Array = ceemx.param(lower=-1.0, upper=1.0)
    c: Array = ceemx.param(positive=True)
    d: Array = ceemx.param(upper=-2.0)

    @property
    def state_dim(self):
        return 1

    @property
    def obs_dim(self):
        return 1

    def dynamics(self, x, u, t):
        return self.a * x + 0.0 * self.d

    def observe(self, x, u, t):
        return self.c * jnp.sqrt(x)


def root(a=0.5, c=1.5, d=-3.0, noise=0.1):
    return Root(a=a, c=c, d=d, process_noise=noise, obs_noise=noise)


B, T = 2, 30
_rng = np.random.default_rng(1)
_x = np.empty((B, T))
_x[:, 0] = 2.0
for _t in range(1, T):
    _x[:, _t] = 0.9 * _x[:, _t - 1] + 0.05 * _rng.standard_normal(B)
DATA = ceemx.Trajectories((np.sqrt(np.abs(_x)) + 0.1 * _rng.standard_normal((B, T)))[..., None])
X0 = np.full((B, T, 1), 0.5)  # the smoother's every trial step leads to x < 0: NaN
SOLVERS = [ceemx.Alternating, ceemx.JointLM, ceemx.LaplaceEM]


def fit(system=None, x_init=X0, **options):
    options = {"max_epochs": 20, "progress": False, "diagnose": False, **options}
    return ceemx.fit(root() if system is None else system, DATA, x_init, **options)


# --- starts no fit can move from: refused before any compute ----------------------------------


@pytest.mark.parametrize(
    "kwargs, text",
    [
        (dict(c=1e-300), "`system.c` = 1e-300 is 1e-300 from its bound 0"),
        (dict(c=1e-200), "`system.c` = 1e-200 is 1e-200 from its bound 0"),
        (dict(c=1e100), "`system.c` = 1e+100 is 1e+100 or more in magnitude"),
        (dict(c=1e308), "`system.c` = 1e+308 is 1e+100 or more in magnitude"),
        (dict(a=1 - 1e-12), "`system.a` = 0.999999999999 is 1e-12 from its bound 1"),
        (dict(d=-2 - 1e-12), "`system.d` = -2.000000000001 is 1e-12 from its bound -2"),
    ],
    ids=["positive-1e-300", "positive-1e-200", "1e100", "1e308", "interval", "upper"],
)
def test_start_at_an_absurd_scale_is_refused(kwargs, text):
    """15 of 30 such starts reported converged=True with θ never moving."""
    for solver in SOLVERS:
        with pytest.raises(ValueError, match=text.replace("+", r"\+").replace("(", r"\(")):
            fit(root(**kwargs), solver=solver())


@pytest.mark.parametrize("c", [1e-20, 1e-12])
def test_start_absurd_against_the_data_is_refused(c):
    """c·√x with y ≈ 1.4: c = 1e-20 is far from 0's rounding, but its e-fold change moves the
    residuals by 1e-20 of their size; Alternating and JointLM reported converged=True with c
    frozen (from 1e-12: moved 0.25 %, "converged")."""
    x_init = np.full((B, T, 1), 2.0)
    for solver in SOLVERS:
        with pytest.raises(ValueError, match=f"`system.c` = {c:g} is too near its bound for the"):
            fit(root(c=c), x_init, solver=solver())


def test_start_just_clear_of_the_limits_is_accepted():
    problem, theta = ceemx.FitProblem.create(root(c=1e-90, a=1 - 1e-9, d=-2 - 1e-9), DATA)
    assert np.all(np.isfinite(np.asarray(theta))) and problem is not None


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: s.__name__)
def test_data_without_observation_is_refused(solver):
    """JointLM reported converged=True after one epoch on data whose every y is masked."""
    empty = ceemx.Trajectories(DATA.y, mask=np.zeros(DATA.y.shape, bool))
    modes = ["fixed", "learn"] if solver().noise_rounds else ["fixed"]
    for noise in modes:
        with pytest.raises(ValueError, match="`data` holds no observation"):
            ceemx.fit(root(), empty, X0, solver=solver(), noise=noise, progress=False)


# --- options whose stopping rule cannot fail, or that wrap: refused ---------------------------


@pytest.mark.parametrize(
    "make, text",
    [
        (lambda: ceemx.Alternating(rtol=1e300), "`rtol` must be < 1"),
        (lambda: ceemx.LaplaceEM(rtol=1.0), "`rtol` must be < 1"),
        (lambda: ceemx.JointLM(damping=1e300), "the initial damping must be below 1/rtol"),
        (lambda: ceemx.JointLM(damping=0.0), "`damping` must be finite and > 0"),
        (lambda: ceemx.LMSmoother(damping=0.0), "`damping` must be finite and > 0"),
        (lambda: ceemx.JointLM(max_trials=2**31), "`max_trials` must be an integer <= 2147483647"),
        (
            lambda: ceemx.LMLearner(max_steps=2**32 + 5),
            "`max_steps` must be an integer <= 2147483647",
        ),
    ],
    ids=["rtol", "rtol-1", "damping-huge", "damping-0", "smoother-damping-0", "int32", "wrap"],
)
def test_options_that_decide_the_fit_are_refused(make, text):
    with pytest.raises(ValueError, match=text.replace("*", r"\*")):
        make()


@pytest.mark.parametrize(
    "solver, text",
    [
        (eqx.tree_at(lambda s: s.smoother.rho_x, ceemx.Alternating(), -1.0), "`rho_x` must be"),
        (eqx.tree_at(lambda s: s.rho_theta, ceemx.LaplaceEM(), np.nan), "`rho_theta` must be"),
        (eqx.tree_at(lambda s: s.rtol, ceemx.JointLM(), 1e300), "`rtol` must be < 1"),
        (eqx.tree_at(lambda s: s.damping, ceemx.JointLM(), 0.0), "`damping` must be"),
    ],
    ids=["smoother-rho_x", "rho_theta-nan", "rtol", "damping"],
)
def test_options_changed_by_tree_at_are_checked_at_fit(solver, text):
    """Equinox's tree_at skips __check_init__: 66 of 66 invalid values reached the fit."""
    with pytest.raises(ValueError, match=text):
        fit(solver=solver)


def test_smoother_changed_by_tree_at_is_checked_at_smooth():
    """``LMSmoother`` with ρ_x = −1 'converged' at J = −4.2e21."""
    bad = eqx.tree_at(lambda s: s.rho_x, ceemx.LMSmoother(), -1.0)
    with pytest.raises(ValueError, match="`rho_x` must be finite and >= 0"):
        ceemx.smooth(root(), DATA, X0, bad)


@pytest.mark.parametrize(
    "solver, text",
    [
        (ceemx.Alternating(atol=1e300), "`atol` = 1e+300 cannot fail"),
        (ceemx.LaplaceEM(atol=1e300), "`atol` = 1e+300 cannot fail"),
        (ceemx.LaplaceEM(rho_theta=1e300), "`rho_theta` = 1e+300 holds θ at the start"),
        (ceemx.JointLM(rho_x=1e300), "`rho_x` = 1e+300 holds the states at the start"),
        (
            ceemx.Alternating(smoother=ceemx.LMSmoother(rho_x=1e300)),
            "`smoother.rho_x` = 1e+300 holds the states",
        ),
    ],
    ids=["atol", "laplace-atol", "rho_theta", "rho_x", "smoother-rho_x"],
)
def test_tolerances_and_trust_regions_against_the_data(solver, text):
    """Each 'converged' after one epoch: refused against the start's misfit, before any epoch."""
    with pytest.raises(ValueError, match=text.replace("+", r"\+")):
        fit(solver=solver)


# --- what the end point shows: statuses that name it -------------------------------------------


def test_states_that_never_moved_are_not_converged():
    """Every smoothing trial leads to x < 0 (NaN): the states stay at their start, θ is fitted to
    them, and Algorithm 1 reported converged=True after 12 epochs."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the health test's and the noise's own remarks
        result = fit(solver=ceemx.Alternating())
    assert all(h["dx_norm"] == 0.0 for h in result.history)
    assert sum(h["dtheta_norm"] for h in result.history) > 0.1  # θ moved, the states did not
    assert not result.converged
    assert np.all(codes(result.status) == codes(RESULTS.never_moved))
    assert "the fit never moved" in result.messages()[0]
    summary = " ".join(result.summary(uncertainty=False).split())
    assert (
        "NOT converged" in summary
        and "status all 2 trajectories: not converged: the fit" in summary
    )


def test_a_start_with_a_nonfinite_gradient_is_refused_naming_it():
    """√x at x = 0: J finite, its derivative not; the fit returned J = 0.0, not converged, without
    saying where."""
    x = X0.copy()
    x[:, 3, 0] = 0.0
    with pytest.warns(UserWarning, match="smoothing failed"):  # the first epoch's
        with pytest.raises(ValueError, match=r"gradient is not.*time step 3, component 0"):
            fit(x_init=x, solver=ceemx.Alternating())


def test_a_start_with_a_nonfinite_J_names_the_noise():
    """A noise scale whose square underflows makes J infinite for any states: say so."""
    with pytest.raises(ValueError, match=r"no trajectory has a finite objective.*std 1e-160"):
        fit(root(noise=1e-160))


def test_a_failed_start_with_a_finite_gradient_names_the_noise():
    """Laplace EM's E-step failing at the start (a collapsed noise scale) raised deep inside."""
    problem, theta = ceemx.FitProblem.create(root(), DATA)
    with pytest.raises(ValueError, match="LaplaceEM's first evaluation failed.*process_noise"):
        refuse_failed_start(problem, theta, jnp.asarray(X0), ceemx.LaplaceEM(), at_init=True)


def _state(theta, J, weights=(1.0, 1.0), status=RESULTS.successful):
    J = jnp.asarray(J, jnp.float64)
    return FitState(
        theta=jnp.asarray(theta, jnp.float64),
        states=jnp.asarray(X0),
        J=J,
        weights=jnp.asarray(weights, jnp.float64),
        status=select(jnp.ones(J.shape, bool), status, RESULTS.successful),
    )


def _epochs(dtheta, dx):
    return [
        {"dtheta_norm": a, "dx_norm": b, "failed_trajectories": []}
        for a, b in zip(dtheta, dx, strict=True)
    ]


def test_J_of_an_epoch_where_every_trajectory_failed_is_nan():
    """Laplace EM recorded J = 0.0 (an empty sum) for an epoch whose E-step failed everywhere."""
    assert np.isnan(total_J(_state([1.0], [3.0, 4.0], weights=(0.0, 0.0))))
    assert total_J(_state([1.0], [3.0, 4.0], weights=(1.0, 0.0))) == 3.0


def test_end_status_rules():
    start = _state([1.0, 2.0], [-9.0, -9.0])
    moved = _epochs([0.5, 1e-3], [0.2, 1e-4])
    # θ never moved: never_moved, whatever the stopping rule said
    state, converged = end_status(
        _state([1.0, 2.0], [-5.0, -5.0]), start, _epochs([0.0], [1.0]), True
    )
    assert not converged
    assert messages(state.status) == [RESULTS[RESULTS.never_moved]] * 2
    # a trajectory ended stalled (Laplace EM with one observed sample): not converged
    stalled = _state([1.0, 2.0], [-5.0, -5.0], status=RESULTS.stalled)
    assert end_status(stalled, start, moved, True)[1] is False
    # J not finite on a trajectory taking part
    state, converged = end_status(_state([1.0, 2.0], [-5.0, np.nan]), start, moved, True)
    assert not converged
    assert list(codes(state.status)) == [
        codes(RESULTS.successful),
        codes(RESULTS.nonfinite_objective),
    ]
    # a start at the optimum (θ within rounding, the states unmoved) stays converged
    still = _epochs([1e-13], [0.0])
    assert end_status(_state([1.0, 2.0], [-5.0, -5.0]), start, still, True)[1] is True
    assert end_status(_state([1.0, 2.0], [-5.0, -5.0]), start, moved, True)[1] is True


def test_quasi_newton_start_without_curvature_takes_an_em_step(monkeypatch):
    """Q's derivatives not finite (an E-step that failed) reached LAPACK: LinAlgError from eigh in
    21 of 100 bank fits. Now: the identity and no gradient, so the next epoch is a plain EM step."""
    problem, theta = ceemx.FitProblem.create(root(), DATA)
    P = theta.shape[0]
    nan = jnp.full((P,), np.nan)

    def broken(problem, theta, e, *, hessian):
        return jnp.nan, nan, jnp.full((P, P), np.nan)

    monkeypatch.setattr(laplace_qn, "q_derivatives", broken)
    Hinv, g = laplace_qn.qn_start(problem, theta, None)
    np.testing.assert_array_equal(Hinv, np.eye(P))
    np.testing.assert_array_equal(g, np.zeros(P))
