"""System and noise models."""

from .noise import (
    AbstractGaussianNoise,
    AbstractNoise,
    CholeskyGaussian,
    DiagonalGaussian,
    StudentT,
)
from .system import AbstractContinuousSystem, AbstractSystem, GaussianPrior, rk4_step

__all__ = [
    "AbstractContinuousSystem",
    "AbstractGaussianNoise",
    "AbstractNoise",
    "AbstractSystem",
    "CholeskyGaussian",
    "DiagonalGaussian",
    "GaussianPrior",
    "StudentT",
    "rk4_step",
]
