"""Built-in systems."""

from .benchmarks import CascadedTanks, CoupledDrives, Silverbox
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
    "CascadedTanks",
    "CoupledDrives",
    "CoupledLorenz",
    "LinearSystem",
    "NeuralObservationSystem",
    "Silverbox",
    "coupling_mask",
    "initial_states",
    "random_coupling",
    "random_observation_matrix",
]
