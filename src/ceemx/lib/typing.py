"""Array shapes: the jaxtyping dimension names used across ceemx, and aliases for common arrays.

Annotations name their axes with jaxtyping (``Float[Array, "B T n"]``); one name means one size
throughout a call (the tests check this at run time with jaxtyping and beartype). The names:

=========== ======================================================================================
``B``       trajectories in a batch
``T``       time steps of a trajectory (``T-1``: its transitions)
``n``       state dimension, x_t ∈ Rⁿ
``m``       observation dimension, y_t ∈ Rᵐ
``p``       input dimension, u_t ∈ Rᵖ (0 for a system without inputs)
``theta``   trainable parameters: the length of the flat vector θ
``d``       a noise model's residual dimension (``n`` for process noise, ``m`` for observations)
``K``       attractors of :class:`ceemx.systems.CoupledLorenz` (``n = 3K``)
``k``       a generic size in :mod:`ceemx.lib` (a small dense matrix's side, right-hand sides)
``Tn``      T·n, the side of the dense form of a block-tridiagonal matrix (tests, debugging)
``*batch``  any number of leading batch axes
``_``       an axis of any size, not checked (e.g. a minibatch of trajectories)
``""``      a scalar
=========== ======================================================================================

Parameters are ``theta``, never ``p``: ``p`` is always the input dimension. So the border of the
joint Gauss–Newton system, the cross-curvature of the states with the parameters, is
``Float[Array, "B T n theta"]``. In formulas and local variables the length of θ is ``P``.

Entry points that validate their arguments on the host (:func:`ceemx.smooth`, :func:`ceemx.fit`,
:class:`ceemx.Trajectories`) raise ``ValueError`` or ``TypeError`` naming the argument. They accept
any ``ArrayLike`` for arrays (their docstrings give the shapes) and are left out of the runtime
checks (:func:`no_type_check`), so that the tests see the errors users see; the functions they
call carry the annotations and are checked.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from jaxtyping import Array, Bool, Float, Int

__all__ = [
    "BoolScalar",
    "Inputs",
    "IntScalar",
    "ObservationMask",
    "Observations",
    "PerTrajectory",
    "Scalar",
    "State",
    "States",
    "Theta",
    "Trajectory",
    "no_type_check",
]

_F = TypeVar("_F", bound=Callable)

Scalar = Float[Array, ""]
"""A floating-point scalar (0-d array)."""

BoolScalar = Bool[Array, ""]
"""A boolean scalar (0-d array)."""

IntScalar = Int[Array, ""]
"""An integer scalar (0-d array)."""

State = Float[Array, " n"]
"""One state x_t."""

Trajectory = Float[Array, "T n"]
"""The states x_1, …, x_T of one trajectory."""

States = Float[Array, "B T n"]
"""The state trajectories of a batch."""

Observations = Float[Array, "B T m"]
"""Observations y of a batch."""

ObservationMask = Bool[Array, "B T m"]
"""Which entries of the observations are present."""

Inputs = Float[Array, "B T p"]
"""Inputs u of a batch (``p = 0`` without inputs)."""

PerTrajectory = Float[Array, " B"]
"""One number per trajectory (e.g. each trajectory's J_b)."""

Theta = Float[Array, " theta"]
"""The flat vector θ of the trainable parameters."""


def no_type_check(fn: _F) -> _F:
    """Leave a host-validating entry point out of the test suite's runtime type checks.

    jaxtyping's import hook (pytest's ``--jaxtyping-packages``) skips every function with a
    decorator named ``no_type_check``. Unlike :func:`typing.no_type_check`, this one leaves the
    annotations to static checkers (pyright). Use it only on entry points that check their own
    arguments and raise errors naming them.
    """
    return fn
