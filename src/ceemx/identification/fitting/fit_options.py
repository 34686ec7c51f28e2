"""The options of one :func:`ceemx.fit` call, checked before any compute.

:func:`fit_options` checks each option by itself (and the solver's own options again, as
``eqx.tree_at`` may have changed them unchecked); :func:`check_against_start` checks the solver's
tolerances and trust-region weights against the data, once the start's misfit is known: none may
be so large that the stopping rule cannot fail or the iterates cannot move.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any, Literal, cast

import jax
import numpy as np
from jax.sharding import Mesh

from ceemx.data.sharding import resolve_devices
from ceemx.identification.fitting.health import OUTLIER_OPTIONS
from ceemx.identification.solvers.alternating import Alternating
from ceemx.identification.solvers.base import AbstractFitSolver
from ceemx.infra.distributed import to_host
from ceemx.infra.options import (
    check_bool,
    check_callable,
    check_choice,
    check_int,
    check_key,
    check_path,
    recheck,
)

__all__ = [
    "CHECKPOINT_MISMATCH_OPTIONS",
    "NOISE_OPTIONS",
    "FitOptions",
    "check_against_start",
    "fit_options",
]

#: ``fit(..., noise=...)``: fit at the system's noise, or learn its two factors from the data
#: (``None``: learned on the path the library chooses without a solver, else fixed)
NOISE_OPTIONS = (None, "fixed", "learn")
#: ``fit(..., checkpoint_mismatch=...)``: on a checkpoint that cannot be resumed
CHECKPOINT_MISMATCH_OPTIONS = ("raise", "restart")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Everything :func:`ceemx.fit` was asked besides the system and the data (see its docs).

    Attributes:
        solver: the fit solver (``fit`` without one: :class:`ceemx.Alternating` for the checks
            here; the default path puts each stage's solver in its place).
        mesh: the devices the batch is split over (``None``: no placement).
        progress_label: which part of a longer fit this is, for the progress display
            (``"stage 1/2, noise round 2"``; ``""``: the whole fit).
        overrides: the per-fit constraints of ``fit(..., bounds=, fixed=)`` by leaf name
            (:mod:`ceemx.identification.fitting.overrides`).
    """

    solver: AbstractFitSolver
    trainable: Any = None
    log_prior: Callable[[Any], Any] | None = None
    max_epochs: int = 100
    callbacks: Sequence[Callable[[Any], Any]] = ()
    progress: bool | None = None
    checkpoint: str | None = None
    checkpoint_mismatch: Literal["raise", "restart"] = "raise"
    key: Any = None
    outliers: str = "exclude"
    mesh: Mesh | None = None
    diagnose: bool = True
    progress_label: str = ""
    overrides: tuple = ()

    @property
    def spread(self) -> bool:
        """Whether the data are spread over several processes' devices."""
        return self.mesh is not None and self.mesh.is_multi_process


def fit_options(
    *,
    solver,
    noise,
    outliers,
    max_epochs,
    key,
    devices,
    checkpoint,
    checkpoint_mismatch,
    callbacks,
    progress,
    diagnose,
    **rest,
) -> FitOptions:
    """The checked :class:`FitOptions` (``rest``: the options checked where they are read).

    Raises:
        ValueError, TypeError: naming the option, before any compute.
    """
    check_bool("diagnose", diagnose)
    check_bool("progress", progress, none=True)
    check_choice("checkpoint_mismatch", checkpoint_mismatch, CHECKPOINT_MISMATCH_OPTIONS)
    checkpoint = check_path("checkpoint", checkpoint, none=True)
    callbacks = _check_callbacks(callbacks)
    if noise not in NOISE_OPTIONS:
        raise ValueError(f"`noise` must be None, 'fixed' or 'learn'; got {noise!r}.")
    if noise == "learn":
        _check_noise_rounds(solver, checkpoint)
    if outliers not in OUTLIER_OPTIONS:
        raise ValueError(f"`outliers` must be one of {OUTLIER_OPTIONS}; got {outliers!r}.")
    solver = Alternating() if solver is None else solver
    if not isinstance(solver, AbstractFitSolver):
        raise TypeError(
            f"`solver` must be a fit solver such as ceemx.Alternating() or ceemx.JointLM(); "
            f"got {solver!r}."
        )
    recheck(solver)  # its options as constructed: eqx.tree_at skips __check_init__
    max_epochs = _check_max_epochs(max_epochs)
    if key is not None:
        check_key(key)
    mesh = resolve_devices(devices)
    if mesh is not None and mesh.is_multi_process and not solver.multi_process:
        raise ValueError(
            f"`devices` spans {jax.process_count()} processes: a multi-process fit runs "
            f"ceemx.JointLM or ceemx.Alternating; {type(solver).__name__} reads per-trajectory "
            "values on the host that are not gathered across processes. Fit it in one process "
            "(devices=None, or a mesh of jax.local_devices())."
        )
    return FitOptions(
        solver=solver,
        max_epochs=max_epochs,
        key=key,
        outliers=outliers,
        mesh=mesh,
        checkpoint=checkpoint,
        checkpoint_mismatch=checkpoint_mismatch,
        callbacks=callbacks,
        progress=progress,
        diagnose=diagnose,
        **rest,
    )


