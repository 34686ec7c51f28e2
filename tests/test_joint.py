"""The joint (x, θ) Levenberg–Marquardt method: exact steps, agreement with alternation, failure
paths, one linearisation per accepted step, and compile-once.

Compilation dominates the run time (each (batch shape, θ size, linear solver) compiles the joint
iteration), so every fit below runs on one shared problem — a single Lorenz attractor observed
directly (C = I), T = 32, learning (σ, ρ, β) and the coupling H (which has no effect for one
attractor: its nine columns of the Jacobian are zero, so the Schur complement is singular). Two
trajectories for most fits, three for the exclusion test, plus one CG configuration. The
``instrumented`` fixture routes the module's compiled entry points through wrappers that fail on a
second trace of a configuration and count evaluations of the joint objective.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
import ceemx.identification.schur
import ceemx.identification.solvers.joint
import ceemx.inference.smoother
from ceemx import lib as linalg
from ceemx.identification.learning import make_problem
from ceemx.inference.objective import linearize
from ceemx.lib import marquardt_scale
from ceemx.systems import CoupledLorenz, initial_states, random_coupling

simulate = eqx.filter_jit(ceemx.simulate)  # eager simulation costs seconds


@pytest.fixture(scope="module", autouse=True)
def instrumented():
    """Route the joint method's and the smoother's compiled entry points through fresh wrappers.

    A wrapper's Python body runs only while tracing: a second (successful) trace of a configuration
    (batch shape, θ size, dtype, linear solver) raises, whichever test causes it. The wrappers
    inline the library's own functions, so results are unchanged. Every evaluation of the joint
    objective and linearisation (``schur.joint_evaluator``'s ``evaluate``) also increments
    ``log.evaluations`` at run time, through ``jax.debug.callback`` (it works inside
    ``lax.while_loop``).
    """
    joint, smoothing = ceemx.identification.solvers.joint, ceemx.inference.smoother
    schur = ceemx.identification.schur
    raw_iteration = joint._iteration.__wrapped__
    raw_linearize = schur.linearize_joint.__wrapped__
    raw_evaluator = schur.joint_evaluator
    raw_smooth = smoothing._smooth_batch  # the compiled program (max_steps an argument)
    log = _TraceLog()

    def counting_evaluator(problem, weights, offset):
        evaluate = raw_evaluator(problem, weights, offset)

        def counted(z):
            jax.debug.callback(log.count)
            return evaluate(z)

        return counted

    @eqx.filter_jit
    def iteration(opts, problem, weights, theta, states, lam):
        out = raw_iteration(opts, problem, weights, theta, states, lam)
        log.record("iteration", states, theta, opts.linear_solver)
        return out

    @eqx.filter_jit
    def linearize_joint(problem, weights, theta, states):
        out = raw_linearize(problem, weights, theta, states)
        log.record("linearize", states, theta)
        return out

    @eqx.filter_jit
    def smooth_batch(solver, max_steps, system, states, data, covariance):
        out = raw_smooth(solver, max_steps, system, states, data, covariance)
        log.record("smooth", states, covariance)
        return out

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(schur, "joint_evaluator", counting_evaluator)
        mp.setattr(joint, "_iteration", iteration)
        mp.setattr(schur, "linearize_joint", linearize_joint)
        mp.setattr(smoothing, "_smooth_batch", smooth_batch)
        yield log


class _TraceLog:
    def __init__(self):
        self.traces = []
        self.evaluations = 0

    def record(self, kind, states, *rest):
        key = (kind, states.shape, str(states.dtype)) + tuple(
            a.shape if hasattr(a, "shape") else a for a in rest
        )
        if key in self.traces:
            raise AssertionError(f"{kind} retraced for an already compiled configuration {key}")
        self.traces.append(key)

    def count(self):
        self.evaluations += 1


# --------------------------------------------------------------------------------------------------
# The damped joint normal equations (coupled Lorenz, K = 2)
# --------------------------------------------------------------------------------------------------


def _coupled(K=2, T=6, B=2, m=4, seed=0):
    """Coupled Lorenz with θ = (σ, ρ, β, H); a linearisation needs no realistic data: states near
    the attractor, arbitrary observations."""
    rng = np.random.default_rng(seed)
    n = 3 * K
    system = CoupledLorenz(
        jnp.full(K, 10.0),
        jnp.full(K, 28.0),
        jnp.full(K, 8 / 3),
        jnp.asarray(rng.standard_normal((m, n))),
        H=random_coupling(jax.random.PRNGKey(seed), K),
        process_noise=0.3,
        obs_noise=0.1,
    )
    x = np.tile([-6.0, -6.0, 24.0], K) + 3.0 * rng.standard_normal((B, T, n))
    data = ceemx.Trajectories(jnp.asarray(5.0 * rng.standard_normal((B, T, m))))
    return system, data, jnp.asarray(x)


def test_joint_step_equals_dense_gauss_newton():
    """The arrowhead solve of the damped joint normal equations equals a dense NumPy solve."""
    system, data, x = _coupled()
    trainable = lambda s: (s.sigma, s.rho, s.beta, s.H)  # noqa: E731
    problem, th = make_problem(system, x, data, trainable=trainable)
    B, T, n = x.shape
    lam = jnp.asarray(1e-3, x.dtype)

    @eqx.filter_jit
    def dense_parts(problem, x, th):
        def r(xflat, th):
            xb = xflat.reshape(x.shape)
            return ceemx.whitened_residuals(problem.build(th), xb, data).reshape(-1)

        xflat = x.reshape(-1)
        return jax.jacfwd(r, 0)(xflat, th), jax.jacfwd(r, 1)(xflat, th), r(xflat, th)

    @eqx.filter_jit
    def arrowhead_step(problem, x, th):
        lin = jax.vmap(
            lambda xb, y, u, m: linearize(problem.build, th, xb, y, u, m, wrt_theta=True)
        )(x, data.y, data.u, data.mask)
        # Same damping on both sides: Marquardt scaling per variable.
        A = lin.hess_x
        dA = jnp.diagonal(A.diagonal, axis1=-2, axis2=-1)
        sA = marquardt_scale(dA.reshape(-1), lam).reshape(dA.shape)
        D = lin.D.sum(0)
        sD = marquardt_scale(jnp.diag(D), lam)
        A_d = linalg.add_to_diagonal(A, sA)
        rhs_t = -lin.grad_theta.sum(0)
        sol = linalg.arrowhead_solve(A_d, lin.E, D + jnp.diag(sD), -lin.grad_x, rhs_t)
        return sol, sA, sD

    Jx, Jt, rv = map(np.asarray, dense_parts(problem.problem, x, th))
    sol, sA, sD = arrowhead_step(problem.problem, x, th)
    H = np.block([[Jx.T @ Jx, Jx.T @ Jt], [Jt.T @ Jx, Jt.T @ Jt]])
    g = np.concatenate([Jx.T @ rv, Jt.T @ rv])
    step = -np.linalg.solve(H + np.diag(np.concatenate([np.ravel(sA), np.asarray(sD)])), g)
    assert bool(sol.ok)
    np.testing.assert_allclose(
        np.ravel(sol.dx), step[: B * T * n], rtol=1e-9, atol=1e-9 * np.abs(step).max()
    )
    np.testing.assert_allclose(
        sol.dtheta, step[B * T * n :], rtol=1e-9, atol=1e-9 * np.abs(step).max()
    )


# --------------------------------------------------------------------------------------------------
# The shared problem: single Lorenz, fully observed, T = 32
# --------------------------------------------------------------------------------------------------


def where_theta(s):
    # H has no effect on a single attractor (its own block is masked): 9 parameters with zero
    # Jacobian columns, so every fit below also exercises a singular Schur complement.
    return (s.sigma, s.rho, s.beta, s.H)


def theta_of(s):
    return np.concatenate([np.ravel(a) for a in where_theta(s)])


@pytest.fixture(scope="module")
def lz():
    """Three trajectories; fits use the first two (``data``, ``x0``) unless they need three.

    Fully observed with process noise dominating (σ_w = 0.1, σ_v = 0.01): x and θ weakly coupled,
    so that alternation (which crawls on strongly coupled problems) also converges in a few hundred
    epochs.
    """
    k1, k2 = jax.random.split(jax.random.PRNGKey(3))
    noise = dict(process_noise=0.1, obs_noise=0.01)
    true = CoupledLorenz(10.0, 28.0, 8 / 3, jnp.eye(3), **noise)
    xs, data3 = simulate(true, k1, initial_states(k2, 3, 1), 32)
    guess = CoupledLorenz(10.6, 27.0, 2.5, jnp.eye(3), **noise)
    x3 = xs + 0.05 * np.random.default_rng(9).standard_normal(xs.shape)
    return dict(
        true=true, guess=guess, xs=xs, data3=data3, x3=x3, data=data3[np.array([0, 1])], x0=x3[:2]
    )


def fit(lz, solver, *, guess=None, x0=None, **kw):
    """``ceemx.fit`` on the two-trajectory problem (same shapes, hence the same compilation)."""
    guess = lz["guess"] if guess is None else guess
    x0 = lz["x0"] if x0 is None else x0
    kw = dict(trainable=where_theta, max_epochs=40) | kw
    return ceemx.fit(guess, lz["data"], x0, solver=solver, **kw)


@pytest.fixture(scope="module")
def joint(lz):
    return fit(lz, ceemx.JointLM(rtol=1e-13))


@pytest.mark.slow
def test_joint_and_alternate_reach_the_same_optimum(lz, joint):
    alt = fit(
        lz,
        ceemx.Alternating(smoother=ceemx.LMSmoother(rtol=1e-14), rtol=1e-13),
        max_epochs=400,
    )
    assert joint.converged
    assert alt.converged
    np.testing.assert_allclose(theta_of(joint.system), theta_of(alt.system), rtol=1e-6)
    np.testing.assert_allclose(joint.states, alt.states, atol=1e-5)
    assert np.max(np.abs(theta_of(joint.system)[:3] / theta_of(lz["guess"])[:3] - 1)) > 1e-2
    # J never decreases across accepted joint steps.
    J = joint.history_array("J")
    assert np.all(np.diff(J) >= -1e-9 * np.abs(J[1:]))
    assert J[0] >= joint.initial_J


def test_singular_schur_complement_is_damped_not_nan(lz, joint):
    """Parameters with no effect make S singular; the step stays finite and the fit converges."""
    assert joint.converged
    assert np.all(np.isfinite(np.asarray(joint.system.H)))
    np.testing.assert_array_equal(joint.system.H, lz["guess"].H)  # no gradient, no move
    assert all(h["accepted"] for h in joint.history)


def test_one_linearisation_per_joint_iteration(lz, instrumented):
    """Joint linearisations = one per iteration (epoch), however many LM trials it takes.

    Trial points are judged by the objective's value alone. From x = 0, with tiny initial damping
    and stiff dynamics (σ_w = 1e-3 in the model), some iterations reject trials: those cost no
    linearisation.
    """
    guess = eqx.tree_at(lambda s: s.process_noise, lz["guess"], ceemx.DiagonalGaussian(1e-3, 3))
    jax.effects_barrier()
    instrumented.evaluations = 0
    opts = ceemx.JointLM(rtol=1e-13, damping=1e-9, max_theta_step=np.inf)  # rejections wanted
    # The noise is too tight for the data on purpose: no end-of-fit noise check (its warning).
    res = fit(lz, opts, guess=guess, x0=jnp.zeros_like(lz["x0"]), diagnose=False)
    jax.effects_barrier()
    trials = res.history_array("trials")
    assert res.converged
    # One more wherever the identifiability check formed the Schur complement.
    checks = sum(h["identifiability_checked"] for h in res.history)
    assert instrumented.evaluations == len(res.history) + checks, (instrumented.evaluations, trials)
    assert np.any(trials == 1)
    assert np.any(trials > 1)
    assert res.epochs > 1


def test_numbers_are_traced(lz, instrumented):
    """New tolerances, trust-region weights and damping do not compile the smoother or the joint
    iteration again (a retrace raises in the ``instrumented`` wrappers)."""
    smoothed, fitted = [], []
    for rtol, rho_x, damping in [(1e-1, 0.0, 1e-3), (1e-9, 0.5, 1e-2), (1e-12, 2.0, 1e-5)]:
        solver = ceemx.LMSmoother(rtol=rtol, rho_x=rho_x)
        smoothed.append(ceemx.smooth(lz["guess"], lz["data"], lz["x0"], solver))
        solver = ceemx.JointLM(rtol=rtol, rho_x=rho_x, damping=damping)
        fitted.append(fit(lz, solver, max_epochs=3))
    assert sum(k[0] == "smooth" for k in instrumented.traces) == 1
    assert sum(k[0] == "iteration" for k in instrumented.traces) <= 3  # B = 2 and 3, CG
    assert sum(k[0] == "linearize" for k in instrumented.traces) <= 2  # B = 2 and 3
    # The numbers took effect.
    iters = [int(np.max(np.asarray(s.iterations))) for s in smoothed]
    assert iters[0] < iters[2], iters
    assert not np.allclose(smoothed[0].states, smoothed[2].states, rtol=0, atol=1e-12)
    damping = [f.history[0]["damping"] for f in fitted]
    assert len(set(damping)) == 3, damping
    assert len({float(f.history_array("J")[-1]) for f in fitted}) == 3


@pytest.mark.slow
def test_matrix_free_cg_matches_dense_schur(lz, joint):
    cg = fit(lz, ceemx.JointLM(linear_solver="cg", cg_rtol=1e-13, rtol=1e-13))
    assert cg.converged
    np.testing.assert_allclose(theta_of(cg.system), theta_of(joint.system), rtol=1e-6)
    np.testing.assert_allclose(cg.states, joint.states, atol=1e-6)


def test_joint_nonfinite_everywhere_is_an_error(lz):
    """Nothing can be fitted when J is not finite for any trajectory: a clear error at the start
    (the fit used to return ``converged=True`` with J = 0 for some methods)."""
    x0 = jnp.full_like(lz["x0"], 1e200)
    with pytest.raises(ValueError, match="no trajectory has a finite objective"):
        ceemx.fit(
            lz["guess"], lz["data"], x0, solver=ceemx.JointLM(), trainable=where_theta, max_epochs=5
        )
