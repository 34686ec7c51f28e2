"""Test configuration: float64, strict dtype promotion and rank-promotion errors; fast compilation.

XLA compilation dominates the run time of this suite (each distinct shape, dtype and solver
structure compiles the smoother, learner or joint iteration). XLA's CPU backend compiles about a
third faster with LLVM optimisation off (``--xla_backend_optimization_level=0``): the same HLO, no
fast-math, results equal to round-off (measured ≤ 1e-13 relative after a 30-epoch fit). It is set
here, before JAX starts its backend, unless ``XLA_FLAGS`` already chooses a level or
``CEEMX_TEST_XLA_OPT=1`` asks for the optimised backend. Subprocesses started by tests inherit it.
"""

import os

import jax

if os.environ.get("CEEMX_TEST_XLA_OPT") != "1":
    _flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level" not in _flags:
        os.environ["XLA_FLAGS"] = f"{_flags} --xla_backend_optimization_level=0".strip()

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
