"""Test configuration: float64, strict dtype promotion and rank-promotion errors; fast compilation.

XLA compilation dominates the run time of this suite: each distinct shape, dtype and solver
structure compiles the smoother, the learner or the joint iteration (about 1700 programs, nearly
all distinct: a session-wide persistent cache finds 6 % of them again). Three XLA:CPU flags make
each compilation cheaper; CPU seconds of test_health + test_joint + test_benchmark_systems (two
runs each, a shared 2-core machine): classic emitters instead of the MLIR fusion emitters
(``--xla_cpu_use_fusion_emitters=false``) 81–83; plus LLVM at -O0 instead of -O2
(``--xla_backend_optimization_level=0``) 47–52; plus one LLVM module instead of a split for
parallel code generation (``--xla_cpu_parallel_codegen_split_count=1``) 41–43 (the last two
without the first: 94). They are the library's own per-program options
(``ceemx.infra.compilation``: ``FAST_COMPILE_FLAGS``, ``ONE_SHOT_COMPILE_FLAGS``), here for every
program of the process. The same HLO optimisations run either way; -O0 machine code runs slower
(a run-time-bound file such as test_particle by ~5 %) and rounds some results differently in the
last bits, which every oracle's tolerance allows. The flags are added here, before JAX starts its
backend, so that test subprocesses and xdist workers inherit them; each one unless ``XLA_FLAGS``
already sets it; none when ``CEEMX_TEST_XLA_DEFAULTS=1`` asks for XLA's defaults. No probe for
unknown flags: the library passes the same options to every program it compiles, so a jaxlib
without them fails its tests either way.

The xdist controller runs no test: it neither imports JAX nor configures it (about a second
before the workers start); each worker, and a run without xdist, does in ``pytest_configure``,
before any test module is imported.
"""

import gc
import os
import sys

import pytest

# Bytecode caches on, even where the environment turns them off (PYTHONDONTWRITEBYTECODE): every
# process of a run (two xdist workers, the CLI and example subprocesses) otherwise recompiles
# every source and re-rewrites every test module's asserts — collection took 19 CPU s per process
# on a 2 GHz 2-core machine, 10 s with the caches. Caches go to the git-ignored __pycache__ folders.
sys.dont_write_bytecode = False
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

# The library's per-program options (ceemx.infra.compilation), spelled out so that the controller
# need not import the library (tests/test_compilation.py checks that they agree).
TEST_XLA_FLAGS = {
    "xla_cpu_use_fusion_emitters": "false",
    "xla_backend_optimization_level": "0",
    "xla_cpu_parallel_codegen_split_count": "1",
}


def _with_flags(flags: str) -> str:
    extra = [f"--{name}={value}" for name, value in TEST_XLA_FLAGS.items() if name not in flags]
    return " ".join([flags, *extra]).strip()


def _fast_compilation() -> None:
    """Add the flags to ``XLA_FLAGS``: xdist workers and test subprocesses inherit them."""
    if os.environ.get("CEEMX_TEST_XLA_DEFAULTS") != "1":
        os.environ["XLA_FLAGS"] = _with_flags(os.environ.get("XLA_FLAGS", ""))


def _pin_xdist_worker() -> None:
    """Give each xdist worker its own CPUs, before JAX starts (its thread pool follows them).

    Unpinned, each of the two workers on a 2-core machine runs XLA's pool of two threads: four
    threads on two cores, whose hand-offs stall when a sibling is descheduled (docs/design.md,
    ``limit_cpu_threads``; benchmarks/README.md "Busy machines"). Only when every worker can have
    at least one CPU of its own; test subprocesses inherit their worker's CPUs.
    """
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if not worker.startswith("gw") or count < 2 or not hasattr(os, "sched_setaffinity"):
        return
    cpus = sorted(os.sched_getaffinity(0))
    share = len(cpus) // count
    if share < 1:
        return
    i = int(worker[2:]) % count
    os.sched_setaffinity(0, cpus[i * share : (i + 1) * share])


_pin_xdist_worker()
_fast_compilation()
# The CLI turns on JAX's persistent compilation cache. In-process it would stay on for the rest of
# the session and write every later executable to disk (slower; and under load jaxlib 0.10.2
# crashed twice in `put_executable_and_time` late in the suite): off for the tests. Tests of the
# cache itself pass their own folder (tests/test_compilation.py).
if "CEEMX_COMPILATION_CACHE" not in os.environ:
    os.environ["CEEMX_COMPILATION_CACHE"] = "off"
