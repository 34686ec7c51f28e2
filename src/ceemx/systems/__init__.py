"""Built-in systems."""

from .linear import LinearSystem
from .lorenz import (
    CoupledLorenz,
    coupling_mask,
    initial_states,
    random_coupling,
    random_observation_matrix,
)

__all__ = [
    "CoupledLorenz",
    "LinearSystem",
    "coupling_mask",
    "initial_states",
    "random_coupling",
    "random_observation_matrix",
]
