"""Particle filtering (bootstrap and fully adapted) and FFBSi backward simulation for any system.

The filter approximates p(x_t | y_{1:t}, θ) by N weighted particles per trajectory and gives an
unbiased estimate p̂(y_{1:T} | θ) of the likelihood; FFBSi draws state trajectories from the
particle approximation of the joint smoothing distribution p(x_{1:T} | y_{1:T}, θ). Both run as a
``lax.scan`` over time, ``vmap``ped over trajectories, compiled once per shape.

Proposals:

- **bootstrap**: x_t ~ p(x_t | x_{t−1}) = f(x_{t−1}) + w, weights p(y_t | x_t). Any system whose
  process noise can be sampled (:meth:`ceemx.AbstractNoise.sample`) and any observation density.
- **fully adapted**: x_t ~ p(x_t | x_{t−1}, y_t), first-stage weights p(y_t | x_{t−1}), in closed
  form when the process and observation noises are Gaussian and the observation is linear in the
  state, y = C x + d(u, t) + v (the system says so through
  :meth:`ceemx.AbstractSystem.linear_observation`). Because C does not depend on the particle,
  one Kalman update per time step serves all N particles.

Resampling is systematic and adaptive: at step t the weights that select ancestors (the previous
weights times the first-stage weights) are resampled only when their effective sample size falls
below ``ess_threshold · N``. Missing observations (the data's mask) drop out of the weights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from ceemx.data.checks import prepare, promote_tree
from ceemx.data.trajectories import Trajectories
from ceemx.infra import options
from ceemx.infra.compilation import jit
from ceemx.lib import kalman
from ceemx.lib import particles as lp
from ceemx.lib.results import RESULTS, select
from ceemx.lib.typing import PerTrajectory, no_type_check
from ceemx.models.noise import AbstractGaussianNoise
from ceemx.models.system import AbstractSystem, GaussianPrior

__all__ = [
    "PROPOSALS",
    "ParticleFilterSolution",
    "check_int",
    "check_proposal",
    "check_threshold",
    "ffbsi",
    "ffbsi_batch",
    "filter_batch",
    "initial_prior",
    "particle_filter",
    "resolve_proposal",
]

Proposal = Literal["auto", "adapted", "bootstrap"]


class ParticleFilterSolution(eqx.Module):
    """The output of :func:`particle_filter` for B trajectories of T steps with N particles.

    Attributes:
        particles: (B, T, N, n) particles x_t^i.
        log_weights: (B, T, N) normalised log-weights of the filtering distribution at each t.
        ancestors: (B, T, N) index at t−1 of the parent of particle i at t (t = 0: i itself).
        ess: (B, T) effective sample size of the weights that chose the ancestors at t (t = 0:
            of the initial weights).
        resampled: (B, T) whether step t resampled (ESS below the threshold).
        log_likelihood: (B,) log p̂(y_{1:T} | θ), whose exponential is an unbiased estimate.
        status: (B,) :class:`ceemx.RESULTS`: ``particle_failure`` where the likelihood estimate
            is not finite (every particle impossible, or NaN in the model), else ``successful``.
        proposal: ``"adapted"`` or ``"bootstrap"`` — the proposal used.
    """

    particles: Float[Array, "B T N n"]
    log_weights: Float[Array, "B T N"]
    ancestors: Int[Array, "B T N"]
    ess: Float[Array, "B T"]
    resampled: Bool[Array, "B T"]
    log_likelihood: PerTrajectory
    status: RESULTS
    proposal: str = eqx.field(static=True)

    def mean(self) -> Float[Array, "B T n"]:
        """The filtering means E[x_t | y_{1:t}] under the particle approximation."""
        w = jnp.exp(self.log_weights)[..., None]
        return jnp.sum(w * self.particles, axis=-2)


PROPOSALS = ("auto", "adapted", "bootstrap")


def check_proposal(proposal) -> None:
    """Raise ``ValueError`` unless ``proposal`` is one of :data:`PROPOSALS` (host-side)."""
    if proposal not in PROPOSALS:
        raise ValueError(f"`proposal` must be 'auto', 'adapted' or 'bootstrap'; got {proposal!r}.")


def resolve_proposal(system: AbstractSystem, proposal: str, prior: GaussianPrior) -> str:
    """``"adapted"`` or ``"bootstrap"`` for ``proposal`` (host-side; raises if impossible)."""
    check_proposal(proposal)
    dtype = prior.mean.dtype
    linear = system.linear_observation(
        jnp.zeros((system.input_dim,), dtype), jnp.zeros((), jnp.int32)
    )
    reasons = []
    if linear is None:
        reasons.append("the observation is not declared linear in x (linear_observation)")
    if not isinstance(system.process_noise, AbstractGaussianNoise):
        reasons.append("the process noise is not Gaussian")
    if not isinstance(system.obs_noise, AbstractGaussianNoise):
        reasons.append("the observation noise is not Gaussian")
    if not isinstance(prior.noise, AbstractGaussianNoise):
        reasons.append("the initial-state prior is not Gaussian")
    if proposal == "adapted" and reasons:
        raise ValueError("proposal='adapted' needs closed forms, but " + "; ".join(reasons) + ".")
    if proposal == "auto":
        return "bootstrap" if reasons else "adapted"
    return proposal


def initial_prior(system: AbstractSystem, initial: GaussianPrior | None) -> GaussianPrior:
    """The distribution of x₁ a particle method uses: ``initial``, else the system's own prior.

    Raises (host-side, naming the argument) when there is none, when it is not a
    :class:`ceemx.GaussianPrior`, or when its mean is not a finite vector of length n.
    """
    prior = system.initial_prior if initial is None else initial
    if prior is None:
        raise ValueError(
            "particle filtering needs a proper initial-state distribution: give `initial` "
            "(a ceemx.GaussianPrior) or set the system's `initial_prior`."
        )
    if not isinstance(prior, GaussianPrior):
        raise TypeError(f"`initial` must be a ceemx.GaussianPrior; got {type(prior).__name__}.")
    mean = np.asarray(prior.mean)
    if mean.shape != (system.state_dim,) or not np.all(np.isfinite(mean)):
        raise ValueError(
            f"the initial-state prior's mean must be a finite vector of length n = "
            f"{system.state_dim}; got shape {mean.shape}."
        )
    prior.noise.check("initial.noise")
    return prior


@dataclass(frozen=True)
class _Bootstrap:
    """The bootstrap proposal: x_t ~ p(x_t | x_{t−1}), incremental weights p(y_t | x_t)."""

    system: AbstractSystem
    dtype: Any
    N: int

    def obs_loglik(self, x, ut, yt, mt, t):
        """The log-density p(y_t | x_t) (missing entries drop out)."""
        return self.system.obs_noise.log_prob(yt - self.system.observe(x, ut, t), mt)

    def initial(self, prior: GaussianPrior, k, y, u, mask, ts):
        """(x₁ particles from p(x₁), their log-weights, log p̂(y₁))."""
        N, dtype = self.N, self.dtype
        m0 = prior.mean.astype(dtype)
        x0 = m0[None, :] + prior.noise.sample(k, (N,), dtype)
        inc = jax.vmap(lambda x: self.obs_loglik(x, u[0], y[0], mask[0], ts[0]))(x0)
        logw0, lse = lp.log_normalize(inc)
        return x0, logw0, lse - math.log(N)

    def first_stage(self, fx, yt, ut, mt, t):
        """No first-stage weights (0 per particle), no shared update."""
        return jnp.zeros((self.N,), self.dtype), None

    def propose(self, k, fa, yt, ut, mt, t, stage):
        """(x_t particles, their incremental log-weights)."""
        x_t = fa + self.system.process_noise.sample(k, (self.N,), self.dtype)
        return x_t, jax.vmap(lambda x: self.obs_loglik(x, ut, yt, mt, t))(x_t)


@dataclass(frozen=True)
class _Adapted:
    """The fully adapted proposal: x_t ~ p(x_t | x_{t−1}, y_t), first-stage p(y_t | x_{t−1}).

    Closed form for Gaussian noises and an observation linear in the state (module notes).
    """

    system: AbstractSystem
    dtype: Any
    N: int

    def update(self, P, ut, t, mt) -> tuple[kalman.GaussianUpdate, Float[Array, " m"]]:
        """The Kalman update from prior covariance P (shared by all particles) and offset d."""
        linear = self.system.linear_observation(ut, t)
        assert linear is not None  # resolve_proposal checked it
        C, d = linear
        L_R = self.system.obs_noise.cholesky().astype(self.dtype)  # type: ignore[attr-defined]
        return kalman.gaussian_update(P, C.astype(self.dtype), L_R, mt), d.astype(self.dtype)

    def initial(self, prior: GaussianPrior, k, y, u, mask, ts):
        """(x₁ particles from p(x₁ | y₁), their log-weights, log p̂(y₁))."""
        N, dtype = self.N, self.dtype
        m0 = prior.mean.astype(dtype)
        P0 = prior.noise.covariance().astype(dtype)  # type: ignore[attr-defined]
        up, d = self.update(P0, u[0], ts[0], mask[0])
        z = jax.random.normal(k, (N, m0.shape[0]), dtype)
        x0 = up.mean(m0, y[0] - d)[None, :] + z @ up.chol_post.T
        ll0 = kalman.predictive_log_density(up, m0, y[0] - d)
        return x0, jnp.full((N,), -math.log(N), dtype), ll0

    def first_stage(self, fx, yt, ut, mt, t):
        """Log p(y_t | x_{t−1}) per particle, and the shared update."""
        Q = self.system.process_noise.covariance().astype(self.dtype)  # type: ignore[attr-defined]
        up, d = self.update(Q, ut, t, mt)
        log_pred = jax.vmap(lambda f: kalman.predictive_log_density(up, f, yt - d))(fx)
        return log_pred, (up, d)

    def propose(self, k, fa, yt, ut, mt, t, stage):
        """(x_t particles, their incremental log-weights: 0)."""
        up, d = stage
        mean = jax.vmap(lambda f: up.mean(f, yt - d))(fa)
        z = jax.random.normal(k, fa.shape, self.dtype)
        return mean + z @ up.chol_post.T, jnp.zeros((self.N,), self.dtype)


def _filter_one(
    system: AbstractSystem,
    prior: GaussianPrior,
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
    key: PRNGKeyArray,
    threshold: Float[Array, ""],
    n_particles: int,
    adapted: bool,
):
    """The filter on one trajectory (see :func:`particle_filter`)."""
    N = n_particles
    T = y.shape[0]
    log_n = math.log(N)
    ts = jnp.arange(T)
    keys = jax.random.split(key, T)
    proposal = (_Adapted if adapted else _Bootstrap)(system, y.dtype, N)
    x0, logw0, ll0 = proposal.initial(prior, keys[0], y, u, mask, ts)

    def step(carry, inp):
        x_prev, logw_prev = carry
        yt, ut, u_prev, mt, t, kt = inp
        k_res, k_prop = jax.random.split(kt)
        fx = jax.vmap(lambda x: system.dynamics(x, u_prev, t - 1))(x_prev)
        log_pred, stage = proposal.first_stage(fx, yt, ut, mt, t)
        logv, lse1 = lp.log_normalize(logw_prev + log_pred)
        ess_t = lp.ess(logv)
        resample = ess_t < threshold * N
        anc = jnp.where(
            resample, lp.systematic_resample(k_res, logv), jnp.arange(N, dtype=jnp.int32)
        )
        base = jnp.where(resample, -log_n, logv)
        x_t, log_inc = proposal.propose(k_prop, fx[anc], yt, ut, mt, t, stage)
        logw, lse2 = lp.log_normalize(base + log_inc)
        out = (x_t, logw, anc, ess_t, resample, lse1 + lse2)
        return (x_t, logw), out

    xs = (y[1:], u[1:], u[:-1], mask[1:], ts[1:], keys[1:])
    _, (xp, lw, anc, ess_s, res, ll) = jax.lax.scan(step, (x0, logw0), xs)
    particles = jnp.concatenate([x0[None], xp], axis=0)
    log_weights = jnp.concatenate([logw0[None], lw], axis=0)
    ancestors = jnp.concatenate([jnp.arange(N, dtype=jnp.int32)[None], anc], axis=0)
    ess_all = jnp.concatenate([lp.ess(logw0)[None], ess_s], axis=0)
    resampled = jnp.concatenate([jnp.zeros((1,), bool), res], axis=0)
    log_lik = ll0 + jnp.sum(ll)
    return particles, log_weights, ancestors, ess_all, resampled, log_lik


@jit
def filter_batch(
    system: AbstractSystem,
    data: Trajectories,
    prior: GaussianPrior,
    key: PRNGKeyArray,
    threshold: Float[Array, ""],
    n_particles: int,
    proposal: str,
) -> ParticleFilterSolution:
    """The compiled kernel of :func:`particle_filter` (no validation; ``proposal`` resolved)."""
    adapted = proposal == "adapted"
    keys = jax.random.split(key, data.batch_size)
    out = jax.vmap(
        lambda y, u, m, k: _filter_one(system, prior, y, u, m, k, threshold, n_particles, adapted)
    )(data.y, data.u, data.mask, keys)
    particles, log_weights, ancestors, ess_all, resampled, log_lik = out
    ok = jnp.isfinite(log_lik) & jnp.all(jnp.isfinite(particles), axis=(1, 2, 3))
    status = select(ok, RESULTS.successful, RESULTS.particle_failure)
    return ParticleFilterSolution(
        particles, log_weights, ancestors, ess_all, resampled, log_lik, status, proposal
    )


def check_int(name: str, value, minimum: int) -> int:
    """``value`` as an int >= ``minimum`` (:func:`ceemx.infra.options.check_int`)."""
    return cast(int, options.check_int(name, value, minimum))


def check_threshold(ess_threshold) -> float:
    """``ess_threshold`` as a float in [0, 1] (raises naming it)."""
    a = options.check_real("ess_threshold", ess_threshold)
    if a is None:  # traced: checked when the options were made
        return ess_threshold
    if a.shape != () or not 0.0 <= float(a) <= 1.0:
        raise ValueError(f"`ess_threshold` must be a number in [0, 1]; got {ess_threshold!r}.")
    return float(a)


@no_type_check  # validates its arguments: prepare and the checks below
def particle_filter(
    system: AbstractSystem,
    data: Trajectories,
    *,
    n_particles: int = 100,
    key: PRNGKeyArray | None = None,
    proposal: Proposal = "auto",
    ess_threshold: float = 0.5,
    initial: GaussianPrior | None = None,
) -> ParticleFilterSolution:
    """Particle filter on every trajectory of ``data`` at the system's θ.

    Args:
        system: the model. Its process noise must be samplable (bootstrap) or Gaussian (adapted).
        data: B trajectories (inputs and masks as everywhere in ceemx; a missing observation skips
            the weight update).
        n_particles: N, particles per trajectory.
        key: PRNG key (default ``PRNGKey(0)``); the result is a deterministic function of it.
        proposal: ``"auto"`` (fully adapted when the system declares a linear observation and
            every noise is Gaussian, else bootstrap), ``"adapted"`` or ``"bootstrap"``.
        ess_threshold: resample when ESS < ``ess_threshold · N`` (0: never, 1: every step).
        initial: the distribution of x₁ (default: the system's ``initial_prior``; one of the two
            is required).

    Data and ``initial`` are cast to the dtype of the system's parameters, as by :func:`ceemx.fit`
    and :func:`ceemx.smooth` (:func:`ceemx.data.checks.promote_inputs`).

    Returns:
        A :class:`ParticleFilterSolution` (arrays in the system's dtype); ``log_likelihood`` is
        log p̂(y_{1:T} | θ) per trajectory,
        ``status`` flags trajectories whose estimate is not finite. Compiled once per shape,
        N and proposal; ``ess_threshold`` is traced.

    Raises:
        ValueError, TypeError: on invalid inputs, before any compute.

    Example:
        >>> pf = ceemx.particle_filter(system, data, n_particles=200, key=key)  # doctest: +SKIP
        >>> pf.log_likelihood  # doctest: +SKIP
    """
    if not isinstance(system, AbstractSystem):
        raise TypeError(f"`system` must be a ceemx.AbstractSystem; got {type(system).__name__}.")
    inputs = prepare(system, data)  # one dtype: the system's, as fit and smooth
    system, data = inputs.system, inputs.data
    if initial is not None:
        initial = promote_tree(initial, system)
    n_particles = check_int("n_particles", n_particles, 1)
    threshold = check_threshold(ess_threshold)
    prior = initial_prior(system, initial)
    resolved = resolve_proposal(system, proposal, prior)
    key = jax.random.PRNGKey(0) if key is None else key
    dtype = data.y.dtype
    return filter_batch(
        system, data, prior, key, jnp.asarray(threshold, dtype), n_particles, resolved
    )


def _ffbsi_one(system, particles, log_weights, u, key, n_samples: int):
    """FFBSi on one trajectory: (S, T, n) draws from the particle smoothing distribution."""
    T, N, n = particles.shape
    keys = jax.random.split(key, T)
    ts = jnp.arange(T)
    last = jax.random.categorical(keys[-1], log_weights[-1], shape=(n_samples,))
    x_last = particles[-1, last]

    def back(x_next, inp):
        xt, lwt, ut, t, kt = inp
        fx = jax.vmap(lambda x: system.dynamics(x, ut, t))(xt)  # (N, n)
        log_trans = jax.vmap(
            lambda xn: jax.vmap(lambda f: system.process_noise.log_prob(xn - f))(fx)
        )(x_next)  # (S, N)
        idx = lp.backward_indices(kt, lwt, log_trans)
        x_t = xt[idx]
        return x_t, x_t

    inputs = (particles[:-1], log_weights[:-1], u[:-1], ts[:-1], keys[:-1])
    _, xs = jax.lax.scan(back, x_last, inputs, reverse=True)
    traj = jnp.concatenate([xs, x_last[None]], axis=0)  # (T, S, n)
    return jnp.swapaxes(traj, 0, 1)


@jit
def ffbsi_batch(
    system: AbstractSystem,
    data: Trajectories,
    pf: ParticleFilterSolution,
    key: PRNGKeyArray,
    n_samples: int,
) -> Float[Array, "B S T n"]:
    """The compiled kernel of :func:`ffbsi`."""
    keys = jax.random.split(key, data.batch_size)
    return jax.vmap(lambda p, w, u, k: _ffbsi_one(system, p, w, u, k, n_samples))(
        pf.particles, pf.log_weights, data.u, keys
    )


@no_type_check  # validates its arguments
def ffbsi(
    system: AbstractSystem,
    data: Trajectories,
    pf: ParticleFilterSolution,
    *,
    n_samples: int = 10,
    key: PRNGKeyArray | None = None,
) -> Float[Array, "B S T n"]:
    """Forward filtering–backward simulation: smoothed state trajectories from a particle filter.

    For each trajectory, draws ``n_samples`` trajectories from the particle approximation of
    p(x_{1:T} | y_{1:T}, θ) (Godsill, Doucet & West 2004; Lindsten & Schön 2013, Alg. 4): x̃_T
    from the final filter weights, then backwards x̃_t = x_t^i with probability ∝
    w_t^i p(x̃_{t+1} | x_t^i). O(N·S·T) density evaluations, N dynamics evaluations per step.

    Args:
        system: the model the filter ran with (its dynamics and process-noise density).
        data: the filtered trajectories (for the inputs).
        pf: the :func:`particle_filter` output.
        n_samples: S, smoothed trajectories per data trajectory.
        key: PRNG key (default ``PRNGKey(0)``).

    Returns:
        (B, S, T, n) smoothed state trajectories (in the system's dtype; ``data`` is cast to it).
    """
    inputs = prepare(system, data)
    system, data = inputs.system, inputs.data
    n_samples = check_int("n_samples", n_samples, 1)
    if not isinstance(pf, ParticleFilterSolution):
        raise TypeError(f"`pf` must be a ParticleFilterSolution; got {type(pf).__name__}.")
    B, T = pf.log_weights.shape[:2]
    if (B, T) != (data.batch_size, data.num_steps):
        raise ValueError(
            f"`pf` is for (B, T) = {(B, T)} but `data` has {(data.batch_size, data.num_steps)}."
        )
    if pf.particles.shape[-1] != system.state_dim:
        raise ValueError(
            f"`pf` has particles of dimension {pf.particles.shape[-1]} but the system's state "
            f"dimension is n = {system.state_dim}."
        )
    key = jax.random.PRNGKey(0) if key is None else key
    return ffbsi_batch(system, data, pf, key, n_samples)
