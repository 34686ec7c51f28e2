"""The fit solvers × test problems table behind tests/test_solver_table.py.

A row is a fit solver (how to build it for a problem, and its known answer on the
linear-Gaussian problems); a column is a small identification problem. ``run`` fits a pair
once — an uninterrupted fit whose checkpoints are copied aside, then a fit resumed from one of
them (``resume_epoch``) — and tests/test_solver_table.py checks what each solver promises on each
problem: its monotone history entry (``AbstractFitSolver.monotone``), a known answer on the
linear-Gaussian problems, valid statuses, resume = uninterrupted run, and no retrace across
epochs. A new solver is tested by adding one row to ``ROWS``.

Known answers (linear-Gaussian model, NumPy float64, dense): the MAP states of every trajectory
at θ (one linear solve of the block-tridiagonal normal equations, the Kalman/RTS smoother's
means), the least-squares (A, C) on given states, and the exact log-likelihood log p(y | θ) of
the observed components (the joint Gaussian of all observations).
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import json
import os
import pathlib
import shutil
import warnings
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import stiff_model

import ceemx
from ceemx.systems import CoupledLorenz, LinearSystem

#: Epochs of a fit that is not run to its optimum.
EPOCHS = 5
#: The resumed fit starts from the checkpoint of epoch ``resume_epoch``: at least RESUME_AT
#: (a resume runs what the first epochs compiled), at most RESUMED epochs before the end.
RESUME_AT = 2
RESUMED = 3
#: The bound on epochs of a fit run to its optimum (a certainty-equivalent method on a
#: linear-Gaussian problem, whose optimum is known).
MAX_EPOCHS = 200


# --------------------------------------------------------------------------------------------------
# Problems
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LinearGaussian:
    """The NumPy matrices of a linear-Gaussian model x' = A x + w, y = C x + v, x₁ ~ N(mu0, P0)."""

    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    mu0: np.ndarray
    P0: np.ndarray

    @classmethod
    def of(cls, system) -> LinearGaussian:
        """The matrices of a ``LinearSystem`` with Gaussian noise and prior."""
        cov = lambda noise: np.asarray(noise.covariance())  # noqa: E731
        prior = system.initial_prior
        return cls(
            np.asarray(system.A),
            np.asarray(system.C),
            cov(system.process_noise),
            cov(system.obs_noise),
            np.asarray(prior.mean),
            cov(prior.noise),
        )

    def system(self) -> LinearSystem:
        chol = lambda S: ceemx.CholeskyGaussian(cov=jnp.asarray(S))  # noqa: E731
        return LinearSystem(
            jnp.asarray(self.A),
            jnp.asarray(self.C),
            process_noise=chol(self.Q),
            obs_noise=chol(self.R),
            initial_prior=ceemx.GaussianPrior(jnp.asarray(self.mu0), chol(self.P0)),
        )


@dataclasses.dataclass(frozen=True)
class Problem:
    """One column of the table.

    Attributes:
        name: the test id.
        start: the model at the initial θ.
        data: the observations.
        x_init: (B, T, n) start states.
        trainable: θ of every solver.
        noise_trainable: θ of a solver that ``learns_noise`` (``None``: ``trainable``).
        initial: the x₁ distribution, for a solver that needs one where the model has none.
        failing: trajectories whose observations (1e200) no solver can fit: each must be left out
            with a warning and a status, the others fitted as if it were absent.
    """

    name: str
    start: ceemx.AbstractSystem
    data: ceemx.Trajectories
    x_init: jax.Array
    trainable: Callable
    noise_trainable: Callable | None = None
    initial: ceemx.GaussianPrior | None = None
    failing: tuple[int, ...] = ()

    @property
    def linear_gaussian(self) -> bool:
        """Whether the model is linear-Gaussian (``LinearGaussian.of(start)``): known answers."""
        return self.name in LINEAR_GAUSSIAN

    @property
    def fitted(self) -> np.ndarray:
        """The indices of the trajectories that are not ``failing``."""
        return np.setdiff1d(np.arange(self.data.batch_size), self.failing)


