"""The learning step's Gauss–Newton matrix from the batch's whitened θ-Jacobian rows, by chunks.

At fixed states, −J_b(θ) is a sum of per-step factors (observations, transitions, the initial
prior). The Gauss–Newton matrix of Σ_b w_b (−J_b) is Σ_b w_b Σ_rows (S J_θ)ᵀ (S J_θ) with each
factor's curvature root S (:mod:`ceemx.models.noise`). :func:`batch_gauss_newton` forms the rows
of a chunk of time steps at a time (every trajectory's steps in one sequence, scaled by √w_b) and
adds each chunk's RᵀR to the P × P sum in a ``lax.scan``: the rows of the whole batch are never
held at once (at the Figure-3 size they were 50 MB, three such arrays a call: fresh pages from
the kernel every call, 36 700 page faults, a third of the build's time; and B·T·n·P numbers on a
long record), while each product stays large enough for the BLAS (``ROWS_CHUNK_BYTES``). Factors
whose residual does not depend on θ at all (the observation model when only the dynamics learn,
or the reverse) contribute no rows: that is decided at trace time from the residual's program
(:func:`ceemx.inference.objective.depends_on`), since the θ-Jacobian of such a factor is
identically zero and its product would be pure cost (on the Figure-3 problem half of the build).
:func:`theta_rows` gives one trajectory's rows at once (the same per-step terms).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ceemx.inference.objective import auto_jacobian, depends_on
from ceemx.lib.typing import PerTrajectory, Scalar, States, Theta, Trajectory
from ceemx.models.system import AbstractSystem

__all__ = ["ROWS_CHUNK_BYTES", "batch_gauss_newton", "gram", "theta_rows"]

#: Bytes of θ-Jacobian rows :func:`batch_gauss_newton` forms at a time: well below glibc's 32 MB
#: ``mmap`` threshold, above which XLA:CPU's fresh temporaries are page-faulted in at every call.
ROWS_CHUNK_BYTES = 4 * 2**20


def _step_terms(
    build: Callable[[Theta], AbstractSystem], theta: Theta, x: Trajectory, y, u
) -> tuple[Callable[..., tuple[Scalar, Array, Array]], int]:
    """``(step, rows per step)`` of the factors of one time step, for θ-Jacobian rows.

    ``step(x_t, x_{t+1}, y_t, u_t, mask_t, t)`` → (−J's terms at step t, their θ-gradient, their
    whitened θ-Jacobian rows S·J_θ): the observation factor at t and the transition t → t+1 (its
    terms zero at the last step, t = T − 1). A factor whose residual does not depend on θ
    (decided at trace time on x[0], y[0], u[0]) contributes no rows.
    """
    system = build(theta)
    T, n = x.shape
    m, P = y.shape[-1], theta.shape[0]
    dtype = x.dtype
    on, pn = system.obs_noise, system.process_noise

    def obs_res(xt, th, yt, ut, t):
        return yt - build(th).observe(xt, ut, t)

    def dyn_res(xt, th, ut, t):
        return -build(th).dynamics(xt, ut, t)  # + x_{t+1}, which does not depend on θ

    t0 = jnp.zeros((), jnp.int32)
    with_obs = depends_on(obs_res, 1, x[0], theta, y[0], u[0], t0)
    with_dyn = T > 1 and depends_on(dyn_res, 1, x[0], theta, u[0], t0)

    def step(xt, xn, yt, ut, mt, t):
        has_next = t < T - 1
        r_obs = yt - system.observe(xt, ut, t)
        r_dyn = xn - system.dynamics(xt, ut, t)
        value = on.nll(r_obs, mt) + jnp.where(has_next, pn.nll(r_dyn), 0.0)
        grad = jnp.zeros((P,), dtype)
        rows = []
        if with_obs:
            G = auto_jacobian(obs_res, 1, P, m)(xt, theta, yt, ut, t)
            grad = grad + G.T @ jax.grad(on.nll)(r_obs, mt)
            if on.diagonal_curvature:
                rows.append(on.sqrt_curvature_diagonal(r_obs, mt)[:, None] * G)
            else:
                rows.append(on.sqrt_curvature(r_obs, mt) @ G)
        if with_dyn:
            F = auto_jacobian(dyn_res, 1, P, n)(xt, theta, ut, t)
            grad = grad + jnp.where(has_next, F.T @ jax.grad(pn.nll)(r_dyn), 0.0)
            if pn.diagonal_curvature:
                SF = pn.sqrt_curvature_diagonal(r_dyn)[:, None] * F
            else:
                SF = pn.sqrt_curvature(r_dyn) @ F
            rows.append(jnp.where(has_next, SF, 0.0))
        R = jnp.concatenate(rows) if rows else jnp.zeros((0, P), dtype)
        return value, grad, R.astype(dtype)

    return step, m * with_obs + n * with_dyn


def _prior_terms(
    build: Callable[[Theta], AbstractSystem], theta: Theta, x1: Float[Array, " n"]
) -> tuple[Scalar, Float[Array, " theta"]]:
    """The initial-state prior's −log p(x₁) and its θ-gradient (zeros without a prior)."""
    if build(theta).initial_prior is None:
        return jnp.zeros((), x1.dtype), jnp.zeros_like(theta)

    def prior_nll(th):
        pr = build(th).initial_prior
        assert pr is not None  # θ does not decide whether there is a prior
        return pr.nll(x1)

    return jax.value_and_grad(prior_nll)(theta)


def _next_states(x: Array) -> Array:
    """x_{t+1} beside x_t along the time axis (axis −2; the last step repeats x_T, unused)."""
    return jnp.concatenate([x[..., 1:, :], x[..., -1:, :]], axis=-2)


