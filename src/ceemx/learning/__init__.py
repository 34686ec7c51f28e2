"""The learning step: θ given the smoothed states (paper Eq. 11)."""

from .expected import ExpectedLearningProblem, expected_learning_problem
from .learners import (
    AbstractLearner,
    LBFGSLearner,
    LearnInfo,
    LMLearner,
    NelderMeadLearner,
    OptaxLearner,
)
from .problem import AbstractLearningProblem, LearningProblem, learning_problem, make_problem
from .step import learn, run_learner

__all__ = [
    "AbstractLearningProblem",
    "ExpectedLearningProblem",
    "expected_learning_problem",
    "AbstractLearner",
    "LBFGSLearner",
    "LMLearner",
    "LearnInfo",
    "LearningProblem",
    "NelderMeadLearner",
    "OptaxLearner",
    "learn",
    "learning_problem",
    "make_problem",
    "run_learner",
]