_LG = LinearGaussian(
    A=np.array([[0.9, 0.2], [-0.15, 0.8]]),
    C=np.array([[1.0, 0.3], [0.2, 1.0]]),
    Q=np.array([[0.05, 0.01], [0.01, 0.04]]),
    R=np.array([[0.1, 0.02], [0.02, 0.2]]),
    mu0=np.zeros(2),
    P0=np.eye(2),
)
_LG_START = dataclasses.replace(
    _LG,
    A=np.array([[0.7, 0.0], [0.0, 0.6]]),
    C=np.array([[0.8, 0.0], [0.1, 1.2]]),
    Q=0.2 * np.eye(2),
    R=0.5 * np.eye(2),
)


def _lg_start() -> LinearSystem:
    """The start model, its A weakly typed as a user may build it (from Python floats): θ comes
    back from the first epoch strongly typed, which must not compile the epoch programs again."""
    weak = jnp.stack([jnp.stack([jnp.asarray(v) for v in row]) for row in _LG_START.A.tolist()])
    assert jax.typeof(weak).weak_type
    return eqx.tree_at(lambda s: s.A, _LG_START.system(), weak)


def _lg_observations(seed: int, B: int, T: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y = np.zeros((B, T, 2))
    for b in range(B):
        x = rng.multivariate_normal(_LG.mu0, _LG.P0)
        for t in range(T):
            y[b, t] = _LG.C @ x + rng.multivariate_normal(np.zeros(2), _LG.R)
            x = _LG.A @ x + rng.multivariate_normal(np.zeros(2), _LG.Q)
    return y


def _lg_theta(s):
    return s.A


def _lg_noise_theta(s):
    return (s.A, s.C, s.process_noise, s.obs_noise)


@functools.cache
def linear_gaussian() -> Problem:
    """n = 2, m = 2, full noise covariances and x₁ prior, T = 40 (drawn in NumPy): three
    trajectories and a fourth no solver can fit."""
    y = np.concatenate([_lg_observations(0, 3, 40), np.full((1, 40, 2), 1e200)])
    return Problem(
        "linear-gaussian",
        _lg_start(),
        ceemx.Trajectories(jnp.asarray(y)),
        jnp.zeros(y.shape[:2] + (2,)),
        _lg_theta,
        _lg_noise_theta,
        failing=(3,),
    )


@functools.cache
def missing_data() -> Problem:
    """The linear-Gaussian model with a third of the components and every fifth step missing."""
    y = _lg_observations(1, 4, 40)  # the shapes of linear_gaussian: the same programs
    rng = np.random.default_rng(2)
    mask = rng.uniform(size=y.shape) > 1 / 3
    mask[:, 2::5] = False
    y = np.where(mask, y, np.nan)
    return Problem(
        "missing-data",
        _lg_start(),
        ceemx.Trajectories(jnp.asarray(y), mask=jnp.asarray(mask)),
        jnp.zeros(y.shape[:2] + (2,)),
        _lg_theta,
        _lg_noise_theta,
    )


def _lorenz_theta(s):
    return (s.sigma, s.rho, s.beta)


@functools.cache
def lorenz() -> Problem:
    """One Lorenz attractor observed through C ∈ R^{2×3}, B = 2, T = 32, θ = (σ, ρ, β)."""
    prior = ceemx.GaussianPrior(jnp.asarray([-6.0, -6.0, 24.0]), ceemx.DiagonalGaussian(2.5, 3))
    C = jnp.asarray([[1.0, 0.5, 0.0], [0.0, 0.3, 1.0]])
    noise = dict(process_noise=0.1, obs_noise=0.3, initial_prior=prior)
    true = CoupledLorenz(10.0, 28.0, 8 / 3, C, **noise)
    rng = np.random.default_rng(7)
    x1 = jnp.asarray([-6.0, -6.0, 24.0] + 2.5 * rng.standard_normal((2, 3)))
    states, data = eqx.filter_jit(ceemx.simulate)(true, jax.random.PRNGKey(7), x1, 32)
    x_init = states + jnp.asarray(0.1 * rng.standard_normal(states.shape))
    start = CoupledLorenz(10.6, 27.0, 2.5, C, **noise)
    # σ weakly typed, as a user may build it: θ comes back from the first epoch strongly typed,
    # which must not compile the epoch programs again.
    start = eqx.tree_at(lambda s: s.sigma, start, jnp.atleast_1d(jnp.asarray(10.6)))
    assert jax.typeof(start.sigma).weak_type
    return Problem("lorenz", start, data, x_init, _lorenz_theta)


def _stiff_theta(s):
    return (s.k, s.c, s.g, s.tau)


@functools.cache
def stiff() -> Problem:
    """tests/stiff_model.py (a fast hidden actuator: RK4 with substeps), B = 2, T = 60."""
    rng = np.random.default_rng(11)
    true = stiff_model.make()
    u = jnp.asarray(np.repeat(rng.standard_normal((2, 6, 1)), 10, axis=1))  # smoothed steps
    key = jax.random.PRNGKey(11)
    states, data = eqx.filter_jit(ceemx.simulate)(true, key, jnp.zeros((2, 3)), 60, u)
    x_init = states + jnp.asarray(stiff_model.PROCESS_STD * rng.standard_normal(states.shape))
    start = stiff_model.make(dict(k=90.0, c=2.4, g=45.0, tau=0.06))
    prior = ceemx.GaussianPrior(
        jnp.zeros(3), ceemx.DiagonalGaussian(jnp.asarray([1e-3, 1e-2, 0.1]), 3)
    )
    return Problem("stiff", start, data, x_init, _stiff_theta, initial=prior)


#: The problems with a linear-Gaussian model, whose answers are known.
LINEAR_GAUSSIAN = ("linear-gaussian", "missing-data")
PROBLEMS: dict[str, Callable[[], Problem]] = {
    "linear-gaussian": linear_gaussian,
    "missing-data": missing_data,
    "lorenz": lorenz,
    "stiff": stiff,
}


# --------------------------------------------------------------------------------------------------
# Rows: the fit solvers
# --------------------------------------------------------------------------------------------------


#: The known answers a row can be checked against on the linear-Gaussian problems.
ANSWERS = {
    "optimum": "a certainty-equivalent method, run to convergence: its end point is J's "
    "stationary point (the MAP states at θ, the least-squares θ on those states)",
    "evidence": "the history's log_evidence after each epoch is log p(y | θ) at that θ",
    "likelihood estimate": "the history's pf_log_likelihood of each epoch is log p(y | θ) at the "
    "epoch's starting θ, to Monte Carlo accuracy",
}


@dataclasses.dataclass(frozen=True)
class Row:
    """One fit solver of the table.

    Attributes:
        name: the test id.
        solver: the solver's class.
        answer: its known answer on the linear-Gaussian problems (a key of ``ANSWERS``).
        options: its options for a problem.
        problems: the problems it applies to.
        slow: the problems on which it runs in the slow tier only (see ``ROWS``).
    """

    name: str
    solver: type[ceemx.AbstractFitSolver]
    answer: str
    options: Callable[[Problem], dict] = lambda p: {}
    problems: tuple[str, ...] = tuple(PROBLEMS)
    slow: tuple[str, ...] = ("lorenz", "stiff")

    def __post_init__(self):
        assert self.answer in ANSWERS, self.answer

    def make(self, problem: Problem) -> ceemx.AbstractFitSolver:
        return self.solver(**self.options(problem))


#: Compilation is most of a pair's cost (a solver compiles its programs once per problem
#: structure; the two linear-Gaussian problems share theirs). Within the default suite's time
#: budget run the linear-Gaussian pairs, with their known answers, of Alternating and Laplace EM
#: (plain and SQUAREM), and particle EM's missing-data pair (its Monte Carlo known answer; the
#: trajectory no solver can fit is checked on the others' complete pair); JointLM (in the default
#: suite through test_joint.py) and the rest of the table run with the slow tests.
ROWS = (
    Row("Alternating", ceemx.Alternating, "optimum"),
    Row("JointLM", ceemx.JointLM, "optimum", slow=tuple(PROBLEMS)),
    Row(
        "JointMatrixFree",
        ceemx.JointLM,
        "optimum",
        lambda p: dict(border="matrix-free", cg_rtol=1e-14),
        slow=tuple(PROBLEMS),
    ),
    Row("LaplaceEM", ceemx.LaplaceEM, "evidence", lambda p: dict(acceleration=None)),
    Row("LaplaceEM-SQUAREM", ceemx.LaplaceEM, "evidence"),
    Row(
        "LaplaceEM-QN",
        ceemx.LaplaceEM,
        "evidence",
        lambda p: dict(acceleration="quasi_newton"),
        slow=tuple(PROBLEMS),
    ),
    Row(
        "ParticleEM",
        ceemx.ParticleEM,
        "likelihood estimate",
        lambda p: dict(n_particles=64, n_smoothed=4, burn_in=2, initial=p.initial),
        slow=("linear-gaussian", "lorenz", "stiff"),
    ),
)


# --------------------------------------------------------------------------------------------------
# Dense NumPy oracles of the linear-Gaussian model
# --------------------------------------------------------------------------------------------------


def _information(lg: LinearGaussian, T: int):
    """Precision and information vector of the states' prior p(x₁, ..., x_T) (dense, T·n)."""
    n = lg.A.shape[0]
    H = np.zeros((T * n, T * n))
    g = np.zeros(T * n)
    P0i = np.linalg.inv(lg.P0)
    H[:n, :n] += P0i
    g[:n] += P0i @ lg.mu0
    D = np.hstack([-lg.A, np.eye(n)])
    W = D.T @ np.linalg.solve(lg.Q, D)
    for t in range(T - 1):
        H[t * n : (t + 2) * n, t * n : (t + 2) * n] += W
    return H, g


def map_states(lg: LinearGaussian, y: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(T, n) argmax_x log p(x, y_observed | θ) of one trajectory: the RTS smoother's means."""
    T, n = y.shape[0], lg.A.shape[0]
    H, g = _information(lg, T)
    for t in range(T):
        o = mask[t]
        if o.any():
            Co = lg.C[o]
            Ri = np.linalg.inv(lg.R[np.ix_(o, o)])
            H[t * n : (t + 1) * n, t * n : (t + 1) * n] += Co.T @ Ri @ Co
            g[t * n : (t + 1) * n] += Co.T @ Ri @ y[t, o]
    return np.linalg.solve(H, g).reshape(T, n)


def log_likelihood(lg: LinearGaussian, y: np.ndarray, mask: np.ndarray) -> float:
    """log p(y_observed | θ) of one trajectory, from the joint Gaussian of its observations."""
    T = y.shape[0]
    H, g = _information(lg, T)
    cov_x = np.linalg.inv(H)
    mean_x = cov_x @ g
    obs = mask.reshape(-1)
    C_big = np.kron(np.eye(T), lg.C)[obs]
    R_big = np.kron(np.eye(T), lg.R)[np.ix_(obs, obs)]
    S = C_big @ cov_x @ C_big.T + R_big
    r = y.reshape(-1)[obs] - C_big @ mean_x
    _, logdet = np.linalg.slogdet(S)
    return float(-0.5 * (r @ np.linalg.solve(S, r) + logdet + r.size * np.log(2 * np.pi)))


def least_squares_AC(lg: LinearGaussian, x: np.ndarray, y: np.ndarray, mask: np.ndarray):
    """argmax_{A, C} log p(x, y_observed | θ) over B trajectories (x: (B, T, n)).

    A by ordinary least squares (every state equation has the same regressors, so the process
    noise's covariance does not enter); C by generalised least squares on the observed
    components, weighted by the inverse of their noise covariance.
    """
    n, m = lg.A.shape[0], lg.C.shape[0]
    X0 = x[:, :-1].reshape(-1, n)
    X1 = x[:, 1:].reshape(-1, n)
    A = np.linalg.solve(X0.T @ X0, X0.T @ X1).T
    N = np.zeros((m * n, m * n))
    v = np.zeros(m * n)
    for xb, yb, mb in zip(x, y, mask, strict=True):
        for xt, yt, o in zip(xb, yb, mb, strict=True):
            if o.any():
                M = np.kron(xt[None, :], np.eye(m))[o]  # C_o x = M vec(C) (column-major vec)
                W = np.linalg.inv(lg.R[np.ix_(o, o)])
                N += M.T @ W @ M
                v += M.T @ W @ yt[o]
    C = np.linalg.solve(N, v).reshape(n, m).T
    return A, C


# --------------------------------------------------------------------------------------------------
# One run of a pair
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Run:
    """What a pair's fits left: the uninterrupted result, the resumed one, per-epoch θ and
    traces.

    Attributes:
        result: the uninterrupted fit.
        resumed: the fit resumed from the uninterrupted fit's checkpoint of epoch
            ``resumed_at``.
        resumed_at: ``resume_epoch(result.epochs)``.
        systems: the model after each epoch of the uninterrupted fit (its callbacks).
        traces: the names of the functions JAX traced (its monitoring events) in the
            uninterrupted fit, between one epoch's callbacks and the next: ``traces[0]`` the
            start and epoch 1, ``traces[k]`` epoch k + 1, the last one the fit's end.
        resumed_traces: the same for the resumed fit's epochs.
        resumed_from: the files of the checkpoint resumed, and its ``latest.json``.
        left: the files of each checkpoint folder after its fit (the uninterrupted, the resumed).
        warnings: the messages of the warnings the two fits gave.
    """

    result: ceemx.FitResult
    resumed: ceemx.FitResult
    resumed_at: int
    systems: list
    traces: list[list[str]]
    resumed_traces: list[list[str]]
    resumed_from: tuple[list[str], dict]
    left: tuple[list[str], list[str]]
    warnings: list[str]


@functools.cache
def ceemx_functions() -> frozenset[str]:
    """The names of the functions ceemx defines: its compiled entry points among them.

    JAX also traces its own small programs for eager operations, once per new signature; one
    first met in a later epoch is no retrace of an epoch program.
    """
    names = set()
    for path in pathlib.Path(ceemx.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                names.add(node.name)
    return frozenset(names)


class _TraceLog:
    """The names of the functions JAX traces, by epoch (callbacks start the next one)."""

    def __init__(self):
        self.epochs: list[list[str]] = [[]]

    def __call__(self, event, duration, **kwargs):
        del duration
        if event == "/jax/core/compile/jaxpr_trace_duration":
            self.epochs[-1].append(str(kwargs.get("fun_name")))

    def next_epoch(self, info):
        del info
        self.epochs.append([])

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self)


def resume_epoch(epochs: int) -> int:
    """The epoch whose checkpoint a pair's fit of ``epochs`` epochs is resumed from."""
    return max(RESUME_AT, epochs - RESUMED)


def run(row: Row, problem: Problem, folder: pathlib.Path) -> Run:
    """``row``'s solver on ``problem``: uninterrupted (with a checkpoint), then resumed."""
    solver = row.make(problem)
    trainable = problem.trainable
    if solver.learns_noise and problem.noise_trainable is not None:
        trainable = problem.noise_trainable
    max_epochs = MAX_EPOCHS if row.answer == "optimum" and problem.linear_gaussian else EPOCHS
    full = folder / "full"
    systems = []

    def keep(info):
        systems.append(info.system)
        if info.epoch > RESUME_AT:  # the checkpoint of the epoch before is on disk, not this one's
            copy = folder / f"epoch-{info.epoch - 1}"
            shutil.copytree(full, copy, ignore=shutil.ignore_patterns(".lock"))
            for old in range(RESUME_AT, resume_epoch(info.epoch)):  # can no longer be resumed
                shutil.rmtree(folder / f"epoch-{old}", ignore_errors=True)

    kwargs = dict(
        solver=solver,
        trainable=trainable,
        max_epochs=max_epochs,
        outliers="keep",
        diagnose=False,
        progress=False,
        key=jax.random.PRNGKey(0),
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with _TraceLog() as log:
            result = ceemx.fit(
                problem.start, problem.data, problem.x_init, checkpoint=str(full),
                callbacks=[keep, log.next_epoch], **kwargs,
            )  # fmt: skip
        assert result.epochs > RESUME_AT, f"{row.name} on {problem.name} stopped too early"
        at = resume_epoch(result.epochs)
        resume = folder / f"epoch-{at}"
        copied = (sorted(os.listdir(resume)), json.loads((resume / "latest.json").read_text()))
        with _TraceLog() as resumed_log:
            resumed = ceemx.fit(
                problem.start, problem.data, problem.x_init, checkpoint=str(resume),
                callbacks=[resumed_log.next_epoch], **kwargs,
            )  # fmt: skip
    return Run(
        result, resumed, at, systems, log.epochs, resumed_log.epochs, copied,
        (sorted(os.listdir(full)), sorted(os.listdir(resume))), [str(w.message) for w in caught],
    )  # fmt: skip
