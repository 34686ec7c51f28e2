"""A physics model that misses a term, completed by a learned term (docs/hybrid_models.md).

The system is a Duffing oscillator, ẍ + c ẋ + k x + k₃ x³ = u, observed through its position
with noise; the model a user wrote is the *linear* oscillator (k₃ unknown to them). The script

1. fits the linear physics model (k, c) by CE-EM;
2. wraps the fit in a hybrid model — the same physics plus a zero-initialised MLP in the velocity
   equation (``ceemx.hybrid(..., dynamics=(1,))``) — and trains physics and weights together with
   weight decay and early stopping on a held-out tail of the training record;
3. scores both on a test record driven by a different input (free run from the first 20 outputs)
   and plots the learned term against the missing −k₃x³ and both test simulations.

Run (from the repository root)::

    python examples/hybrid_duffing.py                    # writes hybrid_duffing.png to --out
    python examples/hybrid_duffing.py --smoke            # a short run, used by the tests
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)  # identify in float64 (before any array is created)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jaxtyping import Array  # noqa: E402

import ceemx  # noqa: E402

DT = 0.1


class Oscillator(ceemx.AbstractContinuousSystem):
    """ẍ = −k x − k₃ x³ − c ẋ + u, y = x; k₃ is fixed (0 in the user's linear model)."""

    k: Array = ceemx.param(positive=True)
    c: Array = ceemx.param(positive=True)
    k3: Array = ceemx.param(fixed=True, default=0.0)

    @property
    def state_dim(self) -> int:
        """Position and velocity."""
        return 2

    @property
    def obs_dim(self) -> int:
        """The position."""
        return 1

    @property
    def control_dim(self) -> int:
        """The force."""
        return 1

    def vector_field(self, x, u, t):
        """(ẋ, ẍ)."""
        return jnp.stack([x[1], -self.k * x[0] - self.k3 * x[0] ** 3 - self.c * x[1] + u[0]])

    def observe(self, x, u, t):
        """The position."""
        return x[:1]


def record(system, key, T: int, freqs, amplitude: float, noise: float = 0.01):
    """A multisine-driven noisy record of ``system`` (and its true states)."""
    t = jnp.arange(T, dtype=float) * DT
    phases = jax.random.uniform(key, (len(freqs),), maxval=2 * jnp.pi)
    u = amplitude * sum(jnp.sin(f * t + p) for f, p in zip(freqs, phases, strict=True))
    u = u[None, :, None] / len(freqs) ** 0.5

    def step(x, ut):
        return system.dynamics(x, ut, 0.0), x

    x = jax.lax.scan(step, jnp.zeros(2), u[0])[1][None]
    y = x[..., :1] + noise * jax.random.normal(jax.random.fold_in(key, 1), x[..., :1].shape)
    return ceemx.Trajectories(y, u), x


def main(argv=None) -> dict:
    """Run the example; returns the test RMSEs of both models."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=".", help="folder for hybrid_duffing.png")
    parser.add_argument("--smoke", action="store_true", help="short records, few iterations")
    args = parser.parse_args(argv)
    T, epochs = (300, 5) if args.smoke else (1200, 60)

    truth = Oscillator(1.0, 0.3, 1.0, dt=DT, process_noise=1e-3, obs_noise=0.01)
    key_train, key_test = jax.random.split(jax.random.PRNGKey(0))
    train, _ = record(truth, key_train, T, (0.5, 0.9, 1.7, 2.9), 3.0)
    test, x_test = record(truth, key_test, 600, (0.6, 1.3, 2.3), 2.5)

    # 1. the user's physics model: linear, k₃ = 0 (a guess of k and c off by 30 %)
    guess = Oscillator(1.3, 0.2, 0.0, dt=DT, process_noise=1e-3, obs_noise=0.01)
    t0 = time.perf_counter()
    physics = ceemx.fit(guess, train, solver=ceemx.JointLM(), max_epochs=50, diagnose=False)
    t_physics = time.perf_counter() - t0

    # 2. physics + a learned term in the velocity equation, early stopping on the last fifth
    cut = int(0.8 * T)
    fit_data, validation = train[:, :cut], train[:, cut - 20 :]
    model = ceemx.hybrid(
        physics.system, fit_data, states=physics.states[:, :cut], dynamics=(1,), width=16
    )
    stopper = ceemx.EarlyStopping(validation, n_init=20, patience=8, start=model)
    t0 = time.perf_counter()
    fitted = ceemx.fit(
        model,
        fit_data,
        physics.states[:, :cut],
        solver=ceemx.JointLM(),
        trainable=model.trainable("both"),
        log_prior=ceemx.weight_decay,
        max_epochs=epochs,
        callbacks=[stopper],
        diagnose=False,
    )
    hybrid = stopper.restore(fitted).system
    t_hybrid = time.perf_counter() - t0

    # 3. held-out test record: free run from the first 20 outputs
    scores = {
        name: ceemx.benchmark_score(s, test, 20)
        for name, s in (("physics", physics.system), ("hybrid", hybrid))
    }
    rmse = {name: float(s.rmse[0, 0]) for name, s in scores.items()}
    grid = jnp.linspace(float(x_test[..., 0].min()), float(x_test[..., 0].max()), 101)
    states = jnp.stack([grid, jnp.zeros_like(grid)], axis=-1)
    u0 = jnp.zeros((1,))
    linear_error = jax.vmap(
        lambda x: hybrid.physics.vector_field(x, u0, 0.0)[1] - truth.vector_field(x, u0, 0.0)[1]
    )(states)
    learned = jax.vmap(lambda x: hybrid.dynamics_term(x, u0)[1])(states)
    print(f"physics fit: k = {float(physics.system.k):.4f}, c = {float(physics.system.c):.4f} "
          f"({t_physics:.1f} s)")  # fmt: skip
    print(f"hybrid: best epoch {stopper.best_epoch} of {len(fitted.history)}, validation RMSE "
          f"{stopper.best_rmse:.4f} ({t_hybrid:.1f} s); k = {float(hybrid.physics.k):.4f}, "
          f"c = {float(hybrid.physics.c):.4f}")  # fmt: skip
    print(f"test free-run RMSE: physics {rmse['physics']:.4f}, hybrid {rmse['hybrid']:.4f} "
          f"(measurement noise 0.01)")  # fmt: skip
    gap = float(jnp.sqrt(jnp.mean((learned + linear_error) ** 2)))
    missing = float(jnp.sqrt(jnp.mean(linear_error**2)))
    print(f"learned term vs the missing physics over the test range: RMS gap {gap:.4f} "
          f"(RMS of the missing term {missing:.4f})")  # fmt: skip

    from ceemx.evaluation import report

    plt = report.plt()
    fig, (ax_f, ax_y) = plt.subplots(1, 2, figsize=(11, 3.6))
    ax_f.plot(grid, -linear_error, "k", lw=1.5, label="missing: truth − physics model")
    ax_f.plot(grid, learned, "C1--", lw=1.5, label="learned term N(x, ẋ = 0, u = 0)")
    ax_f.set_xlabel("position x")
    ax_f.set_ylabel("velocity-equation term")
    ax_f.legend(fontsize=8)
    ax_f.set_title("what the physics model misses, and what was learned", fontsize=9)
    t = np.arange(test.num_steps) * DT
    ax_y.plot(t, np.asarray(test.y[0, :, 0]), "k", lw=0.8, label="measured (test)")
    for name, s in scores.items():
        ax_y.plot(t, np.asarray(s.y_sim[0, :, 0]), lw=0.9,
                  label=f"{name} free run (RMSE {rmse[name]:.3f})")  # fmt: skip
    ax_y.set_xlabel("time [s]")
    ax_y.legend(fontsize=8, loc="upper right")
    ax_y.set_title("held-out test record (different input)", fontsize=9)
    fig.tight_layout()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report.save_figure(fig, out / "hybrid_duffing.png")
    plt.close(fig)
    return rmse


if __name__ == "__main__":
    main()
