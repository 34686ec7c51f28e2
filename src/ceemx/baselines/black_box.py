"""A black-box model in one call: N4SID → CE-EM linear refinement → neural state space.

:func:`black_box` is the route for a record without physics: an affine linear model by N4SID
(:func:`~ceemx.baselines.sid.fit_affine_sid`), refined by CE-EM for simulation
(:func:`~ceemx.baselines.sid.refine_linear`), then a learned term added to its transition and
trained by CE-EM from the linear model's states (:func:`ceemx.hybrid`): x⁺ = A x + B [u; 1] +
N(x, u). Each model is returned as it reads the records as measured
(:class:`~ceemx.systems.constant_input.ConstantInput` supplies the constant channel), so it is
scored, simulated, saved and exported on the raw inputs.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from jaxtyping import PRNGKeyArray

from ceemx.baselines.sid import fit_affine_sid, refine_linear, with_constant_input
from ceemx.data.trajectories import Trajectories
from ceemx.evaluation.early_stopping import EarlyStopping
from ceemx.identification.fitting.driver import fit
from ceemx.identification.fitting.result import FitResult
from ceemx.identification.hybrid_builder import hybrid
from ceemx.identification.solvers.joint import JointLM
from ceemx.infra.options import check_bool
from ceemx.lib.typing import no_type_check
from ceemx.systems.constant_input import ConstantInput
from ceemx.systems.learned_term import weight_decay

__all__ = ["BlackBox", "black_box"]


@dataclasses.dataclass(frozen=True)
class BlackBox:
    """What :func:`black_box` identified; every ``system`` here takes the raw inputs.

    Attributes:
        system: the neural state-space model (the refined linear model plus the learned term).
        linear: the CE-EM refined linear model.
        n4sid: N4SID's affine model.
        result: the neural fit (:class:`ceemx.FitResult`; its ``system`` and ``data`` read the
            constant channel: ``result.system`` is ``system.inner``).
        linear_result: the linear refinement's fit.
    """

    system: ConstantInput
    linear: ConstantInput
    n4sid: ConstantInput
    result: FitResult
    linear_result: FitResult


def _count(name: str, value, low: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"`{name}` must be an integer >= {low}; got {value!r}.")
    return value


def _check(data, validation, n_init, progress, **counts) -> None:
    """Refuse :func:`black_box`'s arguments before any compute (messages name them)."""
    for name, value in (("data", data), ("validation", validation)):
        if value is not None and not isinstance(value, Trajectories):
            raise TypeError(f"`{name}` must be a ceemx.Trajectories; got {type(value).__name__}.")
    for name, value in counts.items():
        _count(name, value)
    if progress is not None:
        check_bool("progress", progress)
    if validation is not None and n_init is None:
        raise ValueError("`validation` needs `n_init`, the records' initial-state window.")


@no_type_check  # checks its arguments itself, with messages naming them
def black_box(
    data: Trajectories,
    *,
    state_dim: int,
    width: int = 16,
    depth: int = 1,
    linear_epochs: int = 100,
    max_epochs: int = 60,
    validation: Trajectories | None = None,
    n_init: int | None = None,
    patience: int = 5,
    key: PRNGKeyArray | None = None,
    progress: bool | None = None,
) -> BlackBox:
    """N4SID → CE-EM linear model → neural state space, each taking the raw inputs (module notes).

    Args:
        data: the training records, as measured (p inputs; complete records, as N4SID needs).
        state_dim: the model order n.
        width: the learned term's hidden width.
        depth: its number of hidden layers.
        linear_epochs: joint iterations of the linear refinement.
        max_epochs: joint iterations of the neural fit (with ``validation``: at most).
        validation: held-out records as measured: the neural fit stops when their free-run
            RMSE stops improving and keeps its best epoch (:class:`ceemx.EarlyStopping`).
        n_init: the validation records' initial-state window (required with ``validation``).
        patience: epochs without improvement before stopping (with ``validation``).
        key: PRNG key of the learned term's hidden layers (default ``PRNGKey(0)``).
        progress: the fits' progress display (``ceemx.fit``'s).

    Returns:
        A :class:`BlackBox`: ``system`` (neural), ``linear``, ``n4sid`` — each a
        :class:`~ceemx.systems.constant_input.ConstantInput` that reads the raw inputs — and the
        two fits.

    Raises:
        TypeError, ValueError: bad arguments (named), before any compute; what a stage refuses.

    Example:
        >>> bb = ceemx.baselines.black_box(train, state_dim=2)  # doctest: +SKIP
        >>> ceemx.benchmark_score(bb.system, test, 50)  # the raw test record  # doctest: +SKIP
    """
    _check(data, validation, n_init, progress, state_dim=state_dim, width=width, depth=depth)
    for name, value in (("linear_epochs", linear_epochs), ("max_epochs", max_epochs)):
        _count(name, value)
    _count("patience", patience)
    train = with_constant_input(data)
    n4sid = fit_affine_sid(data, state_dim=state_dim)
    linear = refine_linear(n4sid, train, max_epochs=linear_epochs)
    neural = hybrid(linear.system, train, states=linear.states, width=width, depth=depth, key=key)
    stopper = None
    if validation is not None:
        assert n_init is not None
        stopper = EarlyStopping(
            with_constant_input(validation), n_init, patience=patience, start=neural
        )
    result = fit(
        neural,
        train,
        jnp.asarray(linear.states),
        solver=JointLM(),
        trainable=neural.trainable("both"),
        log_prior=weight_decay,
        max_epochs=max_epochs,
        callbacks=() if stopper is None else (stopper,),
        diagnose=False,
        progress=progress,
    )
    if stopper is not None:
        result = stopper.restore(result)
    return BlackBox(
        system=ConstantInput(result.system),
        linear=ConstantInput(linear.system),
        n4sid=ConstantInput(n4sid),
        result=result,
        linear_result=linear,
    )
