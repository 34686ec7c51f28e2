"""ceemx: certainty-equivalent EM for partially observed nonlinear dynamical systems, in JAX.

The package reads as the pipeline, one folder a stage (a lower folder never imports a higher one;
``.ci/check_imports.py`` enforces it): :mod:`ceemx.lib` (maths that knows nothing of EM) and
:mod:`ceemx.infra` (checkpoints, compilation cache, threads) at the bottom; :mod:`ceemx.models`,
:mod:`ceemx.data`, :mod:`ceemx.systems`, :mod:`ceemx.datasets` (what goes in);
:mod:`ceemx.inference` (state estimators at fixed θ); :mod:`ceemx.identification` (θ: the fit
driver, its solvers and learners); :mod:`ceemx.evaluation` (simulation, prediction, scores,
reports); :mod:`ceemx.baselines`, :mod:`ceemx.experiments` and the CLI on top.

``import ceemx`` is light: the names below load their modules on first use (PEP 562), so the
``ceemx`` command can install its interrupt handler and answer ``--help`` before JAX is imported.
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the eager imports, for type checkers and IDEs
    from ceemx import datasets, lib, systems
    from ceemx.data.trajectories import Trajectories, foh_inputs, simulate
    from ceemx.evaluation import metrics as evaluate
    from ceemx.evaluation import plots, prediction, report, simulation
    from ceemx.evaluation.early_stopping import EarlyStopping
    from ceemx.evaluation.metrics import (
        BenchmarkScore,
        DynamicsErrorCallback,
        FitTimer,
        benchmark_score,
        is_monotone,
    )
    from ceemx.evaluation.plots import plot_benchmark, plot_resid
    from ceemx.evaluation.simulation import estimate_initial_state, free_run, predict_k_step
    from ceemx.identification import initialize
    from ceemx.identification.diagnostics import ResidualDiagnostics, residual_diagnostics
    from ceemx.identification.driver import EpochInfo, FitResult, fit, particle_em
    from ceemx.identification.hybrid_builder import hybrid
    from ceemx.identification.identifiability import Identifiability
    from ceemx.identification.initialize import perturb, warm_start
    from ceemx.identification.learning import (
        AbstractLearner,
        GaussNewtonCGLearner,
        LBFGSLearner,
        LearnInfo,
        LMLearner,
        NelderMeadLearner,
        OptaxLearner,
        learn,
    )
    from ceemx.identification.noise import estimate_noise
    from ceemx.identification.noise_check import NoiseCheck, NoiseCheckWarning
    from ceemx.identification.problem import FitProblem
    from ceemx.identification.solvers import (
        AbstractFitSolver,
        Alternating,
        FitState,
        JointLM,
        LaplaceEM,
        ParticleEM,
    )
    from ceemx.inference import ekf as filtering
    from ceemx.inference import particle as inference
    from ceemx.inference.ekf import FilterSolution, ekf
    from ceemx.inference.objective import log_joint, whitened_residuals
    from ceemx.inference.particle import ParticleFilterSolution, ffbsi, particle_filter
    from ceemx.inference.smoother import LMSmoother, SmootherSolution, smooth
    from ceemx.infra.compilation import enable_compilation_cache
    from ceemx.lib.results import RESULTS
    from ceemx.models import (
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
    from ceemx.systems.hybrid import Hybrid, HybridContinuous, LearnedTerm, weight_decay

#: module names of the flat layout before the folders, kept as attributes (``ceemx.report``, ...)
_MODULES = {
    "checkpoint": ".infra.checkpoint",
    "compilation": ".infra.compilation",
    "driver": ".identification.driver",
    "evaluate": ".evaluation.metrics",
    "filtering": ".inference.ekf",
    "health": ".identification.health",
    "initialize": ".identification.initialize",
    "learning": ".identification.learning",
    "objective": ".inference.objective",
    "plots": ".evaluation.plots",
    "prediction": ".evaluation.prediction",
    "problem": ".identification.problem",
    "report": ".evaluation.report",
    "runtime": ".infra.runtime",
    "sharding": ".data.sharding",
    "simulation": ".evaluation.simulation",
    "smoothing": ".inference.smoother",
    "solvers": ".identification.solvers",
    "uncertainty": ".identification.uncertainty",
}

#: public name -> the module that defines it (loaded on first access)
_LAZY = {
    "AbstractConstraint": ".models",
    "AbstractContinuousSystem": ".models",
    "AbstractFitSolver": ".identification.solvers",
    "AbstractGaussianNoise": ".models",
    "AbstractLearner": ".identification.learning",
    "AbstractNoise": ".models",
    "AbstractSystem": ".models",
    "Alternating": ".identification.solvers",
    "BenchmarkScore": ".evaluation.metrics",
    "CholeskyGaussian": ".models",
    "DiagonalGaussian": ".models",
    "DynamicsErrorCallback": ".evaluation.metrics",
    "EarlyStopping": ".evaluation.early_stopping",
    "EpochInfo": ".identification.driver",
    "FilterSolution": ".inference.ekf",
    "FitProblem": ".identification.problem",
    "FitResult": ".identification.driver",
    "FitState": ".identification.solvers",
    "FitTimer": ".evaluation.metrics",
    "Fixed": ".models",
    "GaussNewtonCGLearner": ".identification.learning",
    "GaussianPrior": ".models",
    "GreaterThan": ".models",
    "Hybrid": ".systems.hybrid",
    "HybridContinuous": ".systems.hybrid",
    "Identifiability": ".identification.identifiability",
    "Interval": ".models",
    "JointLM": ".identification.solvers",
    "LaplaceEM": ".identification.solvers",
    "LBFGSLearner": ".identification.learning",
    "LMLearner": ".identification.learning",
    "LMSmoother": ".inference.smoother",
    "LearnInfo": ".identification.learning",
    "LearnedTerm": ".systems.hybrid",
    "LessThan": ".models",
    "NelderMeadLearner": ".identification.learning",
    "NoiseCheck": ".identification.noise_check",
    "NoiseCheckWarning": ".identification.noise_check",
    "OptaxLearner": ".identification.learning",
    "ParticleEM": ".identification.solvers",
    "ParticleFilterSolution": ".inference.particle",
    "Positive": ".models",
    "RESULTS": ".lib.results",
    "ResidualDiagnostics": ".identification.diagnostics",
    "SmootherSolution": ".inference.smoother",
    "StudentT": ".models",
    "Trajectories": ".data.trajectories",
    "Unconstrained": ".models",
    "benchmark_score": ".evaluation.metrics",
    "ekf": ".inference.ekf",
    "enable_compilation_cache": ".infra.compilation",
    "estimate_initial_state": ".evaluation.simulation",
    "estimate_noise": ".identification.noise",
    "ffbsi": ".inference.particle",
    "fit": ".identification.driver",
    "foh_inputs": ".data.trajectories",
    "free_run": ".evaluation.simulation",
    "hybrid": ".identification.hybrid_builder",
    "is_monotone": ".evaluation.metrics",
    "learn": ".identification.learning",
    "log_joint": ".inference.objective",
    "param": ".models",
    "particle_em": ".identification.driver",
    "particle_filter": ".inference.particle",
    "perturb": ".identification.initialize",
    "plot_benchmark": ".evaluation.plots",
    "plot_resid": ".evaluation.plots",
    "predict_k_step": ".evaluation.simulation",
    "residual_diagnostics": ".identification.diagnostics",
    "simulate": ".data.trajectories",
    "smooth": ".inference.smoother",
    "warm_start": ".identification.initialize",
    "weight_decay": ".systems.hybrid",
    "whitened_residuals": ".inference.objective",
    "with_noise": ".models",
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is not None:
        value = getattr(import_module(module, __name__), name)
    elif name in _MODULES:
        value = import_module(_MODULES[name], __name__)
    else:
        try:  # a subpackage or module: ceemx.datasets, ceemx.inference, ...
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
    "EarlyStopping",
    "EpochInfo",
    "FilterSolution",
    "FitProblem",
    "FitResult",
    "FitState",
    "FitTimer",
    "Fixed",
    "GaussNewtonCGLearner",
    "GaussianPrior",
    "GreaterThan",
    "Hybrid",
    "HybridContinuous",
    "Identifiability",
    "Interval",
    "JointLM",
    "LaplaceEM",
    "LBFGSLearner",
    "LMLearner",
    "LMSmoother",
    "LearnInfo",
    "LearnedTerm",
    "LessThan",
    "NelderMeadLearner",
    "NoiseCheck",
    "NoiseCheckWarning",
    "OptaxLearner",
    "ParticleEM",
    "ParticleFilterSolution",
    "Positive",
    "RESULTS",
    "ResidualDiagnostics",
    "SmootherSolution",
    "StudentT",
    "Trajectories",
    "Unconstrained",
    "benchmark_score",
    "datasets",
    "ekf",
    "enable_compilation_cache",
    "estimate_initial_state",
    "estimate_noise",
    "evaluate",
    "ffbsi",
    "filtering",
    "fit",
    "foh_inputs",
    "free_run",
    "hybrid",
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
    "plot_benchmark",
    "plot_resid",
    "plots",
    "predict_k_step",
    "prediction",
    "residual_diagnostics",
    "report",
    "simulate",
    "simulation",
    "smooth",
    "systems",
    "warm_start",
    "weight_decay",
    "whitened_residuals",
    "with_noise",
]
