"""ceemx: certainty-equivalent EM for partially observed nonlinear dynamical systems, in JAX.

Two layers: :mod:`ceemx.lib` holds the maths that knows nothing of EM (block-tridiagonal and
arrowhead solves, the Levenberg–Marquardt driver, status codes); the rest composes it into the
user-facing layer — systems, data, the objective, smoothers, learners, fit solvers and the one
:func:`fit` driver.
"""

from importlib.metadata import PackageNotFoundError, version

from . import evaluate, inference, initialize, lib, report, systems
from .data import Trajectories, simulate
from .driver import EpochInfo, FitResult, fit, particle_em
from .evaluate import DynamicsErrorCallback, FitTimer, is_monotone
from .inference import ParticleFilterSolution, ffbsi, particle_filter
from .initialize import perturb, warm_start
from .learning import (
    AbstractLearner,
    LBFGSLearner,
    LearnInfo,
    LMLearner,
    NelderMeadLearner,
    OptaxLearner,
    learn,
)
from .lib.results import RESULTS
from .models import (
    AbstractContinuousSystem,
    AbstractGaussianNoise,
    AbstractNoise,
    AbstractSystem,
    CholeskyGaussian,
    DiagonalGaussian,
    GaussianPrior,
    StudentT,
    with_noise,
)
from .objective import log_joint, whitened_residuals
from .problem import FitProblem
from .smoothing import LMSmoother, SmootherSolution, smooth
from .solvers import AbstractFitSolver, Alternating, FitState, JointLM, ParticleEM

try:
    __version__ = version("ceemx")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = [
    "RESULTS",
    "AbstractContinuousSystem",
    "AbstractFitSolver",
    "AbstractGaussianNoise",
    "AbstractLearner",
    "AbstractNoise",
    "AbstractSystem",
    "Alternating",
    "CholeskyGaussian",
    "DiagonalGaussian",
    "DynamicsErrorCallback",
    "EpochInfo",
    "FitProblem",
    "FitResult",
    "FitState",
    "FitTimer",
    "GaussianPrior",
    "JointLM",
    "LBFGSLearner",
    "LMLearner",
    "LMSmoother",
    "LearnInfo",
    "NelderMeadLearner",
    "OptaxLearner",
    "ParticleEM",
    "ParticleFilterSolution",
    "SmootherSolution",
    "StudentT",
    "Trajectories",
    "evaluate",
    "ffbsi",
    "fit",
    "inference",
    "initialize",
    "is_monotone",
    "learn",
    "lib",
    "log_joint",
    "particle_em",
    "particle_filter",
    "perturb",
    "report",
    "simulate",
    "smooth",
    "systems",
    "warm_start",
    "whitened_residuals",
    "with_noise",
]
