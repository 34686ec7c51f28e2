"""Built-in systems."""

from ceemx.systems.benchmarks import CascadedTanks, CoupledDrives, Silverbox
from ceemx.systems.linear import LinearSystem
from ceemx.systems.lorenz import (
    CoupledLorenz,
    coupling_mask,
    initial_states,
    random_coupling,
    random_observation_matrix,
)
from ceemx.systems.neural import NeuralObservationSystem

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
