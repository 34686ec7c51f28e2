r"""One fit, several processes: the trajectories split over every process's devices.

Each process runs this same script on the same whole data set (here simulated from a fixed seed);
``ceemx.infra.distributed.initialize()`` joins it to the others before any JAX work, and
``fit(..., devices="all")`` splits the B trajectories over all processes' devices (B must be a
multiple of the device count). θ, J and the states equal a one-process fit's to rounding; every
process gets the whole result, process 0 prints it (and alone writes checkpoints). Run, from the
repository root::

    python -m ceemx.infra.distributed -n 2 examples/multi_process_fit.py    # two local processes
    python examples/multi_process_fit.py                                     # one process

or one command per process, on one host or several (process 0's host serves the coordinator)::

    CEEMX_COORDINATOR=host0:12355 CEEMX_NUM_PROCESSES=2 CEEMX_PROCESS_ID=0 \\
        python examples/multi_process_fit.py
    CEEMX_COORDINATOR=host0:12355 CEEMX_NUM_PROCESSES=2 CEEMX_PROCESS_ID=1 \\
        python examples/multi_process_fit.py

``--out FILE`` writes θ and J per epoch as JSON (process 0; the tests compare a two-process run
with a one-process run).
"""

from __future__ import annotations

import argparse
import json
import time

from ceemx.infra import distributed

distributed.initialize()  # before anything else touches JAX; no-op without CEEMX_* variables

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)  # identify in float64 (before any array is created)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.systems import CoupledLorenz  # noqa: E402

SOLVERS = {"joint": ceemx.JointLM, "alternate": ceemx.Alternating}


def problem(B: int, T: int):
    """A seeded Lorenz record set (σ, ρ, β = 10, 28, 8/3; two observed outputs) and a guess."""
    C = jnp.array([[1.0, 0.0, 0.0], [0.0, 0.5, 0.5]])
    one = jnp.ones((1,))
    true = CoupledLorenz(10.0 * one, 28.0 * one, 8 / 3 * one, C, process_noise=0.01, obs_noise=0.1)
    k_x1, k_sim = jax.random.split(jax.random.PRNGKey(0))
    x1 = jnp.array([[-6.0, -6.0, 24.0]]) + 2.5 * jax.random.normal(k_x1, (B, 3))
    _, data = ceemx.simulate(true, k_sim, x1, T)
    guess = CoupledLorenz(9.0 * one, 30.0 * one, 2.4 * one, C, process_noise=0.01, obs_noise=0.1)
    return guess, data


def main() -> None:
    """Fit with each solver named by --solver; process 0 prints (and writes --out)."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--solver", default="joint", help="joint, alternate or both: joint,alternate")
    ap.add_argument("-B", type=int, default=8, help="trajectories (a multiple of the devices)")
    ap.add_argument("-T", type=int, default=64, help="time steps")
    ap.add_argument("--epochs", type=int, default=10, help="max_epochs")
    ap.add_argument("--out", default=None, help="JSON file for θ and J (process 0)")
    args = ap.parse_args()

    guess, data = problem(args.B, args.T)
    main_process = distributed.is_main_process()
    out = {"processes": jax.process_count(), "devices": len(jax.devices()), "fits": {}}
    for name in args.solver.split(","):
        t0 = time.perf_counter()
        result = ceemx.fit(
            guess,
            data,
            solver=SOLVERS[name](),
            trainable=lambda s: (s.sigma, s.rho, s.beta),
            max_epochs=args.epochs,
            progress=False,
            devices="all",
        )
        seconds = time.perf_counter() - t0
        s = result.system
        assert isinstance(s, CoupledLorenz)
        out["fits"][name] = {
            "theta": np.asarray(result.theta).tolist(),
            "J": [h["J"] for h in result.history],
            "states_sum": float(np.sum(np.asarray(result.states))),
            "seconds": seconds,
            "epoch_seconds": [h["time"] for h in result.history],
        }
        if main_process:
            print(
                f"{name}: σ = {float(s.sigma[0]):.4f}, ρ = {float(s.rho[0]):.4f}, "
                f"β = {float(s.beta[0]):.4f}; J = {result.history[-1]['J']:.6f} after "
                f"{len(result.history)} epochs, {seconds:.1f} s on {jax.process_count()} "
                f"process(es), {len(jax.devices())} device(s)",
                flush=True,
            )
    if main_process and args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
