"""Built-in systems.

The paper's coupled Lorenz attractors, a linear system, a neural observation model, and the
gray-box models of the three real datasets (:mod:`ceemx.systems.gray_box`).
"""

from ceemx.systems.constant_input import ConstantInput
from ceemx.systems.gray_box import CascadedTanks, CoupledDrives, Silverbox
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
    "ConstantInput",
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
