"""The options of one :func:`ceemx.fit` call, checked before any compute."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any, Literal

import jax
import numpy as np
from jax.sharding import Mesh

from ceemx.data.sharding import resolve_devices
from ceemx.identification.fitting.health import OUTLIER_OPTIONS
from ceemx.identification.solvers.alternating import Alternating
from ceemx.identification.solvers.base import AbstractFitSolver
from ceemx.infra.options import check_key

__all__ = ["NOISE_OPTIONS", "FitOptions", "fit_options"]

#: ``fit(..., noise=...)``: fit at the system's noise, or learn its two factors from the data
#: (``None``: learned on the path the library chooses without a solver, else fixed)
NOISE_OPTIONS = (None, "fixed", "learn")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Everything :func:`ceemx.fit` was asked besides the system and the data (see its docs).

    Attributes:
        solver: the fit solver (``fit`` without one: :class:`ceemx.Alternating` for the checks
            here; the default path puts each stage's solver in its place).
        mesh: the devices the batch is split over (``None``: no placement).
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

    @property
    def spread(self) -> bool:
        """Whether the data are spread over several processes' devices."""
        return self.mesh is not None and self.mesh.is_multi_process


def fit_options(
    *, solver, noise, outliers, max_epochs, key, devices, checkpoint, **rest
) -> FitOptions:
    """The checked :class:`FitOptions` (``rest``: the options with nothing to check here).

    Raises:
        ValueError, TypeError: naming the option, before any compute.
    """
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
    return int(max_epochs)
