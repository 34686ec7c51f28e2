"""Parameter uncertainty from the Laplace approximation of the joint posterior p(x, θ | y).

At an end point (x̂, θ̂) the Gauss–Newton Hessian of −J(x, θ) − log p(θ) (Eq. 9) is an arrowhead
matrix: per trajectory a block-tridiagonal ``A_b`` (states), a border ``E_b`` (states × θ) and the
shared θ-block ``D`` (:func:`ceemx.identification.schur.linearize_joint`). By the Schur
complement identity the θ-block of its inverse is exactly ``S⁻¹`` with

    ``S = D − Σ_b E_bᵀ A_b⁻¹ E_b``,

so the Laplace covariance of θ is ``S⁻¹`` (no damping, no proximal terms); trajectories with
weight 0 (excluded or failed) take no part.

When it is valid:

* at a converged maximum of J (elsewhere the gradient is not zero and ``S⁻¹`` is only the
  curvature of a quadratic model, not a posterior covariance);
* certainty-equivalent J ignores the volume of the state posterior, so ``S⁻¹`` is the θ-marginal of
  the Laplace approximation of the *joint* posterior p(x, θ | y), conditional on the noise models
  (noise covariances that are not trainable are treated as known); it is close to the marginal
  posterior of θ when that joint posterior is near-Gaussian (informative data, mild
  nonlinearity);
* the same formula holds whichever solver reached the end point (:class:`ceemx.JointLM`,
  :class:`ceemx.Alternating`); for :class:`ceemx.ParticleEM` it is evaluated at the returned
  states and θ.

θ is the flat vector of :class:`ceemx.identification.problem.FitProblem`, in *unconstrained*
coordinates for
constrained parameters (``θ = c.inverse(natural)``). Natural-unit uncertainties follow by the
delta method: ``Cov_nat = J Cov_θ Jᵀ`` with ``J = diag(c.forward'(θ))`` (every transform acts
elementwise, so ``J`` is diagonal).

When ``S`` (or an ``A_b``) is not numerically positive definite — the end point is not a
maximum, or a parameter is not identifiable from the data (e.g. has no effect on it) — every
entry is NaN and a warning says so.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float

from ceemx.data.arrays import is_concrete
from ceemx.identification.analysis.end_point import end_point
from ceemx.identification.problem import FitProblem
from ceemx.identification.schur import schur_complement, schur_complement_work
from ceemx.infra.policy import Runs, program
from ceemx.infra.warn import warn
from ceemx.lib.dense import symmetrize
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import PerTrajectory, States, Theta

__all__ = [
    "Estimate",
    "NamedEstimates",
    "evidence_covariance",
    "evidence_function",
    "fit_covariance",
    "fit_parameter_estimates",
    "fit_standard_errors",
    "natural_covariance",
    "natural_jacobian",
    "parameter_covariance",
    "schur_complement",
    "standard_errors",
    "standard_errors_by_name",
    "stencil_hessian",
]

_NOT_PD = (
    "The Laplace covariance of θ is NaN: the Schur complement S = D − Σ_b E_bᵀ A_b⁻¹ E_b of the "
    "joint Gauss–Newton matrix is not positive definite{which}. Either the end point is not a "
    "maximum of J (the fit did not converge) or a parameter is not identifiable from the data "
    "(e.g. it has no effect on the observations); fix or drop such parameters (`trainable`) or "
    "add a prior (`log_prior`)."
)

_HELD = (
    "Standard errors conditional on {which} held at their estimates: the data do not determine "
    "them (the Schur complement S of the joint Gauss–Newton matrix is singular along them), so "
    "they have no standard error (NaN), and the others' are those at these values."
)


@program(runs=Runs.ONCE, work=schur_complement_work)
def _laplace(
    problem: FitProblem,
    theta: Theta,
    states: States,
    weights: PerTrajectory,
    keep: Float[Array, " theta"],
) -> tuple[Float[Array, "theta theta"], Bool[Array, ""], Bool[Array, " theta"]]:
    """``(S⁻¹ or NaN, ok, weak)``; ``weak`` flags the θ entries with a negligible pivot of S.

    Entries with ``keep`` = 0 (learned noise scales) are held fixed: their rows and columns of S
    are replaced by the identity, so the rest is the inverse of S restricted to the kept entries.
    """
    S, a_ok = schur_complement(problem, theta, states, weights)
    P = S.shape[-1]
    S = keep[:, None] * S * keep[None, :] + jnp.diag(1.0 - keep)
    chol = jnp.linalg.cholesky(S)
    pivots = jnp.diagonal(chol)
    floor = P * jnp.finfo(S.dtype).eps * jnp.max(jnp.abs(jnp.diagonal(S)))
    good = jnp.isfinite(pivots) & (pivots**2 > floor)
    # Which entries are to blame: no curvature of their own, or a large loading on a near-null
    # (or negative) direction of the diagonally scaled S.
    d = jnp.diagonal(S)
    flat = ~(d > floor)
    scale = jnp.where(flat, 1.0, 1.0 / jnp.sqrt(jnp.where(flat, 1.0, d)))
    eigval, eigvec = jnp.linalg.eigh(scale[:, None] * S * scale[None, :])
    null = eigval <= P * jnp.finfo(S.dtype).eps * jnp.maximum(jnp.max(eigval), 1.0)
    weak = flat | jnp.any(null[None, :] & (jnp.abs(eigvec) > 0.3), axis=1)
    eye = jnp.eye(P, dtype=S.dtype)
    cov = symmetrize(jax.scipy.linalg.cho_solve((chol, True), eye))
    ok = a_ok & jnp.all(good) & jnp.all(jnp.isfinite(chol)) & jnp.all(jnp.isfinite(cov))
    return jnp.where(ok, cov, jnp.nan), ok, weak


def _names(problem: FitProblem) -> list[str]:
    """One name per entry of θ as written, e.g. ``A[0,0]`` or ``sigma``."""
    return problem.parameter_names()


class Estimate(NamedTuple):
    """One parameter's estimate and standard error, in natural units (a tuple: ``v, se = e``)."""

    estimate: float
    std_error: float

    def __repr__(self) -> str:
        return f"Estimate(estimate={self.estimate:.6g}, std_error={self.std_error:.6g})"


