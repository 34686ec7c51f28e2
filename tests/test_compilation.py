"""The persistent compilation cache: opt-in, written where asked, off by the environment."""

import os
import subprocess
import sys
import types

import jax
import jax.numpy as jnp
import pytest

from ceemx.infra import compilation
from ceemx.infra.compilation import default_cache_dir, enable_compilation_cache

_SCRIPT = """
import sys
import jax, jax.numpy as jnp
from ceemx.infra.compilation import enable_compilation_cache
print(enable_compilation_cache(sys.argv[1], min_compile_time_s=0.0))
f = jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + 1.0)
print(float(f(jnp.ones((3, 3))).sum()))
"""


@pytest.mark.slow  # two Python processes (≈ 3 s), like the command line's other process tests
def test_cache_is_written_and_reused(tmp_path):
    """A second process finds the first one's executable in the folder (no new entries)."""
    folder = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if k != "CEEMX_COMPILATION_CACHE"}
    run = lambda: subprocess.run(  # noqa: E731
        [sys.executable, "-c", _SCRIPT, str(folder)], env=env, capture_output=True, text=True
    )
    first = run()
    assert first.returncode == 0, first.stderr
    entries = sorted(p.name for p in folder.iterdir())
    assert entries, "nothing was written to the cache folder"
    second = run()
    assert second.returncode == 0, second.stderr
    assert second.stdout == first.stdout
    assert sorted(p.name for p in folder.iterdir()) == entries


def test_environment_switches(monkeypatch, tmp_path):
    monkeypatch.setenv("CEEMX_COMPILATION_CACHE", "off")
    assert enable_compilation_cache() is None
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "ceemx" / "jax"
    with pytest.raises(ValueError, match="min_compile_time_s"):
        enable_compilation_cache(tmp_path, min_compile_time_s=-1.0)


def test_fast_compilation_flags(monkeypatch):
    """Added to XLA_FLAGS before JAX starts; a flag the user set and the opt-out are respected."""
    from ceemx.infra import compilation

    monkeypatch.setattr(compilation, "_backend_started", lambda: False)
    monkeypatch.delenv("CEEMX_XLA_DEFAULTS", raising=False)
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    assert compilation.use_fast_compilation()
    assert os.environ["XLA_FLAGS"] == "--xla_dump_to=/tmp/x --xla_cpu_use_fusion_emitters=false"
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    assert compilation.use_fast_compilation()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"
    monkeypatch.setenv("CEEMX_XLA_DEFAULTS", "1")
    monkeypatch.setenv("XLA_FLAGS", "")
    assert not compilation.use_fast_compilation()
    assert os.environ["XLA_FLAGS"] == ""


def test_suite_compiles_with_the_library_options():
    """The suite's process-wide XLA flags (tests/conftest.py) are the library's per-program ones,
    so that the library's optimised and one-shot variants coincide here (``jit_variants``)."""
    from conftest import TEST_XLA_FLAGS

    assert TEST_XLA_FLAGS == {
        **compilation.FAST_COMPILE_FLAGS,
        **compilation.ONE_SHOT_COMPILE_FLAGS,
    }


def test_fast_compilation_after_jax_started_changes_nothing(monkeypatch):
    import jax.numpy as jnp

    from ceemx.infra.compilation import use_fast_compilation

    jnp.zeros(1).block_until_ready()  # the backend runs
    monkeypatch.delenv("CEEMX_XLA_DEFAULTS", raising=False)
    monkeypatch.setenv("XLA_FLAGS", "")
    assert not use_fast_compilation()
    assert os.environ["XLA_FLAGS"] == ""


