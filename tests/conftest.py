"""Test configuration: float64, strict dtype promotion and rank-promotion errors; fast compilation.

XLA compilation dominates the run time of this suite: each distinct shape, dtype and solver
structure compiles the smoother, the learner or the joint iteration. XLA:CPU's MLIR fusion
emitters cost most of that time; its classic emitters (``--xla_cpu_use_fusion_emitters=false``)
compile the same HLO about twice as fast, and the fits and smoothers of these tests come out
bitwise identical. The flag is added here, before JAX starts its backend, so that test
subprocesses inherit it too; not when ``XLA_FLAGS`` already sets it, when
``CEEMX_TEST_XLA_DEFAULTS=1`` asks for XLA's defaults, or when this jaxlib does not know the flag
(XLA aborts on unknown flags, so a subprocess tries it first, once per session).
"""

import os
import subprocess
import sys

import jax

_FLAG = "--xla_cpu_use_fusion_emitters=false"


def _with_flag(flags: str) -> str:
    return f"{flags} {_FLAG}".strip()


def _fast_compilation() -> None:
    flags = os.environ.get("XLA_FLAGS", "")
    if os.environ.get("CEEMX_TEST_XLA_DEFAULTS") == "1" or "xla_cpu_use_fusion_emitters" in flags:
        return
    probe = subprocess.run(
        [sys.executable, "-c", "import jax; jax.devices('cpu')"],
        env={**os.environ, "XLA_FLAGS": _with_flag(flags)},
        capture_output=True,
        timeout=300,
    )
    if probe.returncode == 0:
        os.environ["XLA_FLAGS"] = _with_flag(flags)
    else:  # unknown flag: keep XLA's defaults, and do not try again in xdist workers
        os.environ["CEEMX_TEST_XLA_DEFAULTS"] = "1"


_fast_compilation()
# The CLI turns on JAX's persistent compilation cache. In-process it would stay on for the rest of
# the session and write every later executable to disk (slower; and under load jaxlib 0.10.2
# crashed twice in `put_executable_and_time` late in the suite): off for the tests. Tests of the
# cache itself pass their own folder (tests/test_compilation.py).
if "CEEMX_COMPILATION_CACHE" not in os.environ:
    os.environ["CEEMX_COMPILATION_CACHE"] = "off"
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