class NamedEstimates(dict):
    """``name → Estimate(estimate, std_error)``, keyed by names as written (``A[0,0]``, ``sigma``).

    The key paths of earlier versions (``.A[0,0]``, ``.sigma``) still look up, through ``[]``,
    ``in`` and ``get``; iteration gives the names as written. ``print`` shows a table.
    """

    def __str__(self) -> str:
        """A table: each parameter's name, estimate and standard error."""
        rows = [("parameter", "estimate", "std. error")]
        rows += [(name, f"{e:.6g}", f"{se:.3g}") for name, (e, se) in self.items()]
        widths = [max(len(r[i]) for r in rows) for i in range(3)]
        return "\n".join(
            f"{r[0].ljust(widths[0])}  {r[1].rjust(widths[1])}  {r[2].rjust(widths[2])}"
            for r in rows
        )

    def __missing__(self, key):
        if isinstance(key, str) and key.startswith(".") and dict.__contains__(self, key[1:]):
            return dict.__getitem__(self, key[1:])
        raise KeyError(key)

    def __contains__(self, key) -> bool:
        return dict.__contains__(self, key) or (
            isinstance(key, str) and key.startswith(".") and dict.__contains__(self, key[1:])
        )

    def get(self, key, default=None):
        """``self[key]`` when present (old key paths included), else ``default``."""
        return self[key] if key in self else default