def theta_rows(
    build: Callable[[Theta], AbstractSystem],
    theta: Theta,
    x: Trajectory,
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
) -> tuple[Scalar, Float[Array, " theta"], Float[Array, "R theta"]]:
    """(−J, its θ-gradient, the whitened θ-Jacobian rows S·J_θ) of one trajectory at fixed x.

    The rows of every step's factors at once, step by step (:func:`_step_terms`; the last step's
    transition rows are zero); RᵀR is the trajectory's Gauss–Newton matrix (that of
    ``inference.objective.linearize(..., wrt_theta=True)``). A prior whose mean depends on θ
    enters the value and the gradient, not the rows (as in ``linearize``).
    :func:`batch_gauss_newton` forms the same sums for a batch without holding the rows.
    """
    step, _ = _step_terms(build, theta, x, y, u)
    ts = jnp.arange(x.shape[0], dtype=jnp.int32)
    v, g, R = jax.vmap(step)(x, _next_states(x), y, u, mask, ts)
    pv, pg = _prior_terms(build, theta, x[0])
    return jnp.sum(v) + pv, jnp.sum(g, axis=0) + pg, R.reshape(-1, theta.shape[0])


def batch_gauss_newton(
    build: Callable[[Theta], AbstractSystem],
    theta: Theta,
    states: States,
    y: Float[Array, "B T m"],
    u: Float[Array, "B T p"],
    mask: Bool[Array, "B T m"],
    weights: PerTrajectory,
    chunk_bytes: int | None = None,
) -> tuple[Scalar, Float[Array, " theta"], Float[Array, "theta theta"]]:
    """(Σ_b w_b (−J_b), its θ-gradient, Σ_b w_b RᵀR_b) at fixed states, rows formed by chunks.

    The same sums as :func:`theta_rows` of every trajectory with weight w_b > 0 (trajectories of
    weight 0 take no part, whatever their numbers); the B·T time steps are cut into chunks of at
    most ``chunk_bytes`` (default :data:`ROWS_CHUNK_BYTES`) of rows, each chunk's rows formed,
    multiplied out and dropped in a ``lax.scan``.
    """
    B, T, _ = states.shape
    P = theta.shape[0]
    dtype = states.dtype
    ok = weights > 0
    w = jnp.where(ok, weights, 0.0)
    step, per_step = _step_terms(build, theta, states[0], y[0], u[0])

    def weighted(xt, xn, yt, ut, mt, t, wt):
        value, grad, R = step(xt, xn, yt, ut, mt, t)
        keep = wt > 0
        return (
            jnp.where(keep, wt * value, 0.0),
            jnp.where(keep, wt * grad, 0.0),
            jnp.where(keep, jnp.sqrt(wt) * R, 0.0).astype(dtype),
        )

    # Every trajectory's steps in one sequence, cut into equal chunks (the last padded by
    # weight-0 steps).
    N = B * T
    budget = ROWS_CHUNK_BYTES if chunk_bytes is None else chunk_bytes
    most = max(1, budget // max(1, per_step * P * jnp.dtype(dtype).itemsize))
    chunks = -(-N // min(most, N))
    size = -(-N // chunks)
    pad = chunks * size - N
    ts = jnp.broadcast_to(jnp.arange(T, dtype=jnp.int32), (B, T))
    wts = jnp.broadcast_to(w[:, None], (B, T))

    def chunked(a):
        a = a.reshape((N,) + a.shape[2:])
        a = jnp.concatenate([a, jnp.zeros((pad,) + a.shape[1:], a.dtype)]) if pad else a
        return a.reshape((chunks, size) + a.shape[1:])

    xs = tuple(chunked(a) for a in (states, _next_states(states), y, u, mask, ts, wts))

    def accumulate(carry, chunk):
        value, grad, hess = carry
        v, g, R = jax.vmap(weighted)(*chunk)
        hess = hess + gram(R.reshape(-1, P))
        return (value + jnp.sum(v), grad + jnp.sum(g, axis=0), hess), None

    zero = (jnp.zeros((), dtype), jnp.zeros((P,), dtype), jnp.zeros((P, P), dtype))
    (value, grad, hess), _ = jax.lax.scan(accumulate, zero, xs)  # each chunk's RᵀR symmetric
    pv, pg = jax.vmap(lambda x1: _prior_terms(build, theta, x1))(states[:, 0])
    value = value + jnp.sum(jnp.where(ok, w * pv, 0.0))
    grad = grad + jnp.sum(jnp.where(ok[:, None], w[:, None] * pg, 0.0), axis=0)
    return value, grad, hess


#: :func:`gram` splits θ into blocks of at least this many columns and forms only the blocks on
#: and above the diagonal (the product is symmetric; XLA has no SYRK): 6 of 9 block products
#: with 3 blocks, fewer in proportion with more.
GRAM_BLOCK_MIN = 96


def gram(rows: Float[Array, "R theta"]) -> Float[Array, "theta theta"]:
    """RᵀR (zeros when R has no rows), by blocks of columns: the upper blocks, mirrored below."""
    P = rows.shape[-1]
    k = max(1, min(4, P // GRAM_BLOCK_MIN))
    if k == 1:
        D = rows.T @ rows
        return 0.5 * (D + D.T)
    edges = [round(i * P / k) for i in range(k + 1)]
    cols = [rows[:, edges[i] : edges[i + 1]] for i in range(k)]
    upper = {(i, j): cols[i].T @ cols[j] for i in range(k) for j in range(i, k)}
    for i in range(k):  # the diagonal blocks exactly symmetric
        upper[i, i] = 0.5 * (upper[i, i] + upper[i, i].T)
    blocks = [[upper[i, j] if i <= j else upper[j, i].T for j in range(k)] for i in range(k)]
    return jnp.block(blocks)
