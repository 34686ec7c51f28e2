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
from ceemx.identification.analysis.evidence_search import (
    DECADE,
    LOG_RANGE,
    EvidenceSearch,
    decade_grid,
    moved,
)
from ceemx.identification.analysis.noise_check import interpolates, square_sums
from ceemx.identification.analysis.noise_floor import check_informative, flagged, with_floors
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
from ceemx.infra.options import check_bool, check_int
from ceemx.infra.policy import entry_point
from ceemx.infra.warn import warn
from ceemx.lib.results import RESULTS, codes
from ceemx.lib.tree import as_jax, trace_numbers
from ceemx.models.system import AbstractSystem

__all__ = [
    "NOISE_FIELDS",
    "NoiseEstimateWarning",
    "NoiseMoments",
    "estimate_noise",
    "noise_ratios",
    "residual_moments",
    "with_noise_from_moments",
]


#: how many times the search box may move by LOG_RANGE beyond the guess's (a factor e^48 ≈ 7e20
#: in all): raised above a scale at its upper edge, lowered when every scale is at its lower one
BOX_MOVES = 3


class NoiseMoments(eqx.Module):
    """Expected residual second moments under the Laplace posterior (module docs).

    Attributes:
        moments: the sums of :func:`ceemx.identification.noise_moments.noise_second_moments`
            (``dyn``, ``dyn_count``, ``obs_diag``, ``obs_count``, ``obs_full``, ...).
        states: (B, T, n) the MAP trajectories they were computed at.
        log_evidence: (B,) the Laplace log-evidence per trajectory at θ.
        ok: (B,) whether the posterior of each trajectory was finite (the others are left out).
        floored: the noise fields :func:`estimate_noise` held at a floor from the data, above
            the evidence's maximum (:mod:`~ceemx.identification.analysis.noise_floor`).
        degenerate: the noise fields whose evidence maximum lies at the degenerate boundary
            σ_v → 0, the states interpolating the data (held at the evidence's margin).
        at_edge: the noise fields whose estimate sits at an edge of the search box
            (guess·e^±12, moved up to :data:`BOX_MOVES` times where the data's scale lay beyond
            it): the evidence kept rising beyond it.
        notes: one sentence per floor or edge, with the numbers.
    """

    moments: dict[str, Array]
    states: Array
    log_evidence: Array
    ok: Array
    floored: tuple[str, ...] = eqx.field(static=True, default=())
    degenerate: tuple[str, ...] = eqx.field(static=True, default=())
    at_edge: tuple[str, ...] = eqx.field(static=True, default=())
    notes: tuple[str, ...] = eqx.field(static=True, default=())

    @property
    def process_covariance(self) -> np.ndarray:
        """(n, n) S_w: the mean expected process residual outer product."""
        return np.asarray(self.moments["dyn"]) / float(self.moments["dyn_count"])

    @property
    def evidence(self) -> float:
        """Σ_b of the Laplace log-evidence over the finite posteriors (−inf when none is)."""
        ok = np.asarray(self.ok)
        if not ok.any():
            return -np.inf
        with np.errstate(over="ignore"):  # terms of −1e300 (data far off the noise's scale)
            return float(np.sum(np.asarray(self.log_evidence)[ok]))

    @property
    def obs_variance(self) -> np.ndarray:
        """(m,) the mean expected squared observation residual per component (present samples)."""
        count = np.asarray(self.moments["obs_count"])
        return np.asarray(self.moments["obs_diag"]) / np.where(count > 0, count, 1.0)