def parameter_covariance(
    problem: FitProblem,
    theta: Theta,
    states: States,
    weights: PerTrajectory | None = None,
    *,
    hold_weak: bool = False,
) -> Float[Array, "theta theta"]:
    """Laplace covariance ``S⁻¹`` of the flat, unconstrained θ at the end point (x, θ).

    Args:
        problem: the fit problem (data, split system, prior).
        theta: (P,) θ̂ in the problem's unconstrained coordinates.
        states: (B, T, n) x̂, one trajectory per trajectory of ``problem.data``.
        weights: (B,) trajectory weights; 0 excludes a trajectory (default: all ones).
        hold_weak: when ``S`` is not positive definite, hold the weakly determined entries (the
            ones the warning names) at their estimates and return the covariance of the rest,
            conditional on them, with NaN in the held entries' rows and columns — instead of NaN
            everywhere. (Still all NaN, with the warning, if the rest is singular too.)

    Returns:
        The (P, P) covariance; all NaN, with a warning, when ``S`` is not positive definite.
        Learned noise scales (:class:`ceemx.LaplaceEM`) are held fixed in ``S`` (the rest is
        conditional on them) and get the Gaussian Fisher variance σ²/(2N) of a scale estimated
        from N residuals, uncorrelated with the rest (the Fisher information of a Gaussian is
        block-diagonal between means and scales); NaN for full Cholesky factors.
        See the module docstring for when it is valid. Not vmappable (the warning is host-side);
        the compiled core is :func:`schur_complement`.
    """
    # the bookkeeping on the host in NumPy (op by op in JAX, each compiled a program per shape)
    dtype = np.dtype(theta.dtype)
    if weights is None:
        weights = as_jax(np.ones(states.shape[0], np.dtype(states.dtype)))
    noise, noise_var = _noise_variances(problem, theta, weights)
    keep = np.where(noise, 0.0, 1.0).astype(dtype)
    cov, ok, weak = _laplace(problem, theta, states, weights, as_jax(keep))
    held = np.zeros_like(noise)
    weak = np.asarray(weak)
    if not bool(ok) and hold_weak and weak.any() and not (weak | noise).all():
        held = weak & ~noise
        keep = np.where(noise | held, 0.0, 1.0).astype(dtype)
        cov, ok, weak = _laplace(problem, theta, states, weights, as_jax(keep))
        if bool(ok):
            flagged = [n for n, w in zip(_names(problem), np.asarray(held), strict=True) if w]
            warn(_HELD.format(which=", ".join(flagged)))
    if not bool(ok):
        flagged = [n for n, w in zip(_names(problem), np.asarray(weak), strict=True) if w]
        which = f" (weakly determined: {', '.join(flagged)})" if flagged else ""
        warn(_NOT_PD.format(which=which))
    return _assemble(cov, as_jax(noise), as_jax(held), as_jax(noise_var))


@program(runs=Runs.ONCE)  # on the host: one program, where op by op it compiled four small ones
def _assemble(cov, noise, held, noise_var):
    """The covariance: 0 in the noise rows/columns, NaN in the held ones, noise variances added."""
    cov = jnp.where(noise[:, None] | noise[None, :], 0.0, cov)
    cov = jnp.where(held[:, None] | held[None, :], jnp.nan, cov)
    return cov + jnp.diag(jnp.where(noise, noise_var, 0.0))


def _noise_variances(
    problem: FitProblem, theta: Theta, weights: PerTrajectory
) -> tuple[np.ndarray, np.ndarray]:
    """``(is_noise, var)`` over θ: which entries are learned noise, and their variances.

    For Gaussian noise the Fisher information is block-diagonal between the mean parameters and
    the scales, and a scale σ estimated from N residuals has variance σ²/(2N) (a scalar scale
    shared by d components: N·d residuals); the scale is the model's
    :meth:`ceemx.AbstractNoise.scale_parameters`. Entries of other noise leaves (full covariance
    factors, CholeskyGaussian) get NaN: no per-entry formula is given. Other entries:
    ``is_noise`` False, ``var`` 0.
    """
    system = problem.build(theta)
    data = problem.data
    w = np.where(np.asarray(weights) > 0, np.asarray(weights), 0.0)
    dtype = np.dtype(theta.dtype)
    flags = jtu.tree_map(lambda leaf: np.zeros(np.shape(leaf), dtype), problem.template)
    var = flags
    counts = {
        "process_noise": np.full(system.state_dim, w.sum() * (data.num_steps - 1)),
        "obs_noise": np.einsum("b,btm->m", w, np.asarray(data.mask, float)),
    }
    for field, count in counts.items():
        if not problem.trains(field):
            continue
        noise = getattr(system, field)
        sub = getattr(flags, field)
        flags = eqx.tree_at(
            lambda t, f=field: getattr(t, f), flags, jtu.tree_map(np.ones_like, sub)
        )
        nan = jtu.tree_map(lambda a: np.full_like(a, np.nan), sub)
        var = eqx.tree_at(lambda t, f=field: getattr(t, f), var, nan)
        scale = noise.scale_parameters() if noise.is_gaussian else None
        if scale is not None:
            scale = np.asarray(scale, dtype)
            n_res = count.sum() if scale.ndim == 0 else count
            v = scale**2 / (2.0 * np.asarray(np.maximum(n_res, 1.0), dtype))
            var = eqx.tree_at(lambda t, f=field: getattr(t, f).scale_parameters(), var, v)
    return _ravel(flags, dtype) > 0, _ravel(var, dtype)


