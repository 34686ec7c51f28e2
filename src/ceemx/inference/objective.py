"""The CE-EM joint objective J(x, θ) (paper Eq. 9), its residuals and their linearisation.

For one trajectory with observation residuals r^v_t = y_t − g_θ(x_t, u_t, t) and dynamics residuals
r^w_t = x_{t+1} − f_θ(x_t, u_t, t):

    −J(x, θ) = −log p(x₁) + Σ_t −log p_v(r^v_t | mask_t) + Σ_{t<T} −log p_w(r^w_t).

Second-order solvers use, per factor, the noise model's curvature W = SᵀS (see
:mod:`ceemx.models.noise`): the generalised Gauss–Newton matrix Σ J_rᵀ W J_r is block-tridiagonal
in x (each factor touches at most x_t and x_{t+1}) and the gradient is Σ J_rᵀ ∇nll(r). For Gaussian
noise S r are the whitened residuals and this is exactly Gauss–Newton on ½‖S r‖².
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ceemx.data.trajectories import Trajectories
from ceemx.lib.blocktri import BlockTridiagonal
from ceemx.lib.cubature import pair_points_first_half
from ceemx.lib.typing import PerTrajectory, Scalar, States, Trajectory
from ceemx.models.system import AbstractSystem

__all__ = [
    "Linearization",
    "auto_jacobian",
    "depends_on",
    "dynamics_weights",
    "expected_neg_log_joint_single",
    "linearize",
    "linearize_expected",
    "log_joint",
    "neg_log_joint_single",
    "nll_offset",
    "nll_offset_single",
    "observed_span",
    "residuals",
    "whitened_residuals",
]


def residuals(
    system: AbstractSystem,
    x: Trajectory,
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
) -> tuple[Float[Array, "T m"], Float[Array, "T-1 n"]]:
    """Observation residuals (T, m) and dynamics residuals (T−1, n) of one trajectory."""
    T = x.shape[0]
    ts = jnp.arange(T)
    r_obs = y - jax.vmap(system.observe)(x, u, ts)
    r_dyn = x[1:] - jax.vmap(system.dynamics)(x[:-1], u[:-1], ts[:-1])
    return r_obs, r_dyn


def neg_log_joint_single(
    system: AbstractSystem,
    x: Trajectory,
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
) -> Scalar:
    """−J(x, θ) of one trajectory (Eq. 9 with the initial-state prior when the system has one)."""
    r_obs, r_dyn = residuals(system, x, y, u)
    total = jnp.sum(jax.vmap(system.obs_noise.nll)(r_obs, mask))
    total = total + jnp.sum(jax.vmap(system.process_noise.nll)(r_dyn))
    if system.initial_prior is not None:
        total = total + system.initial_prior.nll(x[0])
    return total


def nll_offset_single(system: AbstractSystem, mask: Bool[Array, "T m"], T: int, dtype) -> Scalar:
    """The part of −J that does not depend on x: Σ of each factor's −log p at zero residual.

    −J − offset is ½‖whitened residuals‖² for Gaussian noise; solvers use it as the scale of their
    relative tolerances (the normalising constants can dwarf the fit, e.g. with unit weights).
    """
    m = mask.shape[-1]
    n = system.state_dim
    zeros_m = jnp.zeros((m,), dtype)
    total = jnp.sum(jax.vmap(lambda mk: system.obs_noise.nll(zeros_m, mk))(mask))
    total = total + (T - 1) * system.process_noise.nll(jnp.zeros((n,), dtype))
    if system.initial_prior is not None:
        total = total + system.initial_prior.noise.nll(jnp.zeros((n,), dtype))
    return total


def nll_offset(system: AbstractSystem, data: Trajectories) -> PerTrajectory:
    """(B,) :func:`nll_offset_single` of each trajectory."""
    T = data.num_steps
    return jax.vmap(lambda mk: nll_offset_single(system, mk, T, data.y.dtype))(data.mask)


def log_joint(system: AbstractSystem, x: States, data: Trajectories) -> PerTrajectory:
    """J(x, θ) = log p(x, y | θ) of each trajectory (Eq. 9); shape (B,)."""
    return -jax.vmap(neg_log_joint_single, in_axes=(None, 0, 0, 0, 0))(
        system, x, data.y, data.u, data.mask
    )


def _whitened_single(system, x, y, u, mask):
    for name, noise in (("obs_noise", system.obs_noise), ("process_noise", system.process_noise)):
        if not noise.is_gaussian:
            raise TypeError(
                f"whitened residuals need Gaussian noise; system.{name} is {type(noise).__name__}"
            )
    r_obs, r_dyn = residuals(system, x, y, u)
    parts = [
        jax.vmap(system.obs_noise.whiten)(r_obs, mask).reshape(-1),
        jax.vmap(system.process_noise.whiten)(r_dyn).reshape(-1),
    ]
    if system.initial_prior is not None:
        parts.append(system.initial_prior.noise.whiten(x[0] - system.initial_prior.mean))
    return jnp.concatenate(parts)


def whitened_residuals(
    system: AbstractSystem, x: States, data: Trajectories
) -> Float[Array, "B _"]:
    """Whitened residuals r̃ (B, R) with −J = ½‖r̃‖² + const for Gaussian noise models.

    Order per trajectory: the T·m observation residuals (zeros where masked), the (T−1)·n dynamics
    residuals, then the n prior residuals when the system has an initial-state prior.
    """
    return jax.vmap(_whitened_single, in_axes=(None, 0, 0, 0, 0))(
        system, x, data.y, data.u, data.mask
    )


class Linearization(NamedTuple):
    """Value, gradient and Gauss–Newton curvature of −J for one trajectory.

    ``E``, ``D`` and ``grad_theta`` are present only when linearised with respect to θ too.
    """

    value: Array  # scalar −J
    grad_x: Array | None  # (T, n)
    hess_x: BlockTridiagonal | None  # GN blocks in x
    grad_theta: Array | None = None  # (theta,)
    E: Array | None = None  # (T, n, theta) cross blocks J_xᵀ W J_θ
    D: Array | None = None  # (theta, theta) J_θᵀ W J_θ


def auto_jacobian(fun, argnum, in_dim, out_dim):
    """Jacobian by forward mode when the input is the smaller side, reverse mode otherwise."""
    return jax.jacfwd(fun, argnums=argnum) if in_dim <= out_dim else jax.jacrev(fun, argnums=argnum)


def depends_on(fun: Callable[..., Any], argnum: int, *args: Any) -> bool:
    """Whether any output of ``fun(*args)`` depends on ``args[argnum]`` in its traced program.

    A data-flow walk over the jaxpr: an equation with a dependent input makes all its outputs
    dependent (conservative inside nested programs: ``pjit``, ``scan``, custom derivatives), so a
    ``False`` is exact — the Jacobian with respect to that argument is identically zero — and a
    ``True`` may be a structural dependence only. Shapes are all that matter (``args`` may be
    tracers or ``jax.ShapeDtypeStruct``).
    """
    args = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(jnp.shape(a), a.dtype), args)
    closed = jax.make_jaxpr(fun)(*args)
    jaxpr = closed.jaxpr
    leaves = [len(jax.tree_util.tree_leaves(a)) for a in args]
    start = sum(leaves[:argnum])
    hit = {id(v) for v in jaxpr.invars[start : start + leaves[argnum]]}
    for eqn in jaxpr.eqns:
        if any(id(v) in hit for v in eqn.invars):
            hit.update(id(v) for v in eqn.outvars)
    return any(id(v) in hit for v in jaxpr.outvars)


def linearize(
    build: Callable[[Any], AbstractSystem],
    theta: Any,
    x: Trajectory,
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
    *,
    wrt_theta: bool = False,
    wrt_x: bool = True,
) -> Linearization:
    """Linearise −J of one trajectory around (x, θ).

    Args:
        build: maps ``theta`` to the system (``lambda s: s`` when θ is the system itself).
        theta: a flat parameter vector (theta,) when ``wrt_theta`` is True, otherwise any pytree.
        x: one trajectory's states (T, n).
        y: its observations (T, m).
        u: its inputs (T, p).
        mask: which observations are present (T, m).
        wrt_theta: also return the θ-gradient, the cross blocks E and the θθ block D.
        wrt_x: compute the x-gradient and x-blocks (and E); ``False`` for a θ-only linearisation.
    """
    system = build(theta)
    point = _Point(build, theta, x, y, u, jnp.arange(x.shape[0]))
    r_obs, r_dyn = residuals(system, x, y, u)
    on, pn = system.obs_noise, system.process_noise
    S = _sqrt_curvatures(on, pn, r_obs, r_dyn, mask)
    gv = jax.vmap(jax.grad(on.nll))(r_obs, mask)  # (T,m)
    gw = jax.vmap(jax.grad(pn.nll))(r_dyn)  # (T-1,n)
    value = jnp.sum(jax.vmap(on.nll)(r_obs, mask)) + jnp.sum(jax.vmap(pn.nll)(r_dyn))
    prior = system.initial_prior
    prior_x = None  # the prior's gradient and curvature in x₁
    if prior is not None:
        r0 = x[0] - prior.mean
        value = value + prior.noise.nll(r0)
        S0 = prior.noise.sqrt_curvature(r0)
        prior_x = jax.grad(prior.noise.nll)(r0), S0.T @ S0
    grad = hess = x_blocks = None
    if wrt_x:
        grad, hess, x_blocks = _x_blocks(point, S, gv, gw, prior_x)
    if not wrt_theta:
        return Linearization(value, grad, hess)
    grad_theta, E, D = _theta_blocks(point, S, gv, gw, x_blocks)
    if prior is not None:  # a prior whose mean depends on θ
        grad_theta = grad_theta + _prior_theta_gradient(build, x[0], theta)
    return Linearization(value, grad, hess, grad_theta, E, 0.5 * (D + D.T))


def _mT(a: Array) -> Array:
    return jnp.swapaxes(a, -1, -2)


class _Point(NamedTuple):
    """One trajectory at the linearisation point (x, θ), with its residual functions per step."""

    build: Callable[[Any], AbstractSystem]
    theta: Any
    x: Trajectory
    y: Float[Array, "T m"]
    u: Float[Array, "T p"]
    ts: Array

    def obs_res(self, xt, th, yt, ut, t):
        """The observation residual at one step."""
        return yt - self.build(th).observe(xt, ut, t)

    def dyn_res(self, xt, th, ut, t):
        """The dynamics residual at one step, less x_{t+1} (whose Jacobian is the identity)."""
        return -self.build(th).dynamics(xt, ut, t)


class _SqrtCurvatures(NamedTuple):
    """Products with the noise models' square-root curvatures S per step: S_v A, S_w A, S_wᵀ A.

    Row scalings for diagonal noise (no d × d product per step).
    """

    Sv_mul: Callable[[Array], Array]
    Sw_mul: Callable[[Array], Array]
    SwT_mul: Callable[[Array], Array]
    SwT_Sw: Array  # (T-1, n, n)


def _sqrt_curvatures(on, pn, r_obs, r_dyn, mask) -> _SqrtCurvatures:
    """The square-root curvatures of the observation and the process noise at the residuals."""
    if on.diagonal_curvature:
        sv = jax.vmap(on.sqrt_curvature_diagonal)(r_obs, mask)  # (T,m)
        Sv_mul = lambda a: sv[..., None] * a  # noqa: E731
    else:
        Sv = jax.vmap(on.sqrt_curvature)(r_obs, mask)  # (T,m,m)
        Sv_mul = lambda a: Sv @ a  # noqa: E731
    if pn.diagonal_curvature:
        sw = jax.vmap(pn.sqrt_curvature_diagonal)(r_dyn)  # (T-1,n)
        Sw_mul = SwT_mul = lambda a: sw[..., None] * a  # noqa: E731
        SwT_Sw = jax.vmap(jnp.diag)(sw**2)
    else:
        Sw = jax.vmap(pn.sqrt_curvature)(r_dyn)  # (T-1,n,n)
        Sw_mul = lambda a: Sw @ a  # noqa: E731
        SwT_mul = lambda a: _mT(Sw) @ a  # noqa: E731
        SwT_Sw = _mT(Sw) @ Sw
    return _SqrtCurvatures(Sv_mul, Sw_mul, SwT_mul, SwT_Sw)


def _x_blocks(p: _Point, S: _SqrtCurvatures, gv, gw, prior_x):
    """The x-gradient, the block-tridiagonal Gauss–Newton matrix in x, and (S_v G, S_w F)."""
    x, theta, y, u, ts = p.x, p.theta, p.y, p.u, p.ts
    n, m = x.shape[1], y.shape[-1]
    # Per-step Jacobians with respect to x_t.
    G = jax.vmap(auto_jacobian(p.obs_res, 0, n, m), in_axes=(0, None, 0, 0, 0))(x, theta, y, u, ts)
    F = jax.vmap(jax.jacfwd(p.dyn_res, argnums=0), in_axes=(0, None, 0, 0))(
        x[:-1], theta, u[:-1], ts[:-1]
    )  # (T-1,n,n)
    SG = S.Sv_mul(G)
    SF = S.Sw_mul(F)
    diag = _mT(SG) @ SG
    diag = diag.at[:-1].add(_mT(SF) @ SF)
    diag = diag.at[1:].add(S.SwT_Sw)
    lower = S.SwT_mul(SF)  # block (t+1, t)
    grad = jnp.einsum("tmn,tm->tn", G, gv)
    grad = grad.at[:-1].add(jnp.einsum("tkn,tk->tn", F, gw))
    grad = grad.at[1:].add(gw)
    if prior_x is not None:
        grad = grad.at[0].add(prior_x[0])
        diag = diag.at[0].add(prior_x[1])
    return grad, BlockTridiagonal(diagonal=0.5 * (diag + _mT(diag)), lower=lower), (SG, SF)


def _theta_blocks(p: _Point, S: _SqrtCurvatures, gv, gw, x_blocks):
    """(θ-gradient, cross blocks E (None without x-blocks), θθ block D) of the residual factors.

    A factor whose residual does not depend on θ at all (the observation map when only the
    dynamics learn) has a zero θ-Jacobian: its products are skipped, decided at trace time.
    """
    x, theta, y, u, ts = p.x, p.theta, p.y, p.u, p.ts
    (T, n), m, dtype = x.shape, y.shape[-1], x.dtype
    P = theta.shape[0]  # the length of θ
    D = jnp.zeros((P, P), dtype)
    grad_theta = jnp.zeros((P,), dtype)
    E = jnp.zeros((T, n, P), dtype) if x_blocks is not None else None
    if depends_on(p.obs_res, 1, x[0], theta, y[0], u[0], ts[0]):
        Gt = jax.vmap(auto_jacobian(p.obs_res, 1, P, m), in_axes=(0, None, 0, 0, 0))(
            x, theta, y, u, ts
        )  # (T,m,P)
        SGt = S.Sv_mul(Gt)
        D = D + jnp.einsum("tmp,tmq->pq", SGt, SGt)
        grad_theta = grad_theta + jnp.einsum("tmp,tm->p", Gt, gv)
        if E is not None and x_blocks is not None:
            E = E + _mT(x_blocks[0]) @ SGt
    if T > 1 and depends_on(p.dyn_res, 1, x[0], theta, u[0], ts[0]):
        Ft = jax.vmap(auto_jacobian(p.dyn_res, 1, P, n), in_axes=(0, None, 0, 0))(
            x[:-1], theta, u[:-1], ts[:-1]
        )
        SFt = S.Sw_mul(Ft)
        D = D + jnp.einsum("tnp,tnq->pq", SFt, SFt)
        grad_theta = grad_theta + jnp.einsum("tnp,tn->p", Ft, gw)
        if E is not None and x_blocks is not None:
            E = E.at[:-1].add(_mT(x_blocks[1]) @ SFt)
            E = E.at[1:].add(S.SwT_mul(SFt))
    if E is not None:
        E = E.astype(dtype)
    return grad_theta, E, D


def _prior_theta_gradient(build: Callable[[Any], AbstractSystem], x0, theta):
    """The θ-gradient of the initial-state prior's −log p(x₁) (its mean may depend on θ)."""

    def prior_nll(x0, th):
        pr = build(th).initial_prior
        assert pr is not None  # θ does not decide whether there is a prior
        return pr.nll(x0)

    return jax.grad(prior_nll, argnums=1)(x0, theta)


