"""ceemx: certainty-equivalent EM for partially observed nonlinear dynamical systems, in JAX.

Two layers: :mod:`ceemx.lib` holds the maths that knows nothing of EM (block-tridiagonal and
arrowhead solves, the Levenberg–Marquardt driver, status codes); the rest composes it into the
user-facing layer — systems, data, the objective, smoothers, learners, fit solvers and the one
:func:`fit` driver.

``import ceemx`` is light: the names below load their modules on first use (PEP 562), so the
``ceemx`` command can install its interrupt handler and answer ``--help`` before JAX is imported.
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the eager imports, for type checkers and IDEs
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
    from .evaluate import (
        BenchmarkScore,
        DynamicsErrorCallback,
        FitTimer,
        benchmark_score,
        is_monotone,
    )
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
    from .solvers import (
        AbstractFitSolver,
        Alternating,
        FitState,
        JointLM,
        LaplaceEM,
        ParticleEM,
    )

#: public name -> the module that defines it (loaded on first access)
_LAZY = {
    "AbstractConstraint": ".models",
    "AbstractContinuousSystem": ".models",
    "AbstractFitSolver": ".solvers",
    "AbstractGaussianNoise": ".models",
    "AbstractLearner": ".learning",
    "AbstractNoise": ".models",
    "AbstractSystem": ".models",
    "Alternating": ".solvers",
    "BenchmarkScore": ".evaluate",
    "CholeskyGaussian": ".models",
    "DiagonalGaussian": ".models",
    "DynamicsErrorCallback": ".evaluate",
    "EpochInfo": ".driver",
    "FilterSolution": ".filtering",
    "FitProblem": ".problem",
    "FitResult": ".driver",
    "FitState": ".solvers",
    "FitTimer": ".evaluate",
    "Fixed": ".models",
    "GaussianPrior": ".models",
    "GreaterThan": ".models",
    "Interval": ".models",
    "JointLM": ".solvers",
    "LaplaceEM": ".solvers",
    "LBFGSLearner": ".learning",
    "LMLearner": ".learning",
    "LMSmoother": ".smoothing",
    "LearnInfo": ".learning",
    "LessThan": ".models",
    "NelderMeadLearner": ".learning",
    "OptaxLearner": ".learning",
    "ParticleEM": ".solvers",
    "ParticleFilterSolution": ".inference",
    "Positive": ".models",
    "RESULTS": ".lib.results",
    "SmootherSolution": ".smoothing",
    "StudentT": ".models",
    "Trajectories": ".data",
    "Unconstrained": ".models",
    "benchmark_score": ".evaluate",
    "ekf": ".filtering",
    "enable_compilation_cache": ".compilation",
    "estimate_initial_state": ".simulation",
    "ffbsi": ".inference",
    "fit": ".driver",
    "foh_inputs": ".data",
    "free_run": ".simulation",
    "is_monotone": ".evaluate",
    "learn": ".learning",
    "log_joint": ".objective",
    "param": ".models",
    "particle_em": ".driver",
    "particle_filter": ".inference",
    "perturb": ".initialize",
    "predict_k_step": ".simulation",
    "simulate": ".data",
    "smooth": ".smoothing",
    "warm_start": ".initialize",
    "whitened_residuals": ".objective",
    "with_noise": ".models",
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is not None:
        value = getattr(import_module(module, __name__), name)
    else:
        try:  # a subpackage or module: ceemx.datasets, ceemx.smoothing, ...
            value = import_module(f".{name}", __name__)
        except ModuleNotFoundError as e:
            if e.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


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
    "LaplaceEM",
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
