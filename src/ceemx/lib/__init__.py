"""Structured linear algebra: block-tridiagonal SPD matrices and arrowhead systems."""

from ceemx.linalg.arrowhead import ArrowheadSolution as ArrowheadSolution
from ceemx.linalg.arrowhead import arrowhead_solve as arrowhead_solve
from ceemx.linalg.blocktri import BlockTridiagonal as BlockTridiagonal
from ceemx.linalg.blocktri import BlockTridiagonalCholesky as BlockTridiagonalCholesky
from ceemx.linalg.blocktri import add_to_diagonal as add_to_diagonal
from ceemx.linalg.blocktri import cho_solve as cho_solve
from ceemx.linalg.blocktri import cholesky as cholesky
from ceemx.linalg.blocktri import is_finite as is_finite
from ceemx.linalg.blocktri import logdet as logdet
from ceemx.linalg.blocktri import matvec as matvec
from ceemx.linalg.blocktri import selected_inverse as selected_inverse
from ceemx.linalg.blocktri import solve as solve
from ceemx.linalg.blocktri import to_dense as to_dense

__all__ = [
    "ArrowheadSolution",
    "BlockTridiagonal",
    "BlockTridiagonalCholesky",
    "add_to_diagonal",
    "arrowhead_solve",
    "cho_solve",
    "cholesky",
    "is_finite",
    "logdet",
    "matvec",
    "selected_inverse",
    "solve",
    "to_dense",
]
