"""The learning step: θ given the smoothed states."""

from .learners import (
    AbstractLearner,
    LBFGSLearner,
    LearnInfo,
    LMLearner,
    NelderMeadLearner,
    OptaxLearner,
)
from .problem import LearningProblem, split_system, trainable_mask
from .step import learn

__all__ = [
    "AbstractLearner",
    "LBFGSLearner",
    "LMLearner",
    "LearnInfo",
    "LearningProblem",
    "NelderMeadLearner",
    "OptaxLearner",
    "learn",
    "split_system",
    "trainable_mask",
]
