"""The maths layer: structured linear algebra, the Levenberg–Marquardt driver, status codes.

Nothing here knows about EM, systems or data; the user-facing layer (``ceemx``) composes it.

- :mod:`~ceemx.lib.blocktri` — symmetric block-tridiagonal matrices: Cholesky, solves,
  log-determinant, selected inverse (all O(T n³), ``lax.scan`` over time).
- :mod:`~ceemx.lib.parallel_blocktri` — the same solve by associative scans (depth O(log T)).
- :mod:`~ceemx.lib.arrowhead` — bordered block-tridiagonal (arrowhead) systems by the Schur
  complement (dense Cholesky or matrix-free preconditioned CG).
- :mod:`~ceemx.lib.dense` — small dense SPD solves with a failure flag, masked whitening.
- :mod:`~ceemx.lib.lm` — a bounded, vmap-safe Levenberg–Marquardt driver.
- :mod:`~ceemx.lib.kalman` — linear-Gaussian conditioning (Kalman update) with masks.
- :mod:`~ceemx.lib.particles` — log-weights, ESS, systematic resampling, FFBSi index draws.
- :mod:`~ceemx.lib.nullspace` — near-null directions of a curvature matrix (host NumPy) and the
  small-integer monomials they leave determined ("only a·b and a·c").
- :mod:`~ceemx.lib.results` — :class:`RESULTS`, the solvers' status codes.
- :mod:`~ceemx.lib.tree` — pytree utilities for solver objects.
"""

from ceemx.lib.arrowhead import ArrowheadSolution as ArrowheadSolution
from ceemx.lib.arrowhead import arrowhead_solve as arrowhead_solve
from ceemx.lib.arrowhead import arrowhead_solve_matrix_free as arrowhead_solve_matrix_free
from ceemx.lib.arrowhead import pcg as pcg
from ceemx.lib.blocktri import BlockTridiagonal as BlockTridiagonal
from ceemx.lib.blocktri import BlockTridiagonalCholesky as BlockTridiagonalCholesky
from ceemx.lib.blocktri import add_to_diagonal as add_to_diagonal
from ceemx.lib.blocktri import cho_solve as cho_solve
from ceemx.lib.blocktri import cholesky as cholesky
from ceemx.lib.blocktri import is_finite as is_finite
from ceemx.lib.blocktri import logdet as logdet
from ceemx.lib.blocktri import matvec as matvec
from ceemx.lib.blocktri import selected_inverse as selected_inverse
from ceemx.lib.blocktri import solve as solve
from ceemx.lib.blocktri import to_dense as to_dense
from ceemx.lib.dense import cholesky_solve as cholesky_solve
from ceemx.lib.dense import symmetrize as symmetrize
from ceemx.lib.lm import LMOutput as LMOutput
from ceemx.lib.lm import levenberg_marquardt as levenberg_marquardt
from ceemx.lib.lm import marquardt_scale as marquardt_scale
from ceemx.lib.parallel_blocktri import parallel_solve as parallel_solve
from ceemx.lib.results import RESULTS as RESULTS
from ceemx.lib.tree import trace_numbers as trace_numbers

__all__ = [
    "RESULTS",
    "ArrowheadSolution",
    "BlockTridiagonal",
    "BlockTridiagonalCholesky",
    "LMOutput",
    "add_to_diagonal",
    "arrowhead_solve",
    "arrowhead_solve_matrix_free",
    "cho_solve",
    "cholesky",
    "cholesky_solve",
    "is_finite",
    "levenberg_marquardt",
    "logdet",
    "marquardt_scale",
    "matvec",
    "pcg",
    "selected_inverse",
    "solve",
    "symmetrize",
    "to_dense",
    "trace_numbers",
]
