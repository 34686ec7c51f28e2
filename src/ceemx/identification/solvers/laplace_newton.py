"""Newton's check and polish of a Laplace-EM end point (``LaplaceEM(polish=True)``).

EM's fixed point is the Laplace evidence's maximum only where the Gaussian E-step is exact (a
model linear in the state). Where the model is strongly curved in the state (Torricelli outflows,
√h), EM's fixed point lies a few hundredths of a nat beyond the maximum: its epochs then lower
the evidence (``LaplaceEM`` stops at the first such epoch and keeps the better point), and a
change-per-epoch rule either never holds or holds 0.1–0.25 standard errors from the maximum.

The polish tests the end point on the evidence ℓ(θ) (+ log-prior) itself: g by central
differences (steps :data:`GRADIENT_STEP`·max(|θ_i|, 0.01): ℓ is curved enough that the
covariance's steps of 1e-3 give gradients of the wrong size), H with
:func:`~ceemx.identification.analysis.uncertainty.evidence_covariance`'s stencil, and the Newton
decrement δ = ½ gᵀ(−H)⁻¹g — the evidence a Newton step would gain, and ½ s² for a step of s
standard errors (the evidence covariance (−H)⁻¹ as the metric). δ ≤ :data:`POLISH_DECREMENT`
certifies the end point (gradient small in the covariance's metric, −H positive definite:
first- and second-order optimality checked directly); otherwise a Newton step (or half of one)
is kept where the evidence rises by at least half the gain the quadratic model predicts, at most
:data:`POLISH_STEPS` times, then the test again. Where −H is not positive definite the end point
is no maximum the test can certify, and EM's verdict stands.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import jax.numpy as jnp
import numpy as np

from ceemx.identification.analysis.uncertainty import evidence_function, stencil_hessian
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import FitState, participating_sum
from ceemx.identification.solvers.laplace_qn import log_prior_value

if TYPE_CHECKING:
    from ceemx.identification.solvers.laplace import LaplaceEM

__all__ = [
    "GRADIENT_STEP",
    "POLISH_DECREMENT",
    "POLISH_MAX_PARAMETERS",
    "POLISH_STEPS",
    "newton_polish",
]

#: the most θ entries polished: each test costs 2P² + 2P + 1 smoothings (the Hessian's stencil
#: and the gradient), 841 at P = 20 — about what the summary's evidence covariance costs once
POLISH_MAX_PARAMETERS = 20
#: nats: the Newton decrement that certifies an end point. δ = ½ s² for a distance of s standard
#: errors to the maximum (in the covariance's metric), so 1e-3 nats is s ≤ 0.045 — no interval's
#: end moves by a visible amount
POLISH_DECREMENT = 1e-3
#: the most Newton steps taken
POLISH_STEPS = 3
#: the gradient's central-difference step, relative to max(|θ_i|, 0.01): small enough that the
#: third derivative of a curved evidence does not bias it, large against the smoother's round-off
GRADIENT_STEP = 3e-5
#: the Hessian's relative step (``evidence_covariance``'s: the covariance is that matrix)
HESSIAN_STEP = 1e-3


def newton_polish(
    solver: LaplaceEM, problem: FitProblem, state: FitState
) -> tuple[FitState, bool | None, dict[str, Any]]:
    """(state, certified, record) of the polish from ``state`` (module notes).

    ``certified``: ``True`` when the last test's decrement was within :data:`POLISH_DECREMENT`,
    ``False`` when it was not after the steps allowed or no step raised the evidence, ``None``
    when no test could be made (θ too large or empty, −H not positive definite, the evidence not
    finite). ``state`` is the posterior at the last accepted θ (the given one when no step was
    kept). ``record`` holds ``newton_*`` keys and the ``log_evidence`` at the returned θ.
    """
    P = int(np.size(state.theta))
    if P == 0 or P > POLISH_MAX_PARAMETERS:
        return state, None, {}
    dtype = state.theta.dtype
    theta = np.asarray(state.theta, np.float64)
    start, e = state.states, None  # the last kept step's smoother start and posterior
    states = state.states
    decrements: list[float] = []
    steps, gain, certified, why = 0, 0.0, None, ""
    while True:
        ell = evidence_function(
            problem, jnp.asarray(theta, dtype), states, state.weights, solver.smoother
        )

        def f(offset, ell=ell, theta=theta):
            return ell(offset) + log_prior_value(problem, jnp.asarray(theta + offset, dtype))

        f0 = f(np.zeros(P))
        scale = np.maximum(np.abs(theta), 0.01)
        hg = GRADIENT_STEP * scale
        eye = np.eye(P)
        g = np.array([(f(hg[i] * eye[i]) - f(-hg[i] * eye[i])) / (2 * hg[i]) for i in range(P)])
        H = stencil_hessian(f, HESSIAN_STEP * scale)
        info = -0.5 * (H + H.T)
        d = _solve_pd(info, g)
        if d is None or not np.isfinite(f0):
            why = "the evidence's negative Hessian is not positive definite"
            break
        delta = 0.5 * float(g @ d)
        decrements.append(delta)
        if delta <= POLISH_DECREMENT:
            certified, why = True, "certified"
            break
        if steps == POLISH_STEPS:
            certified, why = False, f"decrement {delta:.3g} after {steps} steps"
            break
        kept = None
        for s in (1.0, 0.5):
            f_s = f(s * d)
            if np.isfinite(f_s) and f_s - f0 >= 0.5 * delta * (2 * s - s * s):
                kept = (s, f_s)
                break
        if kept is None:
            certified, why = False, "no Newton step raised the evidence"
            break
        theta = theta + kept[0] * d
        gain += kept[1] - f0
        steps += 1
        start = states
        e = solver._posterior(problem, jnp.asarray(theta, dtype), start, quiet=True)
        states = e.states
    record = {
        "newton_steps": steps,
        "newton_decrements": decrements,
        "newton_gain": gain,
        "newton_result": why,
    }
    if e is not None:  # a step was kept: the fit state of its posterior
        learner_state, _, _ = state.solver_state
        state = solver._state(problem, jnp.asarray(theta, dtype), e, start, learner_state)
    record["log_evidence"] = participating_sum(state.solver_state[1], state.weights)
    return state, certified, record


def _solve_pd(info: np.ndarray, g: np.ndarray) -> np.ndarray | None:
    """``info⁻¹ g`` by Cholesky; ``None`` when ``info`` is not positive definite or not finite."""
    if not np.all(np.isfinite(info)) or not np.all(np.isfinite(g)):
        return None
    try:
        c = np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        return None
    return np.linalg.solve(c.T, np.linalg.solve(c, g))