def _check_noise_rounds(solver, checkpoint) -> None:
    """What ``fit(..., noise="learn")`` refuses: solvers it does not wrap, checkpoints."""
    if solver is not None and not getattr(solver, "noise_rounds", False):
        raise ValueError(
            f"fit(..., noise='learn') alternates certainty-equivalent fits (Alternating, "
            f"JointLM) with noise estimates; {type(solver).__name__} is not one. LaplaceEM "
            "learns noise itself: pass trainable=lambda s: (..., s.process_noise, s.obs_noise)."
        )
    if checkpoint is not None:
        raise ValueError(
            "fit(..., noise='learn') runs several fits (one per noise round) and does not "
            "checkpoint; pass checkpoint=None, or learn the noise with "
            "ceemx.estimate_noise(...) first and fit with noise='fixed' and a checkpoint."
        )


def _check_max_epochs(max_epochs) -> int:
    if isinstance(max_epochs, bool) or not isinstance(max_epochs, int | np.integer):
        raise TypeError(f"`max_epochs` must be an int; got {max_epochs!r}.")
    if max_epochs < 0:
        raise ValueError(f"`max_epochs` must be >= 0; got {max_epochs}.")
    return cast(int, check_int("max_epochs", max_epochs, 0))


def _check_callbacks(callbacks) -> tuple[Callable[[Any], Any], ...]:
    """``callbacks`` as a tuple of callables; a single callable or a string is refused."""
    if (
        callable(callbacks)
        or isinstance(callbacks, str | bytes)
        or not isinstance(callbacks, Sequence)
    ):
        raise TypeError(
            f"`callbacks` must be a list or tuple of callables (e.g. [f] for one); got "
            f"{callbacks!r:.80}."
        )
    for i, callback in enumerate(callbacks):
        check_callable(f"callbacks[{i}]", callback)
    return tuple(callbacks)


def check_against_start(
    solver: AbstractFitSolver, misfit: float, n_residuals: float, theta, states
) -> None:
    """Refuse tolerances and trust-region weights that decide the fit before it starts.

    ``misfit`` is S₀ = −J − c at the start, ½‖whitened residuals‖² for Gaussian noise (summed
    over the trajectories taking part); ``n_residuals`` is their number of residual entries, N.

    - ``atol`` ≥ max(S₀, N/2): no epoch of a CE fit can raise J by more than the misfit left
      (J + c ≤ 0), and N/2 is the misfit expected at the truth: such a tolerance is met by the
      first epoch whatever it does.
    - a trust-region weight ρ (``rho_theta``; ``rho_x`` of the solver or its ``smoother``) with
      √(S₀/ρ) ≤ ε·max(1, |v|) for the largest entry v of what it holds (θ, unconstrained, or
      the states): every step beyond rounding would cost more than the whole misfit, so the
      iterates can never move and the fit stops at once.

    Raises:
        ValueError: naming the option, its limit and the start's misfit (before any epoch).
    """
    atol = float(getattr(solver, "atol", 0.0))
    atol_limit = max(misfit, 0.5 * n_residuals)
    if np.isfinite(atol_limit) and atol >= atol_limit:
        raise ValueError(
            f"`atol` = {atol:g} cannot fail: no epoch raises J by more than the misfit left "
            f"(½‖whitened residuals‖² = {misfit:.6g} at the start), nor by more than the "
            f"misfit expected at the truth ({0.5 * n_residuals:g}, half the {n_residuals:g} "
            "residual entries), so every epoch would meet it and the fit would stop at once, "
            f"'converged'. Use atol < {atol_limit:.6g} (the default 0 leaves the rule to rtol)."
        )
    smoother = getattr(solver, "smoother", None)
    weights = [
        ("rho_theta", getattr(solver, "rho_theta", None), theta, "θ", "it"),
        ("rho_x", getattr(solver, "rho_x", None), states, "the states", "they"),
        ("smoother.rho_x", getattr(smoother, "rho_x", None), states, "the states", "they"),
    ]
    for name, rho, held, what, pronoun in weights:
        if rho is None or not misfit > 0:
            continue
        rho = float(rho)
        values = to_host(held)
        scale = max(1.0, float(np.max(np.abs(values)))) if values.size else 1.0
        rounding = float(np.finfo(values.dtype).eps) * scale
        with np.errstate(divide="ignore"):
            reach = float(np.sqrt(misfit / rho)) if rho > 0 else np.inf
        if reach <= rounding:
            raise ValueError(
                f"`{name}` = {rho:g} holds {what} at the start: a step of length "
                f"√(S₀/{name}) = {reach:.3g} would already cost the whole misfit at the start "
                f"(S₀ = ½‖whitened residuals‖² = {misfit:.6g}), and that is below the rounding "
                f"of {what} ({rounding:.3g}), so {pronoun} could never move and the fit would "
                f"stop at once. Use {name} < {misfit / rounding**2:.3g}."
            )
