"""The smoothing step (paper Eq. 10): batched Levenberg–Marquardt on x, block-tridiagonal solves."""

from __future__ import annotations

import copy

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ceemx import lib
from ceemx.data.checks import prepare
from ceemx.data.trajectories import Trajectories
from ceemx.inference.objective import linearize, neg_log_joint_single, nll_offset_single
from ceemx.infra.options import (
    check_bool,
    check_choice,
    check_damping,
    check_int,
    check_nonnegative,
    check_rtol,
    recheck,
)
from ceemx.infra.policy import Runs, entry_point, program, smoothing_work
from ceemx.lib.lm import levenberg_marquardt, marquardt_scale
from ceemx.lib.parallel_blocktri import parallel_solve
from ceemx.lib.results import RESULTS, messages
from ceemx.lib.tree import trace_numbers
from ceemx.lib.typing import PerTrajectory, States, Trajectory, no_type_check
from ceemx.models.system import AbstractSystem

__all__ = [
    "AUTO_CHUNK_BYTES",
    "AUTO_PARALLEL_MIN_T",
    "LMSmoother",
    "SmootherSolution",
    "auto_batch_chunk",
    "smooth",
    "smooth_batch",
    "smooth_prepared",
    "uses_parallel_solve",
]


class LMSmoother(eqx.Module):
    """Levenberg–Marquardt smoother for Eq. 10 (Gauss–Newton for Gaussian noise, IRLS otherwise).

    Minimises −J(x, θ) + ρ_x‖x − x_init‖² for each trajectory independently. Each iteration
    linearises the residuals, assembles the block-tridiagonal Gauss–Newton matrix from per-step
    Jacobian blocks, adds Marquardt damping λ·diag, factors it by a block Cholesky over time
    (O(T n³)) and accepts the step when the actual decrease is a positive fraction of the
    predicted one.

    Attributes:
        rho_x: trust-region weight ρ_x ≥ 0 towards the initial states (paper Eq. 10).
        rtol: converged when the decrease of the objective, or the predicted decrease, is at most
            ``rtol·|objective| + atol``.
        atol: absolute tolerance on the objective.
        max_steps: bound on iterations (accepted and rejected) per trajectory.
        damping: initial Marquardt damping λ₀ (> 0 and below 1/rtol: :mod:`ceemx.infra.options`).
        throw: raise (via ``eqx.error_if``) when any trajectory fails; otherwise report statuses.
        batch_chunk: smooth at most this many trajectories at once (``None``: all of them;
            ``"auto"``, the default: :func:`auto_batch_chunk`). Memory grows as (chunk)·T·n²
            (≈ 20 live (T, n, n) blocks per trajectory): a chunk bounds it for large state
            dimensions; the answers are the same (each trajectory is solved on its own either
            way).
        time_parallel: how each iteration's block-tridiagonal system is solved. ``False``
            (default): block Cholesky and two sequential scans over time (depth O(T)).
            ``True``: ``lib.parallel_blocktri.parallel_solve``, two associative scans (depth
            O(log T), several times the arithmetic; the same steps to rounding). ``"auto"``:
            parallel where it is faster — never on CPU, where it is slower at every size; on an
            accelerator from ``AUTO_PARALLEL_MIN_T`` time steps (a provisional threshold).
    """

    rho_x: float = 0.0
    rtol: float = 1e-10
    atol: float = 0.0
    max_steps: int = eqx.field(default=50, static=True)
    damping: float = 1e-3
    throw: bool = eqx.field(default=False, static=True)
    batch_chunk: int | str | None = eqx.field(default="auto", static=True)
    time_parallel: bool | str = eqx.field(default=False, static=True)

    def __check_init__(self):
        for name in ("rho_x", "atol"):
            check_nonnegative(name, getattr(self, name))
        check_rtol("rtol", self.rtol)
        check_damping("damping", self.damping, self.rtol)
        check_int("max_steps", self.max_steps, 0)
        check_bool("throw", self.throw)
        if isinstance(self.batch_chunk, str):
            if self.batch_chunk != "auto":
                raise TypeError(
                    f"`batch_chunk` must be an integer >= 1, None or 'auto'; "
                    f"got {self.batch_chunk!r}."
                )
        else:
            check_int("batch_chunk", self.batch_chunk, 1, none=True)
        check_choice("time_parallel", self.time_parallel, (False, True, "auto"))


