"""The noise a record shows: realised residual second moments against the assumed noise model.

A fit's answer depends on the noise scales (they weight dynamics against observations in J). What
the data say about them is the EM noise update: under the Laplace posterior q = N(x̂, Σ̂) at θ
(:func:`ceemx.inference.posterior.gaussian_posterior`), the expected residual second moments

    S_w = mean_t E_q[w_t w_tᵀ],   w_t = x_{t+1} − f_θ(x_t, u_t),
    S_v = mean_t E_q[v_t v_tᵀ],   v_t = y_t − g_θ(x_t, u_t)  (present components only),

by cubature over the marginal and pairwise posteriors. The smoothed residuals alone (x = x̂) are
biased low — the states absorb part of the noise — and the posterior spread is exactly the part
they absorbed; with it, S equals the noise covariance in expectation at the truth (for a
linear-Gaussian model it is the exact EM statistic). The ratio of S to the assumed covariance per
component (whitened: diag L⁻¹ S L⁻ᵀ) is therefore ≈ 1 when the assumed noise is consistent with the
record, and it is the factor to multiply the assumed variance by when it is not.

- :func:`residual_moments` — S_w, S_v (and counts) at θ, from the given start states.
- :func:`noise_ratios` — the per-component ratios realised / assumed.
- :func:`with_noise_from_moments` — the system with its Gaussian noise set to S (the closed-form
  M-step of Laplace EM; same classes and leaf shapes).
- :func:`estimate_noise` — that update iterated at a fixed θ: noise scales from the data, for a
  start (or a check) that does not depend on a guess.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ceemx.data.checks import Prepared, prepare, promote_tree
from ceemx.data.trajectories import Trajectories
from ceemx.identification.initialize import warm_start_states
from ceemx.identification.learning.expected import cubature_points
from ceemx.identification.noise_moments import (
    NOISE_FIELDS,
    coarse_shape,
    noise_second_moments,
    updated_noise,
)
from ceemx.inference.posterior import E_STEP_SMOOTHER, gaussian_posterior
from ceemx.inference.smoother import LMSmoother
from ceemx.infra.compilation import jit
from ceemx.infra.options import check_bool, check_int
from ceemx.infra.policy import entry_point
from ceemx.lib.results import RESULTS
from ceemx.lib.tree import trace_numbers
from ceemx.models.system import AbstractSystem

__all__ = [
    "NOISE_FIELDS",
    "NoiseMoments",
    "estimate_noise",
    "noise_ratios",
    "residual_moments",
    "with_noise_from_moments",
]


class NoiseMoments(eqx.Module):
    """Expected residual second moments under the Laplace posterior (module docs).

    Attributes:
        moments: the sums of :func:`ceemx.identification.noise_moments.noise_second_moments`
            (``dyn``, ``dyn_count``, ``obs_diag``, ``obs_count``, ``obs_full``, ...).
        states: (B, T, n) the MAP trajectories they were computed at.
        log_evidence: (B,) the Laplace log-evidence per trajectory at θ.
        ok: (B,) whether the posterior of each trajectory was finite (the others are left out).
    """

    moments: dict[str, Array]
    states: Array
    log_evidence: Array
    ok: Array

    @property
    def process_covariance(self) -> np.ndarray:
        """(n, n) S_w: the mean expected process residual outer product."""
        return np.asarray(self.moments["dyn"]) / float(self.moments["dyn_count"])

    @property
    def evidence(self) -> float:
        """Σ_b of the Laplace log-evidence over the finite posteriors (−inf when none is)."""
        ok = np.asarray(self.ok)
        return float(np.sum(np.asarray(self.log_evidence)[ok])) if ok.any() else -np.inf

    @property
    def obs_variance(self) -> np.ndarray:
        """(m,) the mean expected squared observation residual per component (present samples)."""
        count = np.asarray(self.moments["obs_count"])
        return np.asarray(self.moments["obs_diag"]) / np.where(count > 0, count, 1.0)


@jit
def _moments(smoother: LMSmoother, system: AbstractSystem, x0, data: Trajectories):
    post = gaussian_posterior(smoother, system, x0, data)
    ok = post.status != RESULTS.nonfinite
    weights = jnp.where(ok, 1.0, 0.0).astype(x0.dtype)
    points, pairs = cubature_points(post.states, post.covariances, post.cross)
    moments = noise_second_moments(system, points, pairs, data, weights)
    return moments, post.states, post.log_evidence, ok


def residual_moments(
    system: AbstractSystem,
    data: Trajectories,
    states: ArrayLike | None = None,
    *,
    smoother: LMSmoother | None = None,
) -> NoiseMoments:
    """Expected residual second moments at the system's θ under the Laplace posterior.

    Args:
        system: the model (θ and the assumed noise).
        data: B observed trajectories.
        states: (B, T, n) start of the MAP smoothing (``None``: least squares through the
            observation map and one smoothing pass, as a fit starts).
        smoother: the MAP smoother (default: Laplace EM's E-step smoother, rtol 1e-14).

    Returns:
        A :class:`NoiseMoments`; trajectories whose posterior is not finite are left out
        (``ok``).
    """
    inputs = prepare(system, data, states, identify=True)
    return moments_prepared(inputs.system, inputs.data, start_states(inputs), smoother)


def start_states(inputs: Prepared):
    """The states given with prepared inputs, else the warm start (as a fit starts)."""
    if inputs.states is not None:
        return inputs.states
    return warm_start_states(inputs.system, inputs.data)


def moments_prepared(
    system: AbstractSystem, data: Trajectories, states, smoother: LMSmoother | None = None
) -> NoiseMoments:
    """:func:`residual_moments` of prepared inputs and states (``ceemx.data.checks.prepare``)."""
    x0 = jnp.asarray(states)
    smoother = trace_numbers(E_STEP_SMOOTHER if smoother is None else smoother, x0.dtype)
    moments, x_hat, log_ev, ok = _moments(smoother, system, x0, data)
    return NoiseMoments(moments, x_hat, log_ev, ok)


def noise_ratios(system: AbstractSystem, nm: NoiseMoments) -> dict[str, np.ndarray]:
    """Realised / assumed variance per component: ``{"process_noise": (n,), "obs_noise": (m,)}``.

    Whitened by the assumed covariance where it is full
    (:meth:`ceemx.AbstractNoise.variance_ratios`); NaN for a noise model without a covariance, and
    for an observation component that is never observed.
    """
    out = {"process_noise": system.process_noise.variance_ratios(nm.process_covariance)}
    obs = system.obs_noise
    count = np.asarray(nm.moments["obs_count"])
    if obs.full_covariance:
        full = np.asarray(nm.moments["obs_full"]) / float(nm.moments["obs_full_count"])
        ratio = obs.variance_ratios(full)
    else:
        ratio = obs.variance_ratios(np.diag(nm.obs_variance))
    out["obs_noise"] = np.where(count > 0, ratio, np.nan)
    return out


def with_noise_from_moments(
    system: AbstractSystem, nm: NoiseMoments, fields: Sequence[str] = NOISE_FIELDS
) -> AbstractSystem:
    """The system with the noise models in ``fields`` set to the realised moments (closed form).

    Each model by its :meth:`ceemx.AbstractNoise.covariance_update`: a scalar
    :class:`~ceemx.DiagonalGaussian` scale stays scalar (the pooled variance); a per-component one
    gets one scale per component; a :class:`~ceemx.CholeskyGaussian` gets the full matrix. A
    component never observed keeps its scale.
    """
    for field in fields:
        noise = getattr(system, field)
        _check_closed_form(field, noise)
        new = updated_noise(noise, field, nm.moments)
        system = eqx.tree_at(lambda s, f=field: getattr(s, f), system, replace=new)
    return system


@entry_point  # BLAS threads and results as the policy says (ceemx.infra.policy)
def estimate_noise(
    system: AbstractSystem,
    data: Trajectories,
    states: ArrayLike | None = None,
    *,
    fields: Sequence[str] = NOISE_FIELDS,
    per_component: bool = False,
    search: bool = True,
    max_evaluations: int = 60,
    smoother: LMSmoother | None = None,
) -> tuple[AbstractSystem, NoiseMoments, int]:
    """Noise scales from the data at a fixed θ: the maximiser of the Laplace log-evidence.

    The noise enters the marginal likelihood log p(y | θ, σ), here its Laplace approximation
    (:func:`ceemx.inference.posterior.gaussian_posterior`), and its gradient in a log-scale is
    free once the expected residual moments are known: ∂/∂ log σ_i = N_i·(ratio_i − 1),
    ratio_i = E_q[r_i²]/σ_i² (:func:`noise_ratios`, whitened for a full covariance; N_i the
    number of residuals of component i) — the statistic of the closed-form EM update. EM itself
    creeps here: from too tight a process noise the states follow the dynamics, the observation
    noise absorbs the misfit, and both ratios sit near 1 while the evidence still rises by
    hundreds of nats along the ridge where process noise grows and observation noise shrinks.
    So the scales are found by L-BFGS (SciPy, on the host; each evaluation one MAP smoothing and
    its posterior, warm-started) on the log-evidence in log-scale, which follows such ridges.
    Where a scale → 0 the evidence goes flat (all the noise in the other model: the output-error
    plateau) and L-BFGS stops; a decade step of each scale from its answer, and L-BFGS again from
    any that gains, finds the slope beyond (up to three times).

    By default each noise model keeps its shape and learns one factor (its covariance times c²):
    the two factors of process and observation noise are what a guess gets wrong by orders of
    magnitude, and the evidence determines them well. ``per_component=True`` learns every scale
    of a :class:`DiagonalGaussian` instead — but in a partially observed model the evidence is
    often flat along some of them (noise on a hidden state that the record cannot tell from noise
    on its neighbour), and at a θ still far from the optimum the model error lands in whichever
    scale absorbs it best, so use it at a fitted θ.

    Args:
        system: the model at the θ to estimate the noise for.
        data: B observed trajectories.
        states: start states of the first smoothing (``None``: as a fit starts).
        fields: which noise models to estimate (``"process_noise"``, ``"obs_noise"``: one, both).
        per_component: one factor per noise model (``False``) or one scale per component of
            each diagonal model (``True``; a full covariance still takes one factor).
        search: before L-BFGS, evaluate the factors on a grid of decades (10⁻³…10³ times the
            start; every combination for up to two factors, one factor at a time beyond) and
            start from the best point. The evidence has a second, degenerate maximum — all noise
            in the process, the observations fitted exactly (σ_v → 0) — whose basin a start far
            too loose in the process noise falls into; the grid finds the other basin when it
            is higher. Only when every field takes one factor (``per_component=False``). On
            long data (:func:`ceemx.identification.noise_moments.coarse_shape`: from 40 000
            time steps) the grid and a first L-BFGS run on their first 10 000 steps, then
            L-BFGS on all of them from there.
        max_evaluations: bound on the posterior evaluations of the L-BFGS refinement (≥ 1).
        smoother: the MAP smoother (default: Laplace EM's E-step smoother).

    Returns:
        ``(system, moments, evaluations)``: the system with the estimated noise, the moments
        under it and the number of posterior evaluations made (on all the data and on their
        first part, together).

    Raises:
        ValueError: for an unknown field, a noise model that is not Gaussian, or an invalid
            ``max_evaluations``.
    """
    fields = _checked_options(system, fields, max_evaluations, per_component, search, smoother)
    inputs = prepare(system, data, states, identify=True)
    return estimate_noise_prepared(
        system,
        inputs.data,
        start_states(inputs),
        fields=fields,
        per_component=per_component,
        search=search,
        max_evaluations=max_evaluations,
        smoother=smoother,
    )


def _checked_options(system, fields, max_evaluations, per_component, search, smoother) -> tuple:
    """The distinct ``fields`` of :func:`estimate_noise`, checked with its other options."""
    fields = tuple(dict.fromkeys((fields,) if isinstance(fields, str) else fields))  # one name
    for field in fields:
        if field not in NOISE_FIELDS:
            raise ValueError(f"`fields` entries must be in {NOISE_FIELDS}; got {field!r}.")
        _check_closed_form(field, getattr(system, field))
    check_int("max_evaluations", max_evaluations, 1)
    check_bool("per_component", per_component)
    check_bool("search", search)
    if smoother is not None and not isinstance(smoother, LMSmoother):
        raise TypeError(f"`smoother` must be a ceemx.LMSmoother or None; got {smoother!r:.80}.")
    return fields


def _check_closed_form(field: str, noise) -> None:
    if not noise.learnable_in_closed_form:
        raise ValueError(
            f"`system.{field}` is {type(noise).__name__}: noise is estimated for noise models "
            "with a closed-form covariance update (`learnable_in_closed_form`: DiagonalGaussian "
            "or CholeskyGaussian) only."
        )


def estimate_noise_prepared(
    system: AbstractSystem,
    data: Trajectories,
    states,
    *,
    fields: Sequence[str] = NOISE_FIELDS,
    per_component: bool = False,
    search: bool = True,
    max_evaluations: int = 60,
    smoother: LMSmoother | None = None,
) -> tuple[AbstractSystem, NoiseMoments, int]:
    """:func:`estimate_noise` of prepared data and states, its options checked: no checks.

    ``system`` as given (the estimate keeps its leaves; promoted for each evaluation).
    """
    fields = tuple(dict.fromkeys(fields))
    nm = moments_prepared(_promoted(system), data, states, smoother)
    if not fields:
        return system, nm, 1
    layout = _ScaleLayout(system, fields, bool(per_component))
    bounds = [(z - _LOG_RANGE, z + _LOG_RANGE) for z in layout.z0]
    full = _EvidenceSearch(system, data, layout, nm, smoother, bounds, max_evaluations)
    start, part_evaluations = layout.z0, 0
    shape = coarse_shape(*nm.states.shape[:2])
    if search and layout.factors_only:
        searched = full
        if shape is not None:
            # long data: the grid and L-BFGS on their first part (the evidence's shape is the
            # same, its scale smaller), then L-BFGS on all of them from there
            b, t = shape
            part_data = data[:b].head(t)
            first = moments_prepared(_promoted(system), part_data, nm.states[:b, :t], smoother)
            searched = _EvidenceSearch(
                system, part_data, layout, first, smoother, bounds, max_evaluations
            )
        for z in _grid(layout.z0):
            searched.objective(z)
        if searched is not full:
            searched.climb(searched.best_z)
            part_evaluations = len(searched.cache)
        start = searched.best_z
    full.climb(start)
    best = full.best
    return layout.system(system, best["z"]), best["nm"], len(full.cache) + part_evaluations


def _promoted(system: AbstractSystem) -> AbstractSystem:
    """The system's floating arrays in its working dtype (as :func:`ceemx.data.checks.prepare`)."""
    return promote_tree(system, system)


class _EvidenceSearch:
    """−(Laplace log-evidence) of one data set in the log-scales z, its gradient, its best point.

    Each evaluation smooths from the best point's MAP states so far (warm), and is cached.
    """

    def __init__(self, system, data, layout, nm, smoother, bounds, max_evaluations):
        self.system, self.data, self.layout, self.smoother = system, data, layout, smoother
        self.bounds, self.max_evaluations = bounds, max_evaluations
        # |∂/∂ log σ| at which to stop: the evidence's curvature in a log-scale is ≈ 2N (N
        # residuals), so the gain still ahead, ≈ g²/4N, is then 1e-8 nat from N = 2 500 on
        # (the fixed 1e-2 of before below that, where it is ≤ 1e-5/N)
        self.steps = float(np.prod(nm.states.shape[:2]))
        self.gtol = 1e-2 * max(1.0, np.sqrt(self.steps / 2500.0))
        self.cache: dict[bytes, NoiseMoments] = {layout.z0.tobytes(): nm}
        self.best = {"f": -nm.evidence, "z": layout.z0.copy(), "nm": nm}

    @property
    def best_z(self) -> np.ndarray:
        """A copy of the best z so far."""
        return self.best["z"].copy()

    def objective(self, z):
        """(−evidence, its gradient in z) at z; 1e300 where the posterior is not finite."""
        key = z.tobytes()
        if key not in self.cache:
            trial = self.layout.system(self.system, z)
            states = self.best["nm"].states
            self.cache[key] = moments_prepared(_promoted(trial), self.data, states, self.smoother)
        m = self.cache[key]
        f = -m.evidence
        if not np.isfinite(f):
            return 1e300, np.zeros_like(z)
        if f < self.best["f"]:
            self.best.update(f=f, z=z.copy(), nm=m)
        return f, -self.layout.gradient(self.layout.system(self.system, z), m)

    def refine(self, z):
        """L-BFGS-B from z (SciPy, on the host), on the evidence per time step.

        Per time step, so that its first step (the gradient's length) is of the scales' order
        whatever the data's size; summed, it jumped to the bounds on a 10⁵-sample record.
        """
        from scipy.optimize import minimize

        def scaled(z):
            f, g = self.objective(z)
            return f / self.steps, g / self.steps

        minimize(
            scaled,
            z,
            jac=True,
            method="L-BFGS-B",
            bounds=self.bounds,
            options={
                "maxfun": self.max_evaluations,
                "ftol": 1e-10,
                "gtol": self.gtol / self.steps,
            },
        )

    def climb(self, z):
        """L-BFGS from z, then from any decade step of one scale that gains (a few times).

        L-BFGS stops where the evidence goes flat: a scale → 0 (all the noise in the other
        model: a whole output-error plateau) or → ∞. A decade either way of each scale from
        its answer finds the slope again where it lies beyond (a 10⁵-sample record: σ_w stuck
        at 3e-6, 300× below the evidence's maximum, 2 400 nats lower).
        """
        self.refine(z)
        for _ in range(_ESCAPES):
            f_before, z_best = self.best["f"], self.best_z
            for k in range(z_best.size):
                for step in (_DECADE, -_DECADE):
                    z = z_best.copy()
                    z[k] += step
                    if self.bounds[k][0] <= z[k] <= self.bounds[k][1]:
                        self.objective(z)
            if not self.best["f"] < f_before - 1e-9 * abs(f_before):
                return
            self.refine(self.best_z)


def _grid(z0: np.ndarray) -> list[np.ndarray]:
    """Points in decades of every factor (all combinations up to two factors, else one by one)."""
    steps = np.log(10.0) * np.arange(-3.0, 4.0)
    if z0.size <= 2:
        mesh = np.meshgrid(*[z + steps for z in z0], indexing="ij")
        return [np.array(p) for p in zip(*(m.ravel() for m in mesh), strict=True)]
    out = []
    for i in range(z0.size):
        for s in steps:
            z = z0.copy()
            z[i] += s
            out.append(z)
    return out


#: how far (in log-scale) from its start a scale may move in one estimate: a factor e^12 ≈ 1.6e5
_LOG_RANGE = 12.0
_DECADE = float(np.log(10.0))
#: restarts of L-BFGS from a decade step that found more evidence
_ESCAPES = 3


class _ScaleLayout:
    """The log-scales (or log-factors) of the noise models in ``fields`` as one flat vector z."""

    def __init__(self, system: AbstractSystem, fields: Sequence[str], per_component: bool):
        self.fields = tuple(fields)
        self.base = {f: getattr(system, f) for f in self.fields}
        self.sizes = []
        parts = []
        for f in self.fields:
            scale = self.base[f].scale_parameters()
            if per_component and scale is not None:
                scale = np.asarray(scale, float)
                self.sizes.append(scale.size)
                parts.append(np.log(scale).ravel())
            else:  # one factor on the whole covariance, z = log c (start 0)
                self.sizes.append(0)
                parts.append(np.zeros(1))
        self.z0 = np.concatenate(parts)
        self.factors_only = not any(self.sizes)

    def system(self, system: AbstractSystem, z: np.ndarray) -> AbstractSystem:
        i = 0
        for field, size in zip(self.fields, self.sizes, strict=True):
            noise = self.base[field]
            if size:
                old = jnp.asarray(noise.scale_parameters())
                scale = jnp.asarray(np.exp(z[i : i + size]).reshape(old.shape), old.dtype)
                new = noise.with_scale_parameters(scale)
                i += size
            else:
                new = noise.scaled(float(np.exp(z[i])))
                i += 1
            system = eqx.tree_at(lambda s, f=field: getattr(s, f), system, replace=new)
        return system

    def gradient(self, system: AbstractSystem, nm: NoiseMoments) -> np.ndarray:
        """∂ log-evidence / ∂ z: N_i·(ratio_i − 1) per component, summed for a factor."""
        ratios = noise_ratios(system, nm)
        obs_count = (
            np.full(system.obs_dim, float(nm.moments["obs_full_count"]))
            if system.obs_noise.full_covariance
            else np.asarray(nm.moments["obs_count"], float)
        )
        counts = {
            "process_noise": np.full(system.state_dim, float(nm.moments["dyn_count"])),
            "obs_noise": obs_count,
        }
        out = []
        for field, size in zip(self.fields, self.sizes, strict=True):
            g = counts[field] * np.nan_to_num(ratios[field] - 1.0)
            if size:
                scale = np.asarray(self.base[field].scale_parameters())
                out.append(np.atleast_1d(g.sum()) if scale.ndim == 0 else g.reshape(-1))
            else:
                out.append(np.atleast_1d(g.sum()))
        return np.concatenate(out)