def test_has_idle_core_follows_cpus_and_load(monkeypatch):
    """fit compiles in the background only where a CPU is idle: runnable tasks now, else load."""
    from ceemx.infra import compilation

    monkeypatch.setattr(compilation.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.setattr(compilation, "_runnable_tasks", lambda: 1)
    assert compilation.has_idle_core()  # this process alone
    monkeypatch.setattr(compilation, "_runnable_tasks", lambda: 2)
    assert not compilation.has_idle_core()  # 2 CPUs, one busy beside this process
    monkeypatch.setattr(compilation, "_runnable_tasks", lambda: None)  # not Linux: the load
    monkeypatch.setattr(compilation.os, "getloadavg", lambda: (0.4, 0.0, 0.0))
    assert compilation.has_idle_core()
    monkeypatch.setattr(compilation.os, "getloadavg", lambda: (1.0, 0.0, 0.0))
    assert not compilation.has_idle_core()
    monkeypatch.setattr(compilation.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    monkeypatch.setattr(compilation, "_runnable_tasks", lambda: 1)
    assert not compilation.has_idle_core()  # one CPU: nothing to compile beside


def test_runnable_tasks_counts_this_process():
    """On Linux at least this process is runnable while it reads the count."""
    from ceemx.infra import compilation

    n = compilation._runnable_tasks()
    assert n is None or n >= 1


def test_program_options_follow_the_environment(monkeypatch):
    """ceemx's per-program XLA options: the fast-compile flags unless XLA_FLAGS or the user says."""
    monkeypatch.delenv("CEEMX_XLA_DEFAULTS", raising=False)
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
    assert compilation.program_options() == {
        "xla_cpu_use_fusion_emitters": False,
        "xla_backend_optimization_level": 1,
    }
    monkeypatch.setenv(
        "XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true --xla_backend_optimization_level=2"
    )
    assert compilation.program_options() == {}  # the user's flags win
    monkeypatch.delenv("XLA_FLAGS")
    monkeypatch.setenv("CEEMX_XLA_DEFAULTS", "1")
    assert compilation.program_options() == {}


def test_jit_passes_its_options_to_xla(monkeypatch):
    """The options reach the compiler: an unknown one fails to compile, the real ones give the
    same numbers as XLA's defaults."""
    monkeypatch.delenv("CEEMX_XLA_DEFAULTS", raising=False)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    f = lambda x: jnp.sin(x) @ jnp.cos(x).T + 1.0  # noqa: E731
    x = jnp.linspace(0.0, 1.0, 12).reshape(3, 4)
    fast = compilation.jit(f)
    assert float(jnp.max(jnp.abs(fast(x) - jax.jit(f)(x)))) < 1e-14
    monkeypatch.setattr(compilation, "FAST_COMPILE_FLAGS", {"xla_not_an_option": "false"})
    with pytest.raises(Exception, match="xla_not_an_option"):
        compilation.jit(lambda x: jnp.cos(x) * 2.0)(x)


def test_one_shot_options_follow_the_environment(monkeypatch):
    """One-shot programs add LLVM -O0 and one codegen module, unless XLA_FLAGS names them."""
    monkeypatch.delenv("CEEMX_XLA_DEFAULTS", raising=False)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert compilation.program_options(one_shot=True) == {
        "xla_cpu_use_fusion_emitters": False,
        "xla_backend_optimization_level": 0,
        "xla_cpu_parallel_codegen_split_count": 1,
    }
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=2")
    assert compilation.program_options(one_shot=True) == {
        "xla_cpu_use_fusion_emitters": False,
        "xla_cpu_parallel_codegen_split_count": 1,
    }
    monkeypatch.delenv("XLA_FLAGS")
    monkeypatch.setenv("CEEMX_ONE_SHOT", "0")  # every program optimised
    assert compilation.program_options(one_shot=True) == compilation.program_options()


def test_one_shot_program_reaches_xla_and_variants_alias_when_alike(monkeypatch):
    """A one-shot program compiles with its options (an unknown one fails) and computes the same
    numbers; the two variants are one object when they would compile alike."""
    monkeypatch.delenv("CEEMX_XLA_DEFAULTS", raising=False)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    f = lambda x: jnp.tanh(x) @ jnp.exp(x).T - 0.5  # noqa: E731
    x = jnp.linspace(-1.0, 1.0, 12).reshape(3, 4)
    optimised, one_shot = compilation.jit_variants(f)
    assert optimised is not one_shot
    assert float(jnp.max(jnp.abs(one_shot(x) - optimised(x)))) < 1e-13
    monkeypatch.setenv("XLA_FLAGS", " ".join(f"--{k}={v}" for k, v in _all_flags().items()))
    a, b = compilation.jit_variants(f)
    assert a is b
    monkeypatch.delenv("XLA_FLAGS")
    monkeypatch.setattr(compilation, "ONE_SHOT_COMPILE_FLAGS", {"xla_not_a_one_shot": "0"})
    with pytest.raises(Exception, match="xla_not_a_one_shot"):
        compilation.jit(lambda x: jnp.cos(x) * 3.0, one_shot=True)(x)


def _all_flags():
    return {**compilation.FAST_COMPILE_FLAGS, **compilation.ONE_SHOT_COMPILE_FLAGS}


def test_one_shot_choice_follows_the_size(monkeypatch):
    """``one_shot_when`` picks by its predicate; the smoother compiles one-shot only when asked and
    B·T·n² ≤ ONE_SHOT_MAX_WORK; the schur complement by B·T·n·P²; a joint fit's warm start asks,
    Algorithm 1's (whose E-step is that program) does not."""
    monkeypatch.delenv("CEEMX_XLA_DEFAULTS", raising=False)
    monkeypatch.delenv("XLA_FLAGS", raising=False)

    class Variant:
        def __init__(self, name):
            self.name = name

        def __call__(self, *args):
            return self.name

        def lower(self, *args):
            return f"{self.name} lowered"

    with monkeypatch.context() as m:
        variants = (Variant("optimised"), Variant("one_shot"))
        m.setattr(compilation, "jit_variants", lambda fun, **kw: variants)
        picked = compilation.one_shot_when(lambda x: x.shape[0] < 3)(lambda x: x)
    assert picked(jnp.ones(2)) == "one_shot" and picked(jnp.ones(4)) == "optimised"
    assert picked.lower(jnp.ones(2)) == "one_shot lowered"
    assert picked.lower(jnp.ones(4)) == "optimised lowered"

    import ceemx
    from ceemx.evaluation import initial_state
    from ceemx.identification import initialize, schur
    from ceemx.identification.solvers import joint
    from ceemx.inference import smoother
    from ceemx.systems import LinearSystem

    calls = []

    class Stop(Exception):
        pass

    def record(name):
        def program(*args):
            calls.append(name)
            raise Stop

        return program

    monkeypatch.setattr(smoother, "_smooth_batch", record("optimised"))
    monkeypatch.setattr(smoother, "_smooth_batch_one_shot", record("one_shot"))
    solver = ceemx.LMSmoother()
    n = 3
    T_max = smoother.ONE_SHOT_MAX_WORK // n**2
    for T, one_shot, want in [
        (8, True, "one_shot"),
        (8, False, "optimised"),
        (T_max + 1, True, "optimised"),
    ]:
        x = jax.ShapeDtypeStruct((1, T, n), jnp.float64)
        with pytest.raises(Stop):
            smoother.smooth_batch(solver, None, x, None, False, one_shot)
        assert calls.pop() == want, (T, one_shot)

    P = 10
    per_unit = 1 * n * P**2
    theta = jax.ShapeDtypeStruct((P,), jnp.float64)
    small = jax.ShapeDtypeStruct((1, schur.SCHUR_ONE_SHOT_MAX_WORK // per_unit, n), jnp.float64)
    large = jax.ShapeDtypeStruct((1, schur.SCHUR_ONE_SHOT_MAX_WORK // per_unit + 1, n), jnp.float64)
    assert schur.small_schur(None, theta, small, None)
    assert not schur.small_schur(None, theta, large, None)
    per_step = n * (n + P) ** 2
    small = jax.ShapeDtypeStruct((1, joint.ITERATION_TINY_WORK // per_step, n), jnp.float64)
    large = jax.ShapeDtypeStruct((1, joint.ITERATION_TINY_WORK // per_step + 1, n), jnp.float64)
    assert joint._tiny_iteration(None, None, None, theta, small, None)
    assert not joint._tiny_iteration(None, None, None, theta, large, None)

    system = LinearSystem(jnp.eye(n), jnp.eye(n)[:2], process_noise=0.1, obs_noise=0.1)
    data = ceemx.Trajectories(y=jnp.zeros((1, 8, 2)))
    # The warm start's least-squares states are not what is tested (and would compile).
    monkeypatch.setattr(initialize, "from_observations", lambda s, d: jnp.zeros((1, 8, n)))
    window = types.SimpleNamespace(y=jax.ShapeDtypeStruct((1, T_max + 1, 2), jnp.float64))
    assert initial_state._small_window(None, system, None, data, None, True)
    assert not initial_state._small_window(None, system, None, window, None, True)
    for solver, want in [(ceemx.JointLM(), "one_shot"), (ceemx.Alternating(), "optimised")]:
        with pytest.raises(Stop):
            solver.initial_states(system, data)
        assert calls.pop() == want, type(solver).__name__


def test_join_runs_the_jobs_the_worker_has_not_started():
    """``join()`` takes the waiting compile jobs into the calling thread; a failing job is
    dropped (the later call compiles and reports it)."""
    import threading

    started, release = threading.Event(), threading.Event()
    ran = {}

    def first():
        started.set()
        release.wait(10)
        ran["first"] = threading.current_thread().name

    def failing():
        raise RuntimeError("dropped")

    def last():
        ran["last"] = threading.current_thread().name
        release.set()

    jobs = compilation.compile_in_background([first, failing, last])
    assert started.wait(10)
    jobs.join()
    assert ran == {"first": "ceemx-compile", "last": threading.current_thread().name}
    assert not jobs.is_alive()