#: ``LMSmoother(batch_chunk="auto")`` keeps a chunk's estimated working memory below this.
#: XLA:CPU allocates a program's temporaries afresh at every call, and glibc serves blocks above
#: 32 MB by ``mmap``: every call of a program with larger temporaries page-faults all of them in
#: again (chunking changes no answer: each trajectory is solved on its own).
AUTO_CHUNK_BYTES = 16 * 2**20


def auto_batch_chunk(B: int, T: int, n: int, itemsize: int) -> int | None:
    """The trajectories :class:`LMSmoother` smooths at once under ``batch_chunk="auto"``.

    ``None`` (all B at once) when the batch's estimated working memory, 20 (T, n, n) blocks per
    trajectory, fits :data:`AUTO_CHUNK_BYTES`, or when fewer than 2 trajectories would (large
    state dimensions, whose per-trajectory programs are not page-fault bound); else the most
    that fit.
    """
    chunk = AUTO_CHUNK_BYTES // max(1, 20 * T * n * n * itemsize)
    return int(chunk) if 2 <= chunk < B else None


#: From this many states per step the smoother judges trial points by −J alone and linearises
#: only at accepted ones (``levenberg_marquardt``'s ``value``). The linearisation costs O(n³) a
#: step against the value's O(n²): from here the run time saved outweighs the value's extra code,
#: which costs compile time that a short fit at smaller n does not win back.
LAZY_MIN_STATES = 48


def judges_by_value(n: int) -> bool:
    """Whether the smoother's trial points are judged by their value alone at n states."""
    return n >= LAZY_MIN_STATES


#: ``LMSmoother(time_parallel="auto")`` solves in parallel on an accelerator from this many steps
AUTO_PARALLEL_MIN_T = 1024


def uses_parallel_solve(option: bool | str, T: int) -> bool:
    """Whether the smoother's ``time_parallel`` option means the associative-scan solve at T."""
    if option == "auto":
        return jax.default_backend() != "cpu" and T >= AUTO_PARALLEL_MIN_T
    return bool(option)


class SmootherSolution(eqx.Module):
    """Result of :func:`smooth`.

    Attributes:
        states: (B, T, n) MAP state trajectories (the initial states where a trajectory's start
            has a non-finite objective; from ``LAZY_MIN_STATES`` states, where a step is accepted
            on its finite value and the gradient there is not finite, that point, ``nonfinite``).
        objective: (B,) −J(x, θ) at ``states`` (without the ρ_x term).
        iterations: (B,) iterations each trajectory took.
        status: (B,) codes from :class:`RESULTS`.
        covariances: (B, T, n, n) marginal covariances of x_t under the Laplace approximation
            (inverse Gauss–Newton matrix of −J), or ``None`` unless requested.
        cross_covariances: (B, T−1, n, n) Cov(x_{t+1}, x_t), or ``None``.
        log_det: (B,) log det of the Gauss–Newton matrix of −J at ``states`` (with the
            covariances), so the Laplace log-evidence is −objective + (Tn/2) log 2π − log_det/2.
    """

    states: States
    objective: PerTrajectory
    iterations: Int[Array, " B"]
    status: RESULTS
    covariances: Float[Array, "B T n n"] | None = None
    cross_covariances: Float[Array, "B T-1 n n"] | None = None
    log_det: PerTrajectory | None = None

    @property
    def converged(self) -> Bool[Array, " B"]:
        """(B,) True where the trajectory converged."""
        return self.status == RESULTS.successful

    def messages(self) -> list[str]:
        """One status message per trajectory (host-side)."""
        return messages(self.status)


