"""``ceemx.infra.runtime.limit_cpu_threads`` and the CLI's ``--threads`` (run in fresh processes:
CPU affinity and JAX's thread pool are process state)."""

import os
import subprocess
import sys
import textwrap

import pytest

from ceemx import cli
from ceemx.infra.runtime import limit_cpu_threads

needs_affinity = pytest.mark.skipif(
    not hasattr(os, "sched_getaffinity"), reason="CPU affinity is Linux-only"
)


def _run(code: str, env=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )


@pytest.mark.parametrize("n", [0, -1, 1.5, True, "2"])
def test_bad_thread_counts_are_refused(n):
    with pytest.raises(ValueError, match="`n` must be an integer >= 1"):
        limit_cpu_threads(n)


@needs_affinity
def test_limit_before_jax_starts_pins_the_process_and_sizes_the_pool():
    proc = _run(
        """
        import os, warnings
        warnings.simplefilter("error")  # no warning: JAX has not started
        from ceemx.infra.runtime import limit_cpu_threads
        n = limit_cpu_threads(1)
        import jax, jax.numpy as jnp
        jax.block_until_ready(jnp.ones(3) @ jnp.ones(3))
        print(n, len(os.sched_getaffinity(0)))
        """
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["1", "1"]


@pytest.mark.slow  # a Python process of its own (≈ 2 s); the limit itself: the test above
@needs_affinity
def test_limit_after_jax_started_warns():
    proc = _run(
        """
        import jax, jax.numpy as jnp, warnings
        jax.block_until_ready(jnp.ones(3) + 1)
        from ceemx.infra.runtime import limit_cpu_threads
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            limit_cpu_threads(1)
        print(any("already running" in str(x.message) for x in w))
        """
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "True"


def test_cli_threads_usage_errors(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--threads", "0", "demo", "--smoke"])
    assert e.value.code == 2
    assert "--threads: must be an integer >= 1" in capsys.readouterr().err


def test_cli_bad_threads_env_is_a_usage_error(tmp_path):
    """Exit 2 before any compute, and before JAX is imported (``-X importtime`` lists imports)."""
    env = dict(os.environ, CEEMX_THREADS="many")
    args = ["demo", "--smoke", "--out", str(tmp_path)]
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "ceemx", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert proc.returncode == 2
    assert "CEEMX_THREADS" in proc.stderr and "integer >= 1" in proc.stderr
    assert not any(tmp_path.iterdir())  # nothing computed or written
    modules = {ln.rsplit("|", 1)[-1].strip() for ln in proc.stderr.splitlines() if "|" in ln}
    assert "ceemx.cli" in modules and not modules & {"jax", "jaxlib", "equinox"}
