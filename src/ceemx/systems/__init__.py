"""Built-in systems."""

from .linear import LinearSystem
from .lorenz import (
    CoupledLorenz,
    coupling_mask,
    initial_states,
    random_coupling,
    random_observation_matrix,
)
from .neural import NeuralObservationSystem

__all__ = [
    "CoupledLorenz",
    "LinearSystem",
    "NeuralObservationSystem",
    "coupling_mask",
    "initial_states",
    "random_coupling",
    "random_observation_matrix",
]