def _smooth_one(
    solver,  # an LMSmoother, or any object with its fields
    max_steps: Int[Array, ""],
    system: AbstractSystem,
    x0: Trajectory,
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
    covariance: bool = False,
):
    """One trajectory's smoothing.

    Returns (states, −J, iterations, status, the Gauss–Newton matrix at the states where
    ``covariance``, else ``None``).
    """
    rho = jnp.asarray(solver.rho_x, x0.dtype)
    ident = lambda s: s  # noqa: E731

    offset = nll_offset_single(
        system, mask, x0.shape[0], x0.dtype
    )  # tolerances are relative to −J − offset

    def evaluate(x):
        lin = linearize(ident, system, x, y, u, mask)
        dx = x - x0
        return lin.value - offset + rho * jnp.sum(dx**2), lin._replace(
            grad_x=lin.grad_x + 2.0 * rho * dx
        )

    def value(x):
        return neg_log_joint_single(system, x, y, u, mask) - offset + rho * jnp.sum((x - x0) ** 2)

    lazy = judges_by_value(x0.shape[-1])

    parallel = uses_parallel_solve(getattr(solver, "time_parallel", False), x0.shape[0])

    def solve(lin, lam):
        h = lin.hess_x
        d = jnp.diagonal(h.diagonal, axis1=-2, axis2=-1)
        damped = lib.add_to_diagonal(h, marquardt_scale(d, lam) + 2.0 * rho)
        if parallel:
            step = -parallel_solve(damped, lin.grad_x)
            return step, jnp.all(jnp.isfinite(step))
        L = lib.cholesky(damped)
        return -lib.solve(L, lin.grad_x), lib.is_finite(L)

    def quad(lin, delta):
        return jnp.sum(delta * lib.matvec(lin.hess_x, delta)) + 2.0 * rho * jnp.sum(delta**2)

    out = levenberg_marquardt(
        evaluate,
        lambda lin: lin.grad_x,
        solve,
        quad,
        x0,
        rtol=solver.rtol,
        atol=solver.atol,
        max_steps=max_steps,
        damping=solver.damping,
        value=value if lazy else None,
    )
    if not lazy:
        hess = out.lin.hess_x if covariance else None
        return out.z, out.lin.value, out.steps, out.status, hess
    # The last accepted point's linearisation was not formed: the covariances form it. (A point
    # accepted on its value whose gradient is not finite ends the run there, ``nonfinite``.)
    raw = out.value + offset - rho * jnp.sum((out.z - x0) ** 2)
    hess = evaluate(out.z)[1].hess_x if covariance else None
    return out.z, raw, out.steps, out.status, hess


def smooth_batch(
    solver: LMSmoother,
    system: AbstractSystem,
    x_init: States,
    data: Trajectories,
    covariance: bool,
    runs: Runs = Runs.EVERY_EPOCH,
) -> SmootherSolution:
    """The compiled batch smoother behind :func:`smooth` (no validation; numbers traced).

    ``solver.max_steps`` is passed to the program as a number, not compiled into it: smoothers
    that differ only in their step bound (a fit's warm start and :class:`ceemx.Alternating`'s
    partial E-step) run one program, traced and compiled once. ``runs``: how often the caller
    smooths at these shapes (a fit's warm start when its epochs do not smooth with this program,
    its end-of-fit check: :attr:`~ceemx.infra.policy.Runs.ONCE`); the policy compiles the
    program for that (:func:`ceemx.infra.policy.compiles_one_shot`).
    """
    steps = jnp.asarray(solver.max_steps, jnp.int32)
    # One static configuration for every bound. A copy with the field set, not
    # ``dataclasses.replace``: that calls ``__init__`` again, whose ``float`` annotations the
    # traced numbers do not meet (and ``eqx.tree_at`` cannot reach a static field).
    canonical = copy.copy(solver)
    object.__setattr__(canonical, "max_steps", 0)
    # The chunk as it acts at these shapes: "auto" and None (or a chunk ≥ B) that smooth every
    # trajectory at once are one program, not two compiled alike.
    object.__setattr__(canonical, "batch_chunk", _effective_chunk(solver, x_init))
    program = _smooth_batch_once if runs is Runs.ONCE else _smooth_batch
    return program(canonical, steps, system, x_init, data, covariance)


def _effective_chunk(solver: LMSmoother, x_init: States) -> int | None:
    """The trajectories smoothed at once at ``x_init``'s shape (``None``: all of them)."""
    chunk = getattr(solver, "batch_chunk", None)
    B, T, n = x_init.shape
    if chunk == "auto":
        chunk = auto_batch_chunk(B, T, n, x_init.dtype.itemsize)
    return None if chunk is None or chunk >= B else int(chunk)


