"""The persistent compilation cache: opt-in, written where asked, off by the environment."""

import os
import subprocess
import sys

import pytest

from ceemx.infra.compilation import default_cache_dir, enable_compilation_cache

_SCRIPT = """
import sys
import jax, jax.numpy as jnp
from ceemx.infra.compilation import enable_compilation_cache
print(enable_compilation_cache(sys.argv[1], min_compile_time_s=0.0))
f = jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + 1.0)
print(float(f(jnp.ones((3, 3))).sum()))
"""


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
