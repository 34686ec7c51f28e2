"""Shared wiring of the experiments: x64, seeds, methods, seeded coupled-Lorenz problems.

The library parts they use live in :mod:`ceemx.identification.initialize` (start guesses),
:mod:`ceemx.evaluation.metrics`
(metrics and fit callbacks) and :mod:`ceemx.evaluation.report` (tables, files, figures).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ceemx import (
    AbstractFitSolver,
    AbstractLearner,
    Alternating,
    GaussianPrior,
    JointLM,
    LaplaceEM,
    LMLearner,
    LMSmoother,
    ParticleEM,
)
from ceemx.data.trajectories import Trajectories, simulate
from ceemx.experiments import METHODS, parse_seeds
from ceemx.identification.initialize import perturb
from ceemx.infra.policy import Runs, program
from ceemx.models.noise import DiagonalGaussian
from ceemx.systems.lorenz import (
    INITIAL_MEAN,
    INITIAL_STD,
    TRUE_PARAMS,
    CoupledLorenz,
    initial_states,
    random_coupling,
    random_observation_matrix,
)

__all__ = [
    "LORENZ_PARAMS",
    "LORENZ_PARAMS_H",
    "METHODS",
    "LorenzProblem",
    "enable_x64",
    "lorenz_initial_prior",
    "lorenz_problem",
    "make_solver",
    "parse_seeds",
    "perturb_lorenz",
    "seed_list",
    "true_lorenz",
]

TRUE_SIGMA, TRUE_RHO, TRUE_BETA = TRUE_PARAMS


def enable_x64() -> None:
    """Turn on float64 (experiments and the CLI do this at start; the library never does)."""
    jax.config.update("jax_enable_x64", True)


# --------------------------------------------------------------------------------------------
# Seeds and methods
# --------------------------------------------------------------------------------------------


def seed_list(seeds: int | str | Sequence[int] | None, *, first: int, default: int) -> list[int]:
    """The seeds of an experiment, whose seed sequence is ``first, first + 1, …``.

    Args:
        seeds: ``None`` → the first ``default`` seeds of the sequence; an ``int`` N → the first N;
            a ``str`` → parsed by :func:`parse_seeds`; a sequence → those seeds.
        first: the first seed of the experiment's sequence (table1: 0; figure3: 42).
        default: how many seeds by default.

    Returns:
        The seeds, in order.

    Raises:
        ValueError: no seeds (a count below 1 or an empty sequence).
    """
    if isinstance(seeds, str):
        seeds = parse_seeds(seeds)
    if seeds is None:
        seeds = default
    out = list(range(first, first + seeds)) if isinstance(seeds, int) else [int(s) for s in seeds]
    if not out:
        raise ValueError(f"an experiment needs at least one seed; got {seeds!r}.")
    return out


def make_solver(
    method: str,
    *,
    rho_x: float = 0.0,
    learner: AbstractLearner | None = None,
    rtol: float = 1e-10,
    initial: GaussianPrior | None = None,
    particle_options: dict | None = None,
) -> AbstractFitSolver:
    """The fit solver of an experiment's ``method``.

    Args:
        method: ``"alternate"`` → :class:`ceemx.Alternating` (paper Algorithm 1) with an
            :class:`ceemx.LMSmoother` of trust-region weight ``rho_x`` and ``learner`` (default
            :class:`ceemx.LMLearner`); ``"joint"`` → :class:`ceemx.JointLM` with proximal weight
            ``rho_x`` on the states (``learner`` unused); ``"particle"`` →
            :class:`ceemx.ParticleEM` (particle filter + FFBSi + SAEM) with ``learner`` as its
            M-step, the initial-state prior ``initial`` and ``particle_options``; ``"laplace"`` →
            :class:`ceemx.LaplaceEM` (Gaussian E-step, cubature M-step by ``learner``; its smoother
            has no trust region, ``rho_x`` unused).
        rho_x: ρ_x.
        learner: the θ-step optimiser of Algorithm 1 (or Particle EM's M-step).
        rtol: relative stopping tolerance on the improvement of J (not used by Particle EM,
            which runs its epochs).
        initial: Particle EM's distribution of x₁ (ignored by the other methods).
        particle_options: further :class:`ceemx.ParticleEM` options (likewise).

    Returns:
        The solver.

    Raises:
        ValueError: on an unknown method.
    """
    if method == "joint":
        return JointLM(rho_x=rho_x, rtol=rtol)
    if method == "alternate":
        learner = LMLearner() if learner is None else learner
        return Alternating(smoother=LMSmoother(rho_x=rho_x), learner=learner, rtol=rtol)
    if method == "laplace":
        learner = LMLearner() if learner is None else learner
        return LaplaceEM(learner=learner, rtol=rtol)
    if method == "particle":
        options = dict(particle_options or {})
        if learner is not None:
            options["learner"] = learner
        return ParticleEM(initial=initial, **options)
    raise ValueError(f"unknown method {method!r}; use one of {', '.join(METHODS)}.")


# --------------------------------------------------------------------------------------------
# Problems
# --------------------------------------------------------------------------------------------


def true_lorenz(
    K: int,
    *,
    key=None,
    m: int | None = None,
    coupling: bool = True,
    dt: float = 0.04,
    process_noise: float = 0.01,
    obs_noise: float = 0.01,
    integrator: str = "rk4",
) -> CoupledLorenz:
    """θ_true of paper §4.1, with C and H drawn from ``key`` (default ``PRNGKey(4)``).

    (σ, ρ, β) = (10, 28, 8/3) per attractor, C standard normal (full row rank, m = 3K − 2 by
    default), H standard normal off the own-attractor blocks with Frobenius norm 5
    (``coupling=False``: H = 0).
    """
    key = jax.random.PRNGKey(4) if key is None else key
    kc, kh = split_key(key, 2)
    C = random_observation_matrix(kc, K, m)
    H = random_coupling(kh, K) if coupling and K > 1 else np.zeros((3 * K, 3 * K))
    ones = np.ones((K,))  # NumPy: no eager program per K
    return CoupledLorenz(
        TRUE_SIGMA * ones,
        TRUE_RHO * ones,
        TRUE_BETA * ones,
        C,
        H=H,
        dt=dt,
        integrator=integrator,
        process_noise=process_noise,
        obs_noise=obs_noise,
    )


@program(runs=Runs.ONCE)
def split_key(key, n: int) -> tuple:
    """``jax.random.split(key, n)`` as a tuple, by one one-shot program (the same keys)."""
    return tuple(jax.random.split(key, n))


LORENZ_PARAMS = lambda s: (s.sigma, s.rho, s.beta)  # noqa: E731
LORENZ_PARAMS_H = lambda s: (s.sigma, s.rho, s.beta, s.H)  # noqa: E731


def perturb_lorenz(
    key, system: CoupledLorenz, *, coupling: bool = True, frac: float = 0.1
) -> CoupledLorenz:
    """Initial guess θ·(1 + U(−frac, frac)) of (σ, ρ, β) and, with ``coupling``, of H."""
    return perturb(key, system, frac, LORENZ_PARAMS_H if coupling else LORENZ_PARAMS)


def lorenz_initial_prior(K: int) -> GaussianPrior:
    """The data's x₁ distribution, N((−6, −6, 24), 2.5²) per attractor (Particle EM's prior)."""
    mean = jnp.tile(jnp.asarray(INITIAL_MEAN), K)
    return GaussianPrior(mean, DiagonalGaussian(INITIAL_STD, 3 * K))


class LorenzProblem(eqx.Module):
    """A simulated identification problem: the true system, its states, the data, a start guess."""

    true_system: CoupledLorenz
    states: jax.Array
    data: Trajectories
    x1: jax.Array
    init_system: CoupledLorenz


def lorenz_problem(
    seed: int,
    true_system: CoupledLorenz,
    *,
    B: int,
    T: int = 128,
    sigma_w: float = 0.0,
    sigma_v: float = 0.01,
    coupling: bool = True,
    x1_std: float = INITIAL_STD,
) -> LorenzProblem:
    """Seeded data and initial guess for a coupled-Lorenz system (paper §4.1).

    From ``PRNGKey(seed)``: x₁ ~ N((−6, −6, 24), 2.5²) per attractor, process noise N(0, σ_w²)
    (none when σ_w = 0), observation noise N(0, σ_v²), and the initial guess
    θ·(1 + U(−0.1, 0.1)) (of H too when ``coupling``).
    """
    k_x1, k_sim, k_theta = split_key(jax.random.PRNGKey(seed), 3)
    K = true_system.K
    x1 = initial_states(k_x1, B, K, std=x1_std)
    pn = DiagonalGaussian(sigma_w, 3 * K) if sigma_w > 0 else False
    on = DiagonalGaussian(sigma_v, true_system.obs_dim) if sigma_v > 0 else False
    xs, data = simulate(true_system, k_sim, x1, T, process_noise=pn, obs_noise=on)
    init = perturb_lorenz(k_theta, true_system, coupling=coupling)
    return LorenzProblem(true_system, xs, data, x1, init)
