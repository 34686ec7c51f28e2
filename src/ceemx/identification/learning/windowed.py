"""Minibatches of time for the learning step: a learner run on windows of the records.

A long single record (B = 1, T = 25 000) gives a first-order learner no minibatches: every
gradient is a pass over all T steps. :class:`WindowedLearner` cuts the records into windows of
``window`` transitions at the current smoothed states
(:class:`~ceemx.identification.learning.learning_problem.WindowedLearningProblem`, whose sum over
windows is the record's −J) and runs its inner learner — typically
``OptaxLearner(optax.adam(1e-3), steps=..., batch_size=...)``, whose minibatches are then
windows of time — so a learning step of thousands of weights costs ``steps`` small gradients.
"""

from __future__ import annotations

from typing import Any

from jaxtyping import PRNGKeyArray

from ceemx.identification.learning.learners import AbstractLearner, LearnInfo
from ceemx.identification.learning.learning_problem import (
    AbstractLearningProblem,
    LearningProblem,
    windowed,
)
from ceemx.infra.options import check_int
from ceemx.lib.typing import Theta

__all__ = ["WindowedLearner"]


class WindowedLearner(AbstractLearner):
    """Run ``learner`` on windows of ``window`` transitions of the records (module notes).

    Attributes:
        learner: the inner learner (a first-order one: the windowed problem has no Gauss–Newton
            form), e.g. ``OptaxLearner(optax.adam(1e-3), steps=200, batch_size=8)``.
        window: transitions per window (≥ 1; longer than the record: one window).
    """

    learner: AbstractLearner
    window: int

    def __check_init__(self):
        if not isinstance(self.learner, AbstractLearner):
            raise TypeError(
                f"`learner` must be a ceemx learner; got {type(self.learner).__name__}."
            )
        check_int("window", self.window, 1)

    def init(self, theta: Theta, key: PRNGKeyArray) -> Any:
        """The inner learner's state."""
        return self.learner.init(theta, key)

    def run(
        self, problem: AbstractLearningProblem, theta: Theta, state: Any
    ) -> tuple[Theta, Any, LearnInfo]:
        """The inner learner's step on the windowed problem."""
        if not isinstance(problem, LearningProblem):
            raise TypeError(
                "WindowedLearner cuts a certainty-equivalent learning problem (fixed states); got "
                f"{type(problem).__name__}."
            )
        return self.learner.run(windowed(problem, self.window), theta, state)
