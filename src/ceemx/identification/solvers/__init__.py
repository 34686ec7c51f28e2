"""Fit solvers: each an ``eqx.Module`` with ``init / step / terminate / postprocess``.

- :class:`Alternating` — the paper's Algorithm 1 (smoothing step, learning step).
- :class:`JointLM` — Levenberg–Marquardt on (x, θ) through the Schur complement.
- :class:`LaplaceEM` — Laplace (MAP-) EM: Gaussian E-step, cubature M-step, learned noise.
- :class:`ParticleEM` — particle filter + FFBSi E-step, SAEM M-step (the paper's baseline).

To add one, subclass :class:`AbstractFitSolver` (see :mod:`ceemx.identification.solvers.base` and
``docs/design.md``) and declare what it can do in its class-level flags (``learns_noise``,
``multi_process``, ``noise_rounds``, ``uncertainty``): :func:`ceemx.fit` asks those, never the
solver's type, and runs it with history, callbacks and checkpoints. Each file holds one solver;
the mathematics solvers share lives below them (:mod:`ceemx.identification.schur`,
:mod:`ceemx.identification.noise_moments`, :mod:`ceemx.identification.problem`).
"""

from ceemx.identification.solvers.alternating import Alternating
from ceemx.identification.solvers.base import AbstractFitSolver, FitState
from ceemx.identification.solvers.joint import JointLM
from ceemx.identification.solvers.laplace import LaplaceEM
from ceemx.identification.solvers.particle_em import ParticleEM, SAEMState, saem_step_size

__all__ = [
    "AbstractFitSolver",
    "Alternating",
    "FitState",
    "JointLM",
    "LaplaceEM",
    "ParticleEM",
    "SAEMState",
    "saem_step_size",
]
