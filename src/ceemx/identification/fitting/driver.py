"""``fit``: the one entry point that identifies θ and the states, with any fit solver.

It checks the options, prepares the inputs once (:func:`ceemx.data.checks.prepare`) and runs one
fit at the system's noise (:func:`~ceemx.identification.fitting.run.run_fit`: start, epochs,
finish) or rounds of them that learn the noise
(:func:`~ceemx.identification.fitting.noise_rounds.learn_noise`); without a solver, the stages
the library chooses from the problem (:mod:`~ceemx.identification.fitting.default_path`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

from jax.sharding import Mesh
from jaxtyping import ArrayLike, PRNGKeyArray

from ceemx.data.checks import prepare
from ceemx.data.trajectories import Trajectories
from ceemx.identification.fitting.default_path import fit_default, fit_named
from ceemx.identification.fitting.fit_options import fit_options
from ceemx.identification.fitting.overrides import with_overrides
from ceemx.identification.fitting.result import EpochInfo, FitResult
from ceemx.identification.fitting.start import require_observations
from ceemx.identification.solvers.base import AbstractFitSolver
from ceemx.infra.policy import entry_point
from ceemx.lib.typing import no_type_check
from ceemx.models.system import AbstractSystem

__all__ = ["fit"]

_INPUTS = ("system", "data", "x_init", "bounds", "fixed")


@entry_point  # BLAS threads and results as the policy says (ceemx.infra.policy)
@no_type_check  # validates its arguments: the options, then ceemx.data.checks.prepare
def fit(
    system: AbstractSystem,
    data: Trajectories,
    x_init: ArrayLike | None = None,
    *,
    solver: AbstractFitSolver | None = None,
    trainable=None,
    log_prior: Callable[[AbstractSystem], Any] | None = None,
    max_epochs: int = 100,
    callbacks: Sequence[Callable[[EpochInfo], Any]] = (),
    progress: bool | None = None,
    checkpoint: str | None = None,
    checkpoint_mismatch: Literal["raise", "restart"] = "raise",
    key: PRNGKeyArray | None = None,
    outliers: str = "exclude",
    devices: Literal["all"] | Mesh | None = None,
    diagnose: bool = True,
    noise: Literal["fixed", "learn"] | None = None,
    bounds: Mapping[str, tuple[float | None, float | None]] | None = None,
    fixed: Mapping[str, Any] | None = None,
) -> FitResult:
    """Identify θ and the state trajectories by maximising the CE-EM objective J(x, θ) (Eq. 9).

    Args:
        system: the model at its initial θ.
        data: B observed trajectories.
        x_init: (B, T, n) initial states (``None``: the solver's ``initial_states``, for the CE
            methods :func:`ceemx.warm_start`).
        solver: the method — :class:`ceemx.Alternating` (the paper's Algorithm 1),
            :class:`ceemx.JointLM`, :class:`ceemx.LaplaceEM` (learns noise covariances) or
            :class:`ceemx.ParticleEM`; its tolerances decide convergence. ``None`` (default):
            chosen from the problem (:mod:`~ceemx.identification.fitting.choice`): up to 200
            parameters, JointLM with the noise learned, then LaplaceEM in θ at that noise (the
            evidence's estimate and intervals, free of the CE bias); beyond, Alternating.
        trainable: which leaves learn (``None``: all model arrays except noise and prior; a
            callable ``where(system)`` or a boolean filter pytree). Noise models only with a
            solver that learns noise (:class:`ceemx.LaplaceEM`).
        log_prior: optional ``system -> log p(θ)``.
        max_epochs: bound on epochs (iterations of the solver).
        callbacks: called with an :class:`EpochInfo` after every epoch; a returned dict is merged
            into that epoch's history record; returning ``False`` stops the fit.
        progress: show a progress bar (``None``: only when stderr is a terminal).
        checkpoint: folder the state is written to atomically after every epoch, and resumed
            from when it holds a checkpoint of the same fit (``docs/guarantees.md``); held by
            this fit alone (a lock on its ``.lock`` file) until it returns.
        checkpoint_mismatch: for a checkpoint of another fit, corrupt or not finite: ``"raise"``
            a ``CheckpointError`` naming what differs, or ``"restart"`` (warn, overwrite it).
        key: PRNG key for stochastic solvers and learners (default ``PRNGKey(0)``).
        outliers: the start-of-fit health test (:mod:`ceemx.identification.fitting.health`):
            ``"exclude"`` (default) fits without the trajectories whose residuals are far
            outside the noise model (named in a warning and :attr:`FitResult.excluded`; status
            ``outlier``), ``"warn"`` only names them, ``"keep"`` skips the test.
        devices: data parallelism over the trajectories (:mod:`ceemx.data.sharding`): ``None``
            (default), ``"all"`` visible devices, or a 1-D :class:`jax.sharding.Mesh`; results
            agree with ``None`` to rounding (several processes: see ``docs/guarantees.md``).
        diagnose: the end-of-fit noise check (:attr:`FitResult.noise_check`; warns when the
            residuals and the assumed noise disagree by more than 2× in standard deviation).
        noise: ``"fixed"``: the system's noise models; ``"learn"``: one factor on each, CE fits
            alternated with the Laplace-evidence estimate until they settle (``noise_rounds``;
            ``max_epochs`` per round; no ``checkpoint``); ``None``: learned without a solver. The
            observation noise has floors from the data (``docs/guarantees.md``, "Learned noise").
        bounds: ``{name: (lower, upper)}`` (``None``: open), e.g. ``{"k": (0, 10)}``: learned
            inside them in this fit, narrowing the class's constraint (:mod:`~.overrides`).
        fixed: ``{name: value}`` (``None``: as it is), e.g. ``{"g": 9.81}``: held in this fit.

    Returns:
        A :class:`FitResult`.

    Raises:
        ValueError, TypeError: on invalid inputs or options, before any compute;
            :class:`ceemx.infra.checkpoint.CheckpointError` for an unwritable or busy
            ``checkpoint`` folder, or a checkpoint that cannot be resumed.

    Example:
        >>> result = ceemx.fit(guess, data, trainable=lambda s: s.rho)  # doctest: +SKIP
    """
    # every option, checked before any compute (the inputs are prepared next)
    options = fit_options(**{k: v for k, v in locals().items() if k not in _INPUTS})
    system, options = with_overrides(system, options, bounds, fixed)
    inputs = prepare(system, data, x_init, identify=True)
    require_observations(inputs.data)  # every solver, every noise mode: before any compute
    if solver is None:
        return fit_default(system, inputs, options, noise)
    return fit_named(system, inputs, options, noise)
