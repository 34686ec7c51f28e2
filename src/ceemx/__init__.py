"""ceemx: certainty-equivalent EM for partially observed nonlinear dynamical systems, in JAX."""

from importlib.metadata import PackageNotFoundError, version

from . import initialize, linalg, systems
from .data import Trajectories, simulate
from .em import EpochInfo, FitResult, fit
from .joint import JointLM
from .learning import (
    AbstractLearner,
    LBFGSLearner,
    LearnInfo,
    LMLearner,
    NelderMeadLearner,
    OptaxLearner,
    learn,
)
from .models import (
    AbstractContinuousSystem,
    AbstractGaussianNoise,
    AbstractNoise,
    AbstractSystem,
    CholeskyGaussian,
    DiagonalGaussian,
    GaussianPrior,
    StudentT,
)
from .objective import log_joint, whitened_residuals
from .smoothing import RESULTS, LMSmoother, SmootherSolution, smooth

try:
    __version__ = version("ceemx")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = [
    "RESULTS",
    "AbstractLearner",
    "EpochInfo",
    "FitResult",
    "JointLM",
    "LBFGSLearner",
    "LMLearner",
    "LearnInfo",
    "NelderMeadLearner",
    "OptaxLearner",
    "fit",
    "initialize",
    "learn",
    "AbstractContinuousSystem",
    "AbstractGaussianNoise",
    "AbstractNoise",
    "AbstractSystem",
    "CholeskyGaussian",
    "DiagonalGaussian",
    "GaussianPrior",
    "LMSmoother",
    "SmootherSolution",
    "StudentT",
    "Trajectories",
    "linalg",
    "log_joint",
    "simulate",
    "smooth",
    "systems",
    "whitened_residuals",
]