def _ravel(tree, dtype) -> np.ndarray:
    """``ravel_pytree(tree)[0]`` of a tree of NumPy leaves, in NumPy (the same order)."""
    return np.concatenate([np.ravel(a) for a in jtu.tree_leaves(tree)] + [np.zeros(0, dtype)])


def evidence_function(
    problem: FitProblem,
    theta: Theta,
    states: States,
    weights: PerTrajectory | None = None,
    smoother=None,
) -> Callable[[np.ndarray], float]:
    """``offset ↦ ℓ(θ + offset)``, the Laplace log-evidence Σ_b w_b log p(y_b | θ + offset).

    Each value is a MAP smoothing from ``states`` and the log-determinant of its Gauss–Newton
    matrix (:func:`ceemx.inference.posterior.gaussian_posterior`); ``smoother`` (``None``: an
    LM smoother at ``rtol=1e-14``) with its numbers traced, so that every θ runs one program.
    """
    from ceemx.inference.posterior import gaussian_posterior
    from ceemx.inference.smoother import LMSmoother
    from ceemx.lib.tree import trace_numbers

    if weights is None:
        weights = jnp.ones(states.shape[0], states.dtype)
    smoother = trace_numbers(LMSmoother(rtol=1e-14) if smoother is None else smoother, states.dtype)
    w = np.where(np.asarray(weights) > 0, np.asarray(weights), 0.0)
    th0 = np.asarray(theta, dtype=np.float64)

    def ell(offset: np.ndarray) -> float:
        th = jnp.asarray(th0 + offset, theta.dtype)
        post = gaussian_posterior(smoother, problem.build(th), states, problem.data)
        return float(np.sum(w * np.asarray(post.log_evidence)))

    return ell


def stencil_hessian(f: Callable[[np.ndarray], float], h: np.ndarray) -> np.ndarray:
    """The (P, P) Hessian of ``f`` at offset 0 by central differences with steps ``h``.

    ``f`` takes an offset from the point; 2P² + 1 evaluations (the diagonal from three points,
    each off-diagonal entry from four).
    """
    P = h.size
    f0 = f(np.zeros(P))
    eye = np.eye(P)
    H = np.zeros((P, P))
    for i in range(P):
        ei = h[i] * eye[i]
        H[i, i] = (f(ei) - 2.0 * f0 + f(-ei)) / h[i] ** 2
        for j in range(i):
            ej = h[j] * eye[j]
            H[i, j] = H[j, i] = (f(ei + ej) - f(ei - ej) - f(-ei + ej) + f(-ei - ej)) / (
                4.0 * h[i] * h[j]
            )
    return H


def evidence_covariance(
    problem: FitProblem,
    theta: Theta,
    states: States,
    weights: PerTrajectory | None = None,
    smoother=None,
    *,
    rel_step: float = 1e-3,
) -> Float[Array, "theta theta"]:
    """Inverse observed information of the Laplace log-evidence ℓ(θ) ≈ Σ_b log p(y_b | θ).

    The covariance of a (Laplace-) EM estimate: the states are integrated out, so it accounts for
    the states being unknown (the Schur complement of :func:`parameter_covariance` holds the noise
    fixed and treats the states as parameters). ℓ is evaluated by a MAP smoothing and the
    log-determinant of the Gauss–Newton matrix
    (:func:`ceemx.inference.posterior.gaussian_posterior`)
    at each θ of a central-difference stencil (steps ``rel_step·max(|θ_i|, 0.01)``), from the
    given states; 2P² + 1 smoothings for P parameters, each compiled once. Learned noise scales
    are included like any other entry of θ.

    Returns:
        The (P, P) covariance; all NaN, with a warning, when −∇²ℓ is not positive definite
        (not at a maximum, or a parameter is not identifiable).
    """
    th0 = np.asarray(theta, dtype=np.float64)
    P = th0.size
    h = rel_step * np.maximum(np.abs(th0), 0.01)
    H = stencil_hessian(evidence_function(problem, theta, states, weights, smoother), h)
    info = -0.5 * (H + H.T)
    try:
        chol = np.linalg.cholesky(info)
        cov = np.linalg.inv(info) if np.all(np.isfinite(chol)) else None
    except np.linalg.LinAlgError:
        cov = None
    if cov is None:
        warn(
            "The evidence covariance of θ is NaN: the negative Hessian of the Laplace "
            "log-evidence is not positive definite. Either the fit did not converge to a maximum "
            "or a parameter is not identifiable from the data; fix or drop such parameters "
            "(`trainable`) or add a prior (`log_prior`)."
        )
        return jnp.full((P, P), jnp.nan, theta.dtype)
    return jnp.asarray(0.5 * (cov + cov.T), theta.dtype)


