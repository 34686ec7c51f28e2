"""System and noise models."""

from .noise import (
    AbstractGaussianNoise,
    AbstractNoise,
    CholeskyGaussian,
    DiagonalGaussian,
    StudentT,
)
from .system import (
    AbstractContinuousSystem,
    AbstractSystem,
    GaussianPrior,
    float_dtype,
    rk4_step,
    with_noise,
)

__all__ = [
    "AbstractContinuousSystem",
    "AbstractGaussianNoise",
    "AbstractNoise",
    "AbstractSystem",
    "CholeskyGaussian",
    "DiagonalGaussian",
    "GaussianPrior",
    "StudentT",
    "float_dtype",
    "rk4_step",
    "with_noise",
]