# --- The expected complete-data objective of Laplace EM -------------------------------------------
#
# Under a Gaussian state posterior q, E_q[−log p(x, y | θ)] is a sum of expectations over the
# marginals of x_t (observation terms, the initial prior) and over the pairs (x_t, x_{t+1})
# (dynamics terms). Each expectation is a cubature sum over equally weighted points
# (:mod:`ceemx.lib.cubature`): ``points`` (T, K, n) of each x_t and ``pairs`` (T−1, K₂, 2n) of each
# (x_t, x_{t+1}).


def dynamics_weights(mask: Bool[Array, "T m"]) -> Bool[Array, " T-1"]:
    """Which transitions (x_t, x_{t+1}) of one trajectory end at or before its last observation.

    The states after a trajectory's last observed sample — the padding of a shorter record in a
    batch (:meth:`ceemx.Trajectories.from_arrays`), or a masked tail — integrate out of p(y | θ)
    exactly: ∫ p(x_{t+1} | x_t) dx_{t+1} = 1 whatever θ. Under Laplace EM's Gaussian posterior
    they are the prior chain run on from the last observed state, its covariance growing with
    every step; their expected dynamics terms would fit θ and the process noise to that
    linearised chain. They are left out of the M-step objective and the noise statistics.
    """
    return observed_span(mask)[1:]