def natural_jacobian(problem: FitProblem, theta: Theta) -> Float[Array, " theta"]:
    """(P,) diagonal of d natural / dθ: each leaf's ``constraint.forward`` derivative."""
    return problem.natural_jacobian(theta)


def natural_covariance(
    problem: FitProblem, theta: Theta, covariance: Float[Array, "theta theta"]
) -> Float[Array, "theta theta"]:
    """Delta method: ``J Cov Jᵀ`` with ``J = diag(`` :func:`natural_jacobian` ``)``."""
    j = natural_jacobian(problem, theta)
    if is_concrete(j) and is_concrete(covariance):  # NumPy on the host: no program per shape
        jh = np.asarray(j)
        return as_jax(jh[:, None] * np.asarray(covariance) * jh[None, :])
    return j[:, None] * covariance * j[None, :]


def standard_errors(
    problem: FitProblem, theta: Theta, covariance: Float[Array, "theta theta"]
) -> Any:
    """Natural-unit standard errors as a pytree like the system.

    Returns:
        The system's structure with each trainable leaf replaced by its standard errors (same
        shape) and ``None`` at every other leaf.
    """
    _, unravel = ravel_pytree(problem.template)
    se = jnp.sqrt(jnp.diagonal(natural_covariance(problem, theta, covariance)))
    return unravel(se)


def standard_errors_by_name(
    problem: FitProblem, theta: Theta, covariance: Float[Array, "theta theta"]
) -> dict[str, tuple[float, float]]:
    """``name → Estimate(estimate, std_error)`` per entry of θ, both in natural units.

    Names as written (:meth:`FitProblem.parameter_names`); a :class:`NamedEstimates`, so the key
    paths of earlier versions (``.A[0,0]``) still look up.
    """
    values = problem.natural(theta)  # natural values, in θ order
    se = np.sqrt(np.diagonal(np.asarray(natural_covariance(problem, theta, covariance))))
    return NamedEstimates(
        (n, Estimate(float(v), float(s)))
        for n, v, s in zip(_names(problem), np.asarray(values), se, strict=True)
    )


def fit_covariance(
    result: Any, natural: bool = False, *, hold_weak: bool = False
) -> Float[Array, "theta theta"]:
    """:meth:`ceemx.FitResult.covariance`: the covariance the fit's solver declares.

    ``"evidence"`` (``AbstractFitSolver.uncertainty``; :class:`ceemx.LaplaceEM`):
    :func:`evidence_covariance` with the solver's E-step smoother; ``"certainty-equivalent"``:
    :func:`parameter_covariance`.
    """
    problem, theta, states, weights = end_point(result)
    if result.solver.uncertainty == "evidence":
        smoother = getattr(result.solver, "smoother", None)
        cov = evidence_covariance(problem, theta, states, weights, smoother)
    else:
        cov = parameter_covariance(problem, theta, states, weights, hold_weak=hold_weak)
    return natural_covariance(problem, theta, cov) if natural else cov


def fit_standard_errors(result: Any) -> Any:
    """:meth:`ceemx.FitResult.standard_errors`: :func:`standard_errors` of its covariance."""
    problem, theta, _, _ = end_point(result)
    return standard_errors(problem, theta, result.covariance())


def fit_parameter_estimates(result: Any) -> dict[str, tuple[float, float]]:
    """:meth:`ceemx.FitResult.parameter_estimates`: :func:`standard_errors_by_name`."""
    problem, theta, _, _ = end_point(result)
    return standard_errors_by_name(problem, theta, result.covariance())
