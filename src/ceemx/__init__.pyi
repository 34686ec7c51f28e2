"""The public names of ``ceemx`` and the modules that define them: the one table.

Read twice: by type checkers and IDEs as the package's interface, and at run time by
``lazy_loader.attach_stub`` (``__init__.py``), which loads each module on first use (SPEC 1).
Each name is imported as ``name as name``, the stub form of a re-export.
"""

from . import (
    baselines as baselines,
)
from . import (
    data as data,
)
from . import (
    datasets as datasets,
)
from . import (
    evaluation as evaluation,
)
from . import (
    experiments as experiments,
)
from . import (
    identification as identification,
)
from . import (
    inference as inference,
)
from . import (
    infra as infra,
)
from . import (
    lib as lib,
)
from . import (
    models as models,
)
from . import (
    systems as systems,
)
from .data.info import (
    DataInfo as DataInfo,
)
from .data.trajectories import (
    Trajectories as Trajectories,
)
from .data.trajectories import (
    foh_inputs as foh_inputs,
)
from .data.trajectories import (
    simulate as simulate,
)
from .evaluation.early_stopping import (
    EarlyStopping as EarlyStopping,
)
from .evaluation.export import (
    export_simulate as export_simulate,
)
from .evaluation.export import (
    export_step as export_step,
)
from .evaluation.hybrid_selection import (
    HybridFit as HybridFit,
)
from .evaluation.hybrid_selection import (
    fit_hybrid as fit_hybrid,
)
from .evaluation.initial_state import (
    estimate_initial_state as estimate_initial_state,
)
from .evaluation.metrics import (
    BenchmarkScore as BenchmarkScore,
)
from .evaluation.metrics import (
    DynamicsErrorCallback as DynamicsErrorCallback,
)
from .evaluation.metrics import (
    FitTimer as FitTimer,
)
from .evaluation.metrics import (
    benchmark_score as benchmark_score,
)
from .evaluation.metrics import (
    is_monotone as is_monotone,
)
from .evaluation.plots import (
    plot_benchmark as plot_benchmark,
)
from .evaluation.plots import (
    plot_resid as plot_resid,
)
from .evaluation.simulation import (
    free_run as free_run,
)
from .evaluation.simulation import (
    predict_k_step as predict_k_step,
)
from .identification.analysis.diagnostics import (
    ResidualDiagnostics as ResidualDiagnostics,
)
from .identification.analysis.diagnostics import (
    residual_diagnostics as residual_diagnostics,
)
from .identification.analysis.identifiability import (
    Identifiability as Identifiability,
)
from .identification.analysis.noise_check import (
    NoiseCheck as NoiseCheck,
)
from .identification.analysis.noise_check import (
    NoiseCheckWarning as NoiseCheckWarning,
)
from .identification.analysis.noise_estimate import (
    NoiseEstimateWarning as NoiseEstimateWarning,
)
from .identification.analysis.noise_estimate import (
    estimate_noise as estimate_noise,
)
from .identification.fitting.driver import (
    fit as fit,
)
from .identification.fitting.particle_fit import (
    particle_em as particle_em,
)
from .identification.fitting.result import (
    EpochInfo as EpochInfo,
)
from .identification.fitting.result import (
    FitResult as FitResult,
)
from .identification.hybrid_builder import (
    hybrid as hybrid,
)
from .identification.initialize import (
    perturb as perturb,
)
from .identification.initialize import (
    warm_start as warm_start,
)
from .identification.learning import (
    AbstractLearner as AbstractLearner,
)
from .identification.learning import (
    GaussNewtonCGLearner as GaussNewtonCGLearner,
)
from .identification.learning import (
    LBFGSLearner as LBFGSLearner,
)
from .identification.learning import (
    LearnInfo as LearnInfo,
)
from .identification.learning import (
    LMLearner as LMLearner,
)
from .identification.learning import (
    NelderMeadLearner as NelderMeadLearner,
)
from .identification.learning import (
    OptaxLearner as OptaxLearner,
)
from .identification.learning import (
    learn as learn,
)
from .identification.problem import (
    FitProblem as FitProblem,
)
from .identification.saving import (
    ModelInfo as ModelInfo,
)
from .identification.saving import (
    load as load,
)
from .identification.saving import (
    save as save,
)
from .identification.solvers import (
    AbstractFitSolver as AbstractFitSolver,
)
from .identification.solvers import (
    Alternating as Alternating,
)
from .identification.solvers import (
    FitState as FitState,
)
from .identification.solvers import (
    JointLM as JointLM,
)
from .identification.solvers import (
    LaplaceEM as LaplaceEM,
)
from .identification.solvers import (
    ParticleEM as ParticleEM,
)
from .inference.ekf import (
    FilterSolution as FilterSolution,
)
from .inference.ekf import (
    ekf as ekf,
)
from .inference.objective import (
    log_joint as log_joint,
)
from .inference.objective import (
    whitened_residuals as whitened_residuals,
)
from .inference.particle import (
    ParticleFilterSolution as ParticleFilterSolution,
)
from .inference.particle import (
    ffbsi as ffbsi,
)
from .inference.particle import (
    particle_filter as particle_filter,
)
from .inference.smoother import (
    LMSmoother as LMSmoother,
)
from .inference.smoother import (
    SmootherSolution as SmootherSolution,
)
from .inference.smoother import (
    smooth as smooth,
)
from .infra.compilation import (
    enable_compilation_cache as enable_compilation_cache,
)
from .lib.results import (
    RESULTS as RESULTS,
)
from .models import (
    AbstractConstraint as AbstractConstraint,
)
from .models import (
    AbstractContinuousSystem as AbstractContinuousSystem,
)
from .models import (
    AbstractGaussianNoise as AbstractGaussianNoise,
)
from .models import (
    AbstractNoise as AbstractNoise,
)
from .models import (
    AbstractSystem as AbstractSystem,
)
from .models import (
    CholeskyGaussian as CholeskyGaussian,
)
from .models import (
    DiagonalGaussian as DiagonalGaussian,
)
from .models import (
    Fixed as Fixed,
)
from .models import (
    GaussianPrior as GaussianPrior,
)
from .models import (
    GreaterThan as GreaterThan,
)
from .models import (
    Interval as Interval,
)
from .models import (
    LaplaceNoise as LaplaceNoise,
)
from .models import (
    LessThan as LessThan,
)
from .models import (
    Positive as Positive,
)
from .models import (
    StudentT as StudentT,
)
from .models import (
    Unconstrained as Unconstrained,
)
from .models import (
    param as param,
)
from .models import (
    with_noise as with_noise,
)
from .systems.hybrid import (
    Hybrid as Hybrid,
)
from .systems.hybrid import (
    HybridContinuous as HybridContinuous,
)
from .systems.learned_term import (
    LearnedTerm as LearnedTerm,
)
from .systems.learned_term import (
    weight_decay as weight_decay,
)

__version__: str
