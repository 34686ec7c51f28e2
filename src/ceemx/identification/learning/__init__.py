"""The learning step: θ given the smoothed states (paper Eq. 11)."""

from ceemx.identification.learning.expected import (
    ExpectedLearningProblem,
    expected_learning_problem,
)
from ceemx.identification.learning.gauss_newton_cg import (
    GaussNewtonCGLearner,
    gauss_newton_diagonal,
    gauss_newton_product,
)
from ceemx.identification.learning.learners import (
    AbstractLearner,
    LBFGSLearner,
    LearnInfo,
    LMLearner,
    NelderMeadLearner,
    OptaxLearner,
)
from ceemx.identification.learning.learning_problem import (
    AbstractLearningProblem,
    LearningProblem,
    WindowedLearningProblem,
    learning_problem,
    make_problem,
    windowed,
)
from ceemx.identification.learning.step import learn, run_learner
from ceemx.identification.learning.windowed import WindowedLearner

__all__ = [
    "AbstractLearningProblem",
    "ExpectedLearningProblem",
    "expected_learning_problem",
    "gauss_newton_diagonal",
    "gauss_newton_product",
    "AbstractLearner",
    "GaussNewtonCGLearner",
    "LBFGSLearner",
    "LMLearner",
    "LearnInfo",
    "LearningProblem",
    "NelderMeadLearner",
    "OptaxLearner",
    "WindowedLearner",
    "WindowedLearningProblem",
    "learn",
    "learning_problem",
    "make_problem",
    "run_learner",
    "windowed",
]
