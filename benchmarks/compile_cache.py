"""Compile time of a 2-state gray-box fit and of the initial-state estimation, with and without
JAX's persistent compilation cache (issue 13).

Usage (one process per measurement; the first ``cache`` run fills the folder, later ones reuse it)::

    python benchmarks/compile_cache.py nocache
    python benchmarks/compile_cache.py cache /tmp/ceemx-jax-cache   # fills the cache
    python benchmarks/compile_cache.py cache /tmp/ceemx-jax-cache   # warm

Each run fits the friction model of ``tests/test_joint_guard.py`` (Coulomb + viscous friction,
velocity hidden, 2000 samples, 30 Alternating epochs) twice in the same process and estimates
its initial state twice: first minus second is the compile time. Record ``uptime`` beside it.

Backs: ``docs/results.md`` ("Gray-box CE-EM on real benchmarks", compile time: "without the cache
the first fit takes 9.7 s ... with the cache warm 5.2 s").
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import ceemx  # noqa: E402


class Friction(ceemx.AbstractContinuousSystem):
    """m ẍ = u − k x − c ẋ − F_c tanh(ẋ/ε), m = 1, positive k, c, F_c."""

    k: jax.Array = ceemx.param(positive=True)
    c: jax.Array = ceemx.param(positive=True)
    fc: jax.Array = ceemx.param(positive=True)

    @property
    def state_dim(self) -> int:
        """N = 2 (position, velocity)."""
        return 2

    @property
    def obs_dim(self) -> int:
        """M = 1 (position)."""
        return 1

    @property
    def control_dim(self) -> int:
        """P = 1 (force)."""
        return 1

    def vector_field(self, x, u, t):
        """The friction oscillator."""
        pos, vel = x
        return jnp.stack([vel, u[0] - self.k * pos - self.c * vel - self.fc * jnp.tanh(vel / 0.01)])

    def observe(self, x, u, t):
        """The position."""
        return x[:1]


def make(k: float, c: float, fc: float) -> Friction:
    """The model with process noise (1e-4, 1e-3) and observation noise 1e-3, dt = 0.01."""
    return Friction(
        k=jnp.asarray(k),
        c=jnp.asarray(c),
        fc=jnp.asarray(fc),
        dt=0.01,
        process_noise=jnp.array([1e-4, 1e-3]),
        obs_noise=1e-3,
    )


def main(argv: list[str]) -> None:
    """Time the fits and the initial-state estimation (see the module notes)."""
    mode = argv[1] if len(argv) > 1 else "nocache"
    if mode == "cache":
        print("cache folder:", ceemx.enable_compilation_cache(argv[2] if len(argv) > 2 else None))
    T = 2000
    u = np.repeat(np.random.default_rng(0).normal(0, 2.0, (T // 50, 1)), 50, axis=0)[None]
    _, data = ceemx.simulate(
        make(4.0, 0.5, 0.3), jax.random.PRNGKey(0), jnp.zeros((1, 2)), T, u=jnp.asarray(u)
    )
    guess = make(2.0, 1.0, 0.1)
    t = [time.perf_counter()]
    result = ceemx.fit(guess, data, solver=ceemx.Alternating(), max_epochs=30)
    t.append(time.perf_counter())
    ceemx.fit(guess, data, solver=ceemx.Alternating(), max_epochs=30)
    t.append(time.perf_counter())
    ceemx.estimate_initial_state(result.system, data, 50)
    t.append(time.perf_counter())
    ceemx.estimate_initial_state(result.system, data, 50)
    t.append(time.perf_counter())
    d = np.diff(t)
    print(
        f"{mode}: fit first {d[0]:.2f} s, second {d[1]:.2f} s (compile ≈ {d[0] - d[1]:.2f} s); "
        f"initial state first {d[2]:.2f} s, second {d[3]:.3f} s"
    )


if __name__ == "__main__":
    main(sys.argv)