# Strict dtype promotion and rank-promotion errors: JAX reads its options' defaults from these
# variables when it is imported, so the xdist workers and the test subprocesses (the CLI, the
# examples) run under them too; ``pytest_configure`` sets them again in this process.
STRICT_PROMOTION = {"JAX_NUMPY_DTYPE_PROMOTION": "strict", "JAX_NUMPY_RANK_PROMOTION": "raise"}
for _name, _value in STRICT_PROMOTION.items():
    os.environ[_name] = _value


def _is_xdist_controller(config) -> bool:
    """Whether this process hands the tests to xdist workers (and runs none itself)."""
    if hasattr(config, "workerinput"):
        return False
    dist = getattr(config.option, "dist", "no")
    return bool(getattr(config.option, "numprocesses", None)) and dist != "no"


def pytest_configure(config):
    if _is_xdist_controller(config):
        return
    import jax

    jax.config.update("jax_enable_x64", True)
    for name, value in STRICT_PROMOTION.items():
        jax.config.update(name.lower(), value)
    gc.set_threshold(*GC_THRESHOLDS)


# Python's cyclic garbage collector at its default thresholds (700, 10, 10) ran a collection every
# 700 allocations of JAX's tracing and lowering, and took about a tenth of the CPU samples of
# compile-bound test files (perf). Collections 70× rarer, and the modules imported by collection
# frozen out of them: 2–9 % less CPU on such files, the same peak memory.
GC_THRESHOLDS = (50_000, 20, 100)


def pytest_collection_finish(session):
    """Freeze what collection imported: later collections need not scan it again."""
    del session
    gc.collect()
    gc.freeze()


# The suite's files by the seconds their tests take in a full run, heaviest first (subprocesses
# included). Run in this order (pyproject's ``--no-loadscope-reorder``; xdist otherwise orders
# files by their number of tests), the two workers get the long files first and finish within
# seconds of each other (longest processing time first); files not listed follow in collection
# order. A stale order costs balance, never correctness.
_HEAVY_FIRST = (
    "test_solver_table.py",
    "test_validation.py",
    "test_particle.py",
    "test_default_path.py",
    "test_smoother.py",
    "test_analysis_defects.py",
    "test_joint.py",
    "test_profile.py",
    "test_save_load.py",
    "test_laplace_noise.py",
    "test_learners.py",
    "test_subspace.py",
    "test_fit.py",
    "test_baselines.py",
    "test_noise_learning.py",
    "test_noise_diagnostics.py",
    "test_hybrid.py",
    "test_linalg.py",
    "test_evaluate_real.py",
    "test_gray_box.py",
    "test_checkpoint_safety.py",
    "test_uncertainty.py",
    "test_prediction.py",
    "test_lapack_safety.py",
    "test_convergence_claims.py",
    "test_constraints.py",
    "test_fuzz.py",
    "test_data.py",
    "test_learning_gauss_newton.py",
    "test_filtering.py",
    "test_report.py",
    "test_runtime.py",
    "test_identifiability.py",
    "test_datasets.py",
    "test_custom_system.py",
    "test_parallel_in_time.py",
    "test_health.py",
    "test_evaluate.py",
    "test_initialize.py",
    "test_experiments.py",
    "test_compilation.py",
    "test_noise_models.py",
    "test_cli_reliability.py",
    "test_memory_guard.py",
    "test_laplace_em.py",
)


def pytest_collection_modifyitems(config, items):
    """Heaviest files first (a stable sort: each file's tests stay together and in order)."""
    del config
    rank = {name: i for i, name in enumerate(_HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture
def no_compute():
    """Fails the test if compute started before the refusal it expects (tests/refusals.py).

    The only trace of a counting model's methods allowed is the one-time check of their output
    shapes (``ceemx.models.method_check``: abstract evaluation, nothing compiled or computed); a
    fit, smoothing or health test traces them many times.
    """
    from refusals import TRACES

    TRACES.clear()
    yield
    assert TRACES.count("dynamics") <= 1 and TRACES.count("observe") <= 1, (
        f"compute started before the refusal: {TRACES[:6]}"
    )


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    """An xdist worker leaves at once when its session is over: its results are sent, and the
    interpreter's teardown of a few hundred compiled programs (1–3 s, on the suite's critical path:
    the controller waits for every worker to exit) has nothing left to do."""
    if hasattr(config, "workerinput"):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