def observed_span(mask: Bool[Array, "T m"]) -> Bool[Array, " T"]:
    """Which steps of one trajectory come at or before its last observed sample."""
    steps = jnp.arange(mask.shape[0])
    last = jnp.max(jnp.where(jnp.any(mask, axis=-1), steps, -1))
    return steps <= last


def _expected_terms(theta_build, points, pairs, y, u, mask):
    """Per-point residual functions of θ, flattened over (time, point): used by both functions.

    The dynamics are evaluated once per distinct x_t of the pair points (``dyn_rows``, 2n + 1
    per step, not 4n: :func:`ceemx.lib.cubature.pair_points_first_half`); ``spread`` takes
    their values (or Jacobians), shaped (rows, …), to one per pair point, and ``z_next`` holds
    each pair point's x_{t+1} in the same order: the dynamics residual of the pair points is
    ``z_next − spread(f(dyn_rows))``.
    """
    T, K1, n = points.shape
    K2 = pairs.shape[1]
    ts = jnp.arange(T)
    obs_rows = (
        points.reshape(T * K1, n),
        jnp.repeat(y, K1, axis=0),
        jnp.repeat(u, K1, axis=0),
        jnp.repeat(mask, K1, axis=0),
        jnp.repeat(ts, K1),
    )
    prev, spread_steps = pair_points_first_half(pairs, n)
    D = prev.shape[1]
    dyn_rows = (
        prev.reshape((T - 1) * D, n),
        jnp.repeat(u[:-1], D, axis=0),
        jnp.repeat(ts[:-1], D),
    )
    z_next = pairs[..., n:].reshape((T - 1) * K2, n)

    def spread(values):
        per_step = spread_steps(values.reshape((T - 1, D) + values.shape[1:]))
        return per_step.reshape(((T - 1) * K2,) + values.shape[1:])

    def obs_res(th, x, yt, ut, mk, t):
        return yt - theta_build(th).observe(x, ut, t)

    def dyn_fn(th, x, ut, t):
        return theta_build(th).dynamics(x, ut, t)

    return obs_rows, (dyn_rows, z_next, spread), obs_res, dyn_fn, 1.0 / K1, 1.0 / K2


