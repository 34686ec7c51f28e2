"""ceemx: certainty-equivalent EM for partially observed nonlinear dynamical systems, in JAX.

Two layers: :mod:`ceemx.lib` holds the maths that knows nothing of EM (block-tridiagonal and
arrowhead solves, the Levenberg–Marquardt driver, status codes); the rest composes it into the
user-facing layer — systems, data, the objective, smoothers, learners, fit solvers and the one
:func:`fit` driver.
"""

from importlib.metadata import PackageNotFoundError, version

from . import (
    datasets,
    evaluate,
    filtering,
    inference,
    initialize,
    lib,
    prediction,
    report,
    simulation,
    systems,
)
from .compilation import enable_compilation_cache
from .data import Trajectories, foh_inputs, simulate
from .driver import EpochInfo, FitResult, fit, particle_em
from .evaluate import BenchmarkScore, DynamicsErrorCallback, FitTimer, benchmark_score, is_monotone
from .filtering import FilterSolution, ekf
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
    AbstractConstraint,
    AbstractContinuousSystem,
    AbstractGaussianNoise,
    AbstractNoise,
    AbstractSystem,
    CholeskyGaussian,
    DiagonalGaussian,
    Fixed,
    GaussianPrior,
    GreaterThan,
    Interval,
    LessThan,
    Positive,
    StudentT,
    Unconstrained,
    param,
    with_noise,
)
from .objective import log_joint, whitened_residuals
from .problem import FitProblem
from .simulation import estimate_initial_state, free_run, predict_k_step
from .smoothing import LMSmoother, SmootherSolution, smooth
from .solvers import AbstractFitSolver, Alternating, FitState, JointLM, ParticleEM


def __getattr__(name: str):
    # ceemx.datasets imports SciPy's signal module (≈ 2 s): loaded on first use only.
    if name == "datasets":
        import importlib

        return importlib.import_module(".datasets", __name__)
    raise AttributeError(f"module 'ceemx' has no attribute {name!r}")


try:
    __version__ = version("ceemx")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = [
    "AbstractConstraint",
    "AbstractContinuousSystem",
    "AbstractFitSolver",
    "AbstractGaussianNoise",
    "AbstractLearner",
    "AbstractNoise",
    "AbstractSystem",
    "Alternating",
    "BenchmarkScore",
    "CholeskyGaussian",
    "DiagonalGaussian",
    "DynamicsErrorCallback",
    "EpochInfo",
    "FilterSolution",
    "FitProblem",
    "FitResult",
    "FitState",
    "FitTimer",
    "Fixed",
    "GaussianPrior",
    "GreaterThan",
    "Interval",
    "JointLM",
    "LBFGSLearner",
    "LMLearner",
    "LMSmoother",
    "LearnInfo",
    "LessThan",
    "NelderMeadLearner",
    "OptaxLearner",
    "ParticleEM",
    "ParticleFilterSolution",
    "Positive",
    "RESULTS",
    "SmootherSolution",
    "StudentT",
    "Trajectories",
    "Unconstrained",
    "benchmark_score",
    "datasets",
    "ekf",
    "enable_compilation_cache",
    "estimate_initial_state",
    "evaluate",
    "ffbsi",
    "filtering",
    "fit",
    "foh_inputs",
    "free_run",
    "inference",
    "initialize",
    "is_monotone",
    "learn",
    "lib",
    "log_joint",
    "param",
    "particle_em",
    "particle_filter",
    "perturb",
    "predict_k_step",
    "prediction",
    "report",
    "simulate",
    "simulation",
    "smooth",
    "systems",
    "warm_start",
    "whitened_residuals",
    "with_noise",
]
