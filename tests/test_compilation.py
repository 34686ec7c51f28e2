"""Compilation: the persistent cache (opt-in, written where asked, off by the environment), the
per-program XLA options, the compile thread, and the policy that picks one-shot or optimised
programs and compiles ahead only on an idle core (``ceemx.infra.policy``)."""

import os
import subprocess
import sys
import types

import jax
import jax.numpy as jnp
import pytest

from ceemx.infra import compilation, policy
from ceemx.infra.compilation import default_cache_dir, enable_compilation_cache
from ceemx.infra.policy import Runs, Work

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
    so that the library's optimised and one-shot variants coincide here (``policy.program``)."""
    from conftest import TEST_XLA_FLAGS

    assert TEST_XLA_FLAGS == {
        **compilation.FAST_COMPILE_FLAGS,
        **compilation.ONE_SHOT_COMPILE_FLAGS,
    }


def test_suite_runs_with_strict_promotion():
    """Every test process (this one, each xdist worker, the CLI and example subprocesses through
    the environment) computes under strict dtype promotion and rank-promotion errors
    (tests/conftest.py): an implicit int/float mix or an implicit broadcast of ranks raises."""
    assert os.environ["JAX_NUMPY_DTYPE_PROMOTION"] == "strict"
    assert os.environ["JAX_NUMPY_RANK_PROMOTION"] == "raise"
    with pytest.raises(jax.dtypes.TypePromotionError):
        jnp.ones(2) + jnp.ones(2, jnp.int32)
    with pytest.raises(ValueError, match="jax_numpy_rank_promotion"):
        jnp.ones(2) + jnp.ones((3, 2))


def test_fast_compilation_after_jax_started_changes_nothing(monkeypatch):
    import jax.numpy as jnp

    from ceemx.infra.compilation import use_fast_compilation

    jnp.zeros(1).block_until_ready()  # the backend runs
    monkeypatch.delenv("CEEMX_XLA_DEFAULTS", raising=False)
    monkeypatch.setenv("XLA_FLAGS", "")
    assert not use_fast_compilation()
    assert os.environ["XLA_FLAGS"] == ""