def _moments(smoother: LMSmoother, system: AbstractSystem, x0, data: Trajectories):
    # The posterior, its cubature points and the moments as three programs, not one: the first
    # two are the programs Laplace EM, the covariance and the profiles compile for the same
    # system, and the posterior's compilation is the largest of a fit's.
    post = gaussian_posterior(smoother, system, x0, data)
    ok = codes(post.status) != codes(RESULTS.nonfinite)
    weights = as_jax(ok.astype(np.dtype(x0.dtype)))
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
    return NoiseMoments(moments, x_hat, log_ev, as_jax(ok))


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
    number of residuals of component i) — the statistic of the closed-form EM update, which
    creeps along the evidence's ridges (``docs/decisions.md``). So the scales are found by L-BFGS
    (SciPy, on the host; each evaluation one MAP smoothing and its posterior, warm-started).
    Where a scale → 0 the evidence goes flat (the output-error plateau) and L-BFGS stops; a
    decade step of each scale, and L-BFGS again from any that gains, finds the slope beyond.

    σ_v is held at or above floors from the data (:mod:`~.noise_floor`: a quantised y's
    quantum/√12; where the evidence does not fall as σ_v → 0, the largest σ_v within 1.92 nats of
    its maximum); a floor or an edge of the box (start·e^±12, moved by e¹² up to three times
    where the best sits at its upper edge or every scale at its lower one) is named in a warning.

    By default each noise model keeps its shape and learns one factor (its covariance times c²):
    the two factors of process and observation noise are what a guess gets wrong by orders of
    magnitude, and the evidence determines them well. ``per_component=True`` learns every scale
    of a :class:`DiagonalGaussian`; in a partially observed model the evidence is often flat
    along some of them, and at a θ far off the model error lands in whichever scale absorbs it
    best: use it at a fitted θ.

    Args:
        system: the model at the θ to estimate the noise for.
        data: B observed trajectories.
        states: start states of the first smoothing (``None``: as a fit starts).
        fields: which noise models to estimate (``"process_noise"``, ``"obs_noise"``: one, both).
        per_component: one factor per noise model (``False``) or one scale per component of
            each diagonal model (``True``; a full covariance still takes one factor).
        search: before L-BFGS, evaluate the factors on a grid of decades (10⁻³…10³ times the
            start; every combination for up to two factors, one factor at a time beyond) and
            start from the best point: a start far too loose in the process noise falls into
            the basin of the degenerate maximum σ_v → 0; the grid finds the other basin. Only
            when every field takes one factor (``per_component=False``). On
            long data (:func:`ceemx.identification.noise_moments.coarse_shape`: from 40 000
            time steps) the grid and a first L-BFGS run on their first 10 000 steps, then
            L-BFGS on all of them from there.
        max_evaluations: bound on the posterior evaluations of the L-BFGS refinement (≥ 1).
        smoother: the MAP smoother (default: Laplace EM's E-step smoother).

    Returns:
        ``(system, moments, evaluations)``: the system with the estimated noise, the moments
        under it and the number of posterior evaluations made (on all the data and its part).

    Raises:
        ValueError: for an unknown field, a noise model that is not Gaussian, an invalid
            ``max_evaluations``, data with no observation or whose observed outputs are all
            constant (no noise can be told from signal).
    """
    fields = _checked_options(system, fields, max_evaluations, per_component, search, smoother)
    inputs = prepare(system, data, states, identify=True)
    if fields:
        check_informative(inputs.data)
    out = estimate_noise_prepared(
        system,
        inputs.data,
        start_states(inputs),
        fields=fields,
        per_component=per_component,
        search=search,
        max_evaluations=max_evaluations,
        smoother=smoother,
    )
    if out[1].notes:
        warn("estimate_noise: " + "; ".join(out[1].notes) + ".", NoiseEstimateWarning)
    return out


class NoiseEstimateWarning(UserWarning):
    """A noise estimate held at a floor from the data, or sitting at an edge of its search box.

    The numbers are in the warning and in :attr:`NoiseMoments.notes`
    (:mod:`ceemx.identification.analysis.noise_floor`).
    """


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
    around: AbstractSystem | None = None,
) -> tuple[AbstractSystem, NoiseMoments, int]:
    """:func:`estimate_noise` of prepared data and states, its options checked: no checks.

    ``system`` as given (the estimate keeps its leaves; promoted for each evaluation).
    ``around``: an earlier estimate for a nearby θ, not degenerate (the noise rounds'): the grid
    then spans one decade either way of its factors, and each factor alone over the guess's
    seven decades with the others at the estimate's (23 points for two factors, not 49). The
    lines keep the grid's task, finding the basin that is not a collapsed one: an estimate at a
    θ still far off can lie in it without being flagged (Lorenz from a 100× tight guess: σ_v =
    1.5e-8 against 0.01, kept by a grid around it alone, where the evidence at σ_v = 0.05 is
    1.8 nats higher). The search box and the floors are the guess's as always.
    """
    fields = tuple(dict.fromkeys(fields))
    nm = moments_prepared(_promoted(system), data, states, smoother)
    if not fields:
        return system, nm, 1
    layout = _ScaleLayout(system, fields, bool(per_component))
    bounds = [(z - LOG_RANGE, z + LOG_RANGE) for z in layout.z0]
    full = _search(system, data, layout, nm, smoother, bounds, max_evaluations)
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
            searched = _search(system, part_data, layout, first, smoother, bounds, max_evaluations)
        grid = decade_grid(layout.z0)
        if around is not None:  # one decade around it, and each factor over the guess's decades
            grid = decade_grid(layout.z_of(around), 1) + _decade_lines(
                layout.z_of(around), layout.z0
            )
        for z in grid:
            searched.objective(z)
        if searched is not full:
            searched.climb(searched.best_z)
            part_evaluations = len(searched.cache)
        start = searched.best_z
    full.climb(start)
    for _ in range(BOX_MOVES):  # the data's scale beyond the guess's box (evidence_search.moved)
        beyond = moved(full)
        if beyond is None:
            break
        full = beyond
    if "obs_noise" in fields:  # the degenerate boundary σ_v → 0 (analysis.noise_floor)
        best = full.best_z
        states = full.best["nm"].states
        full = with_floors(full, layout, data, _interpolates(system, layout, data, best, states))
    z = full.best["z"]
    estimate = layout.system(system, z)
    stds = {f: _stds(getattr(estimate, f)) for f in NOISE_FIELDS}
    nm = flagged(full.best["nm"], layout, stds, z, full)
    return estimate, nm, len(full.cache) + part_evaluations


def _interpolates(system, layout, data: Trajectories, z: np.ndarray, states) -> bool:
    """Whether the MAP states at log-scales ``z`` interpolate the data.

    The noise check's criterion (:func:`~ceemx.identification.analysis.noise_check.interpolates`):
    the observation residuals' mean squared whitened value below 1e-4.
    """
    obs, _, _ = square_sums(_promoted(layout.system(system, z)), states, data)
    return interpolates(float(np.sum(np.asarray(obs))), float(np.sum(np.asarray(data.mask))))


def _decade_lines(z: np.ndarray, z0: np.ndarray) -> list[np.ndarray]:
    """Points: one entry of z at a time moved over the seven decades of ``z0``'s."""
    out = []
    for i in range(z.size):
        for step in DECADE * np.arange(-3.0, 4.0):
            point = z.copy()
            point[i] = z0[i] + step
            out.append(point)
    return out


def _search(system, data, layout, nm, smoother, bounds, max_evaluations) -> EvidenceSearch:
    """The evidence search over ``layout``'s log-scales of ``system`` on ``data``."""

    def evaluate(z, states):
        trial = _promoted(layout.system(system, z))
        return moments_prepared(trial, data, states, smoother)

    def gradient(z, m):
        return layout.gradient(layout.system(system, z), m)

    return EvidenceSearch(evaluate, gradient, layout.z0, nm, bounds, max_evaluations)


def _stds(noise) -> np.ndarray:
    return np.sqrt(np.diagonal(np.asarray(noise.covariance(), float)))


def _promoted(system: AbstractSystem) -> AbstractSystem:
    """The system's floating arrays in its working dtype (as :func:`ceemx.data.checks.prepare`)."""
    return promote_tree(system, system)


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
        #: the field of each entry of z
        self.entry_fields = [
            f for f, k in zip(self.fields, self.sizes, strict=True) for _ in range(max(k, 1))
        ]

    def z_of(self, other: AbstractSystem) -> np.ndarray:
        """The factors z (log, one per field) that scale this layout's noise to ``other``'s."""
        assert self.factors_only
        ratios = [
            np.mean(np.log(_stds(getattr(other, f)) / _stds(self.base[f]))) for f in self.fields
        ]
        return np.asarray(ratios, np.float64)

    def entries_of(self, field: str) -> list[int]:
        """The indices of z that scale ``field``."""
        return [i for i, f in enumerate(self.entry_fields) if f == field]

    def floor_z(self, i: int, floors: np.ndarray) -> float:
        """The smallest z_i at which every component it scales has std ≥ its floor (−inf: none).

        ``floors``: (d,) per component of the entry's field (NaN: no floor).
        """
        field = self.entry_fields[i]
        first = self.entries_of(field)[0]
        if self.sizes[self.fields.index(field)] and floors.size == len(self.entries_of(field)):
            wanted = floors[i - first : i - first + 1]  # one scale per component
            base = np.ones(1)
        else:  # a factor on the whole covariance (z = log c), or one scale shared by all
            wanted = floors
            noise = self.base[field]
            base = np.sqrt(np.diagonal(np.asarray(noise.covariance(), float)))
            if self.sizes[self.fields.index(field)]:  # a shared scale: z is its log
                base = base / float(np.asarray(noise.scale_parameters()))
        ok = np.isfinite(wanted) & (base > 0)
        return float(np.log(np.max(wanted[ok] / base[ok]))) if ok.any() else -np.inf

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