def _smooth_batch_impl(
    solver: LMSmoother,
    max_steps: Int[Array, ""],
    system: AbstractSystem,
    x_init: States,
    data: Trajectories,
    covariance: bool,
) -> SmootherSolution:
    chunk = _effective_chunk(solver, x_init)

    def batched(f, *args):
        """``vmap`` over the trajectories, in chunks of ``solver.batch_chunk`` when set."""
        if chunk is None or chunk >= x_init.shape[0]:
            return jax.vmap(f)(*args)
        return jax.lax.map(lambda a: f(*a), args, batch_size=chunk)

    def one(x0, y, u, mask):
        x, value, steps, status, hess = _smooth_one(
            solver, max_steps, system, x0, y, u, mask, covariance
        )
        if hess is None:
            return x, value, steps, status, None
        factor = lib.cholesky(hess)
        sel = lib.selected_inverse(factor)
        return x, value, steps, status, (sel.diagonal, sel.lower, lib.logdet(factor))

    x, value, steps, status, sel = batched(one, x_init, data.y, data.u, data.mask)
    cov = cross = log_det = None
    if sel is not None:
        cov, cross, log_det = sel
    if solver.throw:
        x = eqx.error_if(
            x, jnp.any(status != RESULTS.successful), "smoothing failed on a trajectory"
        )
    return SmootherSolution(x, value, steps, status, cov, cross, log_det)


def _smoothing_work(solver, max_steps, system, x_init: States, data, covariance):
    """The work of smoothing ``x_init``'s batch (:func:`ceemx.infra.policy.smoothing_work`)."""
    del solver, max_steps, system, data, covariance
    B, T, n = x_init.shape
    return smoothing_work(B, T, n)


_smooth_batch = program(_smooth_batch_impl, work=_smoothing_work)  # the E-step's, every epoch
_smooth_batch_once = _smooth_batch.with_runs(Runs.ONCE)  # a start or a check: the same program


@entry_point  # BLAS threads and results as the policy says (ceemx.infra.policy)
@no_type_check  # validates its arguments: ceemx.data.checks.prepare
def smooth(
    system: AbstractSystem,
    data: Trajectories,
    x_init: ArrayLike,
    solver: LMSmoother | None = None,
    *,
    covariance: bool = False,
) -> SmootherSolution:
    """MAP state trajectories for every trajectory of ``data`` (the CE-EM smoothing step, Eq. 10).

    Args:
        system: the model with its current parameters θ.
        data: B trajectories of observations (and inputs, mask).
        x_init: (B, T, n) initial state estimates; also the centre of the ρ_x trust region.
        solver: the smoother configuration (default :class:`LMSmoother`).
        covariance: also return the marginal covariances of each x_t (Laplace approximation), from
            the selected inverse of the Gauss–Newton matrix at the solution.

    Returns:
        A :class:`SmootherSolution`; inspect ``status`` for per-trajectory failures (a failed
        trajectory never changes the others' answers).

    Raises:
        ValueError: on mismatched shapes, non-finite ``x_init``, invalid noise parameters, or a
            value that overflows the working dtype.
        TypeError: on a ``data`` or ``solver`` of the wrong type, or a complex ``x_init``.

    Data, ``x_init`` and the system's floating arrays are cast to the system's dtype
    (:func:`ceemx.data.checks.promote_inputs`): the result is in the dtype of the system's
    parameters.

    Trajectories are processed with ``vmap``; compiled once per shape and solver type: the
    solver's numbers (``rho_x``, ``rtol``, ``atol``, ``damping``, ``max_steps``) are traced, so
    changing them does not recompile.
    """
    if solver is not None and not isinstance(solver, LMSmoother):
        raise TypeError(f"`solver` must be a ceemx.LMSmoother; got {solver!r}.")
    check_bool("covariance", covariance)
    if solver is not None:
        recheck(solver)  # as constructed: eqx.tree_at skips __check_init__
    inputs = prepare(system, data, x_init)
    return smooth_prepared(inputs.system, inputs.data, inputs.states, solver, covariance=covariance)


def smooth_prepared(
    system: AbstractSystem,
    data: Trajectories,
    x_init: ArrayLike,
    solver: LMSmoother | None = None,
    *,
    covariance: bool = False,
    runs: Runs = Runs.EVERY_EPOCH,
) -> SmootherSolution:
    """:func:`smooth` of inputs already prepared (:func:`ceemx.data.checks.prepare`): no checks.

    For the library's own smoothing passes (a fit's warm start) on values validated at their
    entry point; ``runs`` as :func:`smooth_batch`'s.
    """
    solver = LMSmoother() if solver is None else solver
    x_init = jnp.asarray(x_init)
    return smooth_batch(trace_numbers(solver, x_init.dtype), system, x_init, data, covariance, runs)