def test_compiles_ahead_follows_cpus_and_load(monkeypatch):
    """fit compiles in the background only where a CPU is idle: runnable tasks now, else load."""
    monkeypatch.setattr(policy.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.setattr(policy, "_runnable_tasks", lambda: 1)
    assert policy.compiles_ahead()  # this process alone
    monkeypatch.setattr(policy, "_runnable_tasks", lambda: 2)
    assert not policy.compiles_ahead()  # 2 CPUs, one busy beside this process
    monkeypatch.setattr(policy, "_runnable_tasks", lambda: None)  # not Linux: the load
    monkeypatch.setattr(policy.os, "getloadavg", lambda: (0.4, 0.0, 0.0))
    assert policy.compiles_ahead()
    monkeypatch.setattr(policy.os, "getloadavg", lambda: (1.0, 0.0, 0.0))
    assert not policy.compiles_ahead()
    monkeypatch.setattr(policy.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    monkeypatch.setattr(policy, "_runnable_tasks", lambda: 1)
    assert not policy.compiles_ahead()  # one CPU: nothing to compile beside


def test_runnable_tasks_counts_this_process():
    """On Linux at least this process is runnable while it reads the count."""
    n = policy._runnable_tasks()
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
    """A one-shot program compiles with its options (an unknown one fails, through the policy's
    programs too) and computes the same numbers; a program's two variants are one object when
    they would compile alike."""
    monkeypatch.delenv("CEEMX_XLA_DEFAULTS", raising=False)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    f = lambda x: jnp.tanh(x) @ jnp.exp(x).T - 0.5  # noqa: E731
    x = jnp.linspace(-1.0, 1.0, 12).reshape(3, 4)
    optimised, one_shot = compilation.jit(f), compilation.one_shot_jit(f)
    assert float(jnp.max(jnp.abs(one_shot(x) - optimised(x)))) < 1e-13
    assert policy.program(f)._optimised is not policy.program(f)._one_shot
    monkeypatch.setenv("XLA_FLAGS", " ".join(f"--{k}={v}" for k, v in _all_flags().items()))
    alike = policy.program(f)
    assert alike._optimised is alike._one_shot
    monkeypatch.delenv("XLA_FLAGS")
    monkeypatch.setattr(compilation, "ONE_SHOT_COMPILE_FLAGS", {"xla_not_a_one_shot": "0"})
    with pytest.raises(Exception, match="xla_not_a_one_shot"):
        policy.program(lambda x: jnp.cos(x) * 3.0, runs=Runs.ONCE)(x)


def _all_flags():
    return {**compilation.FAST_COMPILE_FLAGS, **compilation.ONE_SHOT_COMPILE_FLAGS}


def test_policy_rule_by_runs_and_work():
    """One-shot: a program run once whose run time is negligible, or whose work is at most its
    bound for how often it runs; optimised otherwise (the E-step's smoothing always)."""
    assert policy.compiles_one_shot(Runs.ONCE)
    assert not policy.compiles_one_shot(Runs.EVERY_EPOCH)
    n, P = 3, 10
    cases = [  # (work at B = 1 and T steps, how often it runs)
        (lambda T: policy.smoothing_work(1, T, n), Runs.ONCE, 5 * 10**5, n**2),
        (lambda T: policy.schur_work(1, T, n, P), Runs.ONCE, 2 * 10**9, n * P**2),
        (
            lambda T: policy.joint_iteration_work(1, T, n, P),
            Runs.EVERY_EPOCH,
            10**5,
            n * (n + P) ** 2,
        ),
    ]
    for work, runs, bound, per_step in cases:
        T_max = bound // per_step
        assert policy.ONE_SHOT_MAX_WORK[(work(1).kind, runs)] == bound
        assert policy.compiles_one_shot(runs, work(T_max)), work(T_max)
        assert not policy.compiles_one_shot(runs, work(T_max + 1)), work(T_max + 1)
    assert not policy.compiles_one_shot(Runs.EVERY_EPOCH, policy.smoothing_work(1, 2, 1))
    assert not policy.compiles_one_shot(Runs.ONCE, Work("no bound listed", 1))


class _Variant:
    def __init__(self, name):
        self.name = name

    def __call__(self, *args):
        return self.name

    def lower(self, *args):
        return f"{self.name} lowered"


def test_program_picks_its_variant_per_call():
    """A program runs the variant the rule picks for the call's shapes; ``with_runs`` shares the
    variants; ``.lower`` follows the same choice."""
    variants = (_Variant("optimised"), _Variant("one_shot"))
    work = lambda x: policy.smoothing_work(1, x.shape[0], 1)  # noqa: E731
    once = policy.Program(lambda x: x, Runs.ONCE, work, variants)
    small, large = jnp.ones(2), jax.ShapeDtypeStruct((5 * 10**5 + 1,), jnp.float64)
    assert once(small) == "one_shot" and once(large) == "optimised"
    assert once.lower(small) == "one_shot lowered" and once.lower(large) == "optimised lowered"
    assert once.with_runs(Runs.EVERY_EPOCH)(small) == "optimised"
    assert policy.Program(lambda x: x, Runs.ONCE, None, variants)(large) == "one_shot"


def test_library_programs_ask_the_policy(monkeypatch):
    """The smoother compiles one-shot only when called once and small; the Schur complement, the
    parameter covariance, the joint iteration and a score's initial-state estimate by their work;
    a joint fit's warm start smooths once, Algorithm 1's (whose E-step is that program) does not,
    and neither does ``ceemx.smooth``."""
    import ceemx
    from ceemx.evaluation import initial_state
    from ceemx.identification import initialize, schur
    from ceemx.identification.analysis import uncertainty
    from ceemx.identification.solvers import joint
    from ceemx.inference import smoother
    from ceemx.systems import LinearSystem

    n, P = 3, 10

    def states(T):
        return jax.ShapeDtypeStruct((1, T, n), jnp.float64)

    theta = jax.ShapeDtypeStruct((P,), jnp.float64)
    T_max = 5 * 10**5 // n**2
    for program in (smoother._smooth_batch_once, smoother._smooth_batch):
        once = program.runs is Runs.ONCE
        assert program.compiles_one_shot(None, None, None, states(8), None, False) == once
        assert not program.compiles_one_shot(None, None, None, states(T_max + 1), None, False)
    system = LinearSystem(jnp.eye(n), jnp.eye(n)[:2], process_noise=0.1, obs_noise=0.1)
    window = types.SimpleNamespace(y=jax.ShapeDtypeStruct((1, T_max + 1, 2), jnp.float64))
    assert not initial_state.initial_state_batch.compiles_one_shot(
        None, system, None, window, None, True
    )
    window = types.SimpleNamespace(y=jax.ShapeDtypeStruct((1, T_max, 2), jnp.float64))
    assert initial_state.initial_state_batch.compiles_one_shot(
        None, system, None, window, None, True
    )
    T_schur = 2 * 10**9 // (n * P**2)
    for program in (schur.schur_complement, uncertainty._laplace):
        assert program.compiles_one_shot(None, theta, states(T_schur), None, None)
        assert not program.compiles_one_shot(None, theta, states(T_schur + 1), None, None)
    T_joint = 10**5 // (n * (n + P) ** 2)
    assert joint._iteration.compiles_one_shot(None, None, None, theta, states(T_joint), None)
    large = states(T_joint + 1)
    assert not joint._iteration.compiles_one_shot(None, None, None, theta, large, None)

    calls = []

    class Stop(Exception):
        pass

    def record(name):
        def program(*args):
            calls.append(name)
            raise Stop

        return program

    monkeypatch.setattr(smoother, "_smooth_batch", record("every epoch"))
    monkeypatch.setattr(smoother, "_smooth_batch_once", record("once"))
    data = ceemx.Trajectories(y=jnp.zeros((1, 8, 2)))
    # The warm start's least-squares states are not what is tested (and would compile).
    monkeypatch.setattr(initialize, "from_observations", lambda s, d: jnp.zeros((1, 8, n)))
    for solver, want in [(ceemx.JointLM(), "once"), (ceemx.Alternating(), "every epoch")]:
        with pytest.raises(Stop):
            solver.initial_states(system, data)
        assert calls.pop() == want, type(solver).__name__
    with pytest.raises(Stop):
        ceemx.smooth(system, data, jnp.zeros((1, 8, n)))
    assert calls.pop() == "every epoch"


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
