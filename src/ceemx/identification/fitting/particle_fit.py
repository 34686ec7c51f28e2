"""``particle_em``: :func:`ceemx.fit` with :class:`ceemx.ParticleEM`, its options spelled out."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from jaxtyping import ArrayLike, PRNGKeyArray

from ceemx.data.trajectories import Trajectories
from ceemx.identification.fitting.driver import fit
from ceemx.identification.fitting.result import EpochInfo, FitResult
from ceemx.identification.solvers.particle_em import ParticleEM
from ceemx.lib.typing import no_type_check
from ceemx.models.system import AbstractSystem

__all__ = ["particle_em"]


@no_type_check  # validates its arguments through fit and ParticleEM
def particle_em(
    system: AbstractSystem,
    data: Trajectories,
    x_init: ArrayLike | None = None,
    *,
    n_particles: int = 100,
    n_smoothed: int = 10,
    learner=None,
    burn_in: int = 5,
    alpha: float = 0.7,
    memory: int = 10,
    initial=None,
    trainable=None,
    log_prior: Callable[[AbstractSystem], Any] | None = None,
    max_epochs: int = 50,
    callbacks: Sequence[Callable[[EpochInfo], Any]] = (),
    progress: bool | None = None,
    checkpoint: str | None = None,
    key: PRNGKeyArray | None = None,
    checkpoint_mismatch: str = "raise",
    outliers: str = "exclude",
    diagnose: bool = True,
    **options: Any,
) -> FitResult:
    """Particle EM (fully adapted particle filter, FFBSi, SAEM): ``fit`` with :class:`ParticleEM`.

    ``system``, ``data``, ``trainable``, ``log_prior``, ``max_epochs``, ``callbacks``,
    ``progress``, ``checkpoint``, ``key``, ``checkpoint_mismatch``, ``outliers`` and ``diagnose``
    are as for :func:`ceemx.fit`; ``x_init`` only sets the
    states reported before epoch 1. ``n_particles``, ``n_smoothed``, ``learner`` (``None``:
    Levenberg–Marquardt), ``burn_in``, ``alpha``, ``memory``, ``initial`` and further
    ``options`` (``proposal``, ``ess_threshold``, ``rho_theta``, ``rtol``, ``atol``) are the
    :class:`ceemx.ParticleEM` options.

    Returns:
        A :class:`ceemx.FitResult` whose history has :func:`ceemx.fit`'s keys plus
        ``ParticleEM.history_keys`` (the PF log-likelihood estimate and the SAEM objective per
        epoch among them); ``states`` are the means of the last epoch's FFBSi draws.
    """
    kwargs = dict(
        n_particles=n_particles,
        n_smoothed=n_smoothed,
        burn_in=burn_in,
        alpha=alpha,
        memory=memory,
        initial=initial,
        **options,
    )
    if learner is not None:
        kwargs["learner"] = learner
    return fit(
        system,
        data,
        x_init,
        solver=ParticleEM(**kwargs),
        trainable=trainable,
        log_prior=log_prior,
        max_epochs=max_epochs,
        callbacks=callbacks,
        progress=progress,
        checkpoint=checkpoint,
        key=key,
        checkpoint_mismatch=checkpoint_mismatch,  # pyright: ignore[reportArgumentType]
        outliers=outliers,
        diagnose=diagnose,
    )
