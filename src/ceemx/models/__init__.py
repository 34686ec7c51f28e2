"""System and noise models, and parameter constraints."""

from ceemx.models.constraints import (
    AbstractConstraint,
    Fixed,
    GreaterThan,
    Interval,
    LessThan,
    Positive,
    Unconstrained,
    param,
)
from ceemx.models.laplace_noise import LaplaceNoise
from ceemx.models.noise import (
    AbstractGaussianNoise,
    AbstractNoise,
    CholeskyGaussian,
    DiagonalGaussian,
)
from ceemx.models.student_t import StudentT
from ceemx.models.system import (
    AbstractContinuousSystem,
    AbstractSystem,
    GaussianPrior,
    float_dtype,
    rk4_step,
    with_noise,
)

__all__ = [
    "AbstractConstraint",
    "AbstractContinuousSystem",
    "AbstractGaussianNoise",
    "AbstractNoise",
    "AbstractSystem",
    "CholeskyGaussian",
    "DiagonalGaussian",
    "Fixed",
    "GaussianPrior",
    "GreaterThan",
    "Interval",
    "LaplaceNoise",
    "LessThan",
    "Positive",
    "StudentT",
    "Unconstrained",
    "float_dtype",
    "param",
    "rk4_step",
    "with_noise",
]