def expected_neg_log_joint_single(
    system: AbstractSystem,
    points: Float[Array, "T K n"],
    pairs: Float[Array, "T-1 K2 n2"],
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
) -> Scalar:
    """E_q[−log p(x, y | θ)] of one trajectory by cubature over marginal and pairwise points."""
    ident = lambda th: th  # noqa: E731
    obs_rows, dyn, obs_res, dyn_fn, c1, c2 = _expected_terms(ident, points, pairs, y, u, mask)
    x, yy, uu, mk, t = obs_rows
    r_obs = jax.vmap(obs_res, in_axes=(None, 0, 0, 0, 0, 0))(system, x, yy, uu, mk, t)
    (xp, uw, tw), z_next, spread = dyn
    keep = jnp.repeat(dynamics_weights(mask), pairs.shape[1])  # per pair point
    r_dyn = z_next - spread(jax.vmap(dyn_fn, in_axes=(None, 0, 0, 0))(system, xp, uw, tw))
    r_dyn = jnp.where(keep[:, None], r_dyn, 0.0)
    total = c1 * jnp.sum(jax.vmap(system.obs_noise.nll)(r_obs, mk))
    dyn_nll = jax.vmap(system.process_noise.nll)(r_dyn)
    total = total + c2 * jnp.sum(jnp.where(keep, dyn_nll, 0.0))
    if system.initial_prior is not None:
        total = total + jnp.mean(jax.vmap(system.initial_prior.nll)(points[0]))
    return total


def linearize_expected(
    build: Callable[[Any], AbstractSystem],
    theta: Float[Array, " theta"],
    points: Float[Array, "T K n"],
    pairs: Float[Array, "T-1 K2 n2"],
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
) -> tuple[Scalar, Float[Array, " theta"], Float[Array, "theta theta"]]:
    """(value, θ-gradient, Gauss–Newton matrix in θ) of :func:`expected_neg_log_joint_single`.

    The Gauss–Newton matrix is Σ_points c·J_θᵀ W J_θ with each noise model's curvature W = SᵀS, as
    for the CE learning step; for Gaussian noise and a model linear in θ it is the exact Hessian.
    """
    system = build(theta)
    obs_rows, dyn, obs_res, dyn_fn, c1, c2 = _expected_terms(build, points, pairs, y, u, mask)
    P = theta.shape[0]
    m = y.shape[-1]
    n = points.shape[-1]
    on, pn = system.obs_noise, system.process_noise
    x, yy, uu, mk, t = obs_rows
    r_obs = jax.vmap(obs_res, in_axes=(None, 0, 0, 0, 0, 0))(theta, x, yy, uu, mk, t)
    G = jax.vmap(auto_jacobian(obs_res, 0, P, m), in_axes=(None, 0, 0, 0, 0, 0))(
        theta, x, yy, uu, mk, t
    )
    (xp, uw, tw), z_next, spread = dyn
    keep = jnp.repeat(dynamics_weights(mask), pairs.shape[1])  # per pair point
    r_dyn = z_next - spread(jax.vmap(dyn_fn, in_axes=(None, 0, 0, 0))(theta, xp, uw, tw))
    r_dyn = jnp.where(keep[:, None], r_dyn, 0.0)
    # ∂r/∂θ = −∂f/∂θ at each pair point's x_t (x_{t+1} does not depend on θ)
    F = -spread(
        jax.vmap(auto_jacobian(dyn_fn, 0, P, n), in_axes=(None, 0, 0, 0))(theta, xp, uw, tw)
    )
    F = jnp.where(keep[:, None, None], F, 0.0)
    # Row scalings for diagonal noise (as in `linearize`): no d × d product per cubature point.
    if on.diagonal_curvature:
        SG = jax.vmap(on.sqrt_curvature_diagonal)(r_obs, mk)[..., None] * G
    else:
        SG = jax.vmap(on.sqrt_curvature)(r_obs, mk) @ G
    if pn.diagonal_curvature:
        SF = jax.vmap(pn.sqrt_curvature_diagonal)(r_dyn)[..., None] * F
    else:
        SF = jax.vmap(pn.sqrt_curvature)(r_dyn) @ F
    dyn_nll = jnp.where(keep, jax.vmap(pn.nll)(r_dyn), 0.0)
    value = c1 * jnp.sum(jax.vmap(on.nll)(r_obs, mk)) + c2 * jnp.sum(dyn_nll)
    grad = c1 * jnp.einsum("kmp,km->p", G, jax.vmap(jax.grad(on.nll))(r_obs, mk))
    grad = grad + c2 * jnp.einsum("knp,kn->p", F, jax.vmap(jax.grad(pn.nll))(r_dyn))
    D = c1 * jnp.einsum("kmp,kmq->pq", SG, SG) + c2 * jnp.einsum("knp,knq->pq", SF, SF)
    if system.initial_prior is not None:

        def prior_nll(th):
            pr = build(th).initial_prior
            assert pr is not None  # θ does not decide whether there is a prior
            return jnp.mean(jax.vmap(pr.nll)(points[0]))

        pv, gp = jax.value_and_grad(prior_nll)(theta)
        value, grad = value + pv, grad + gp
    return value, grad, 0.5 * (D + D.T)
