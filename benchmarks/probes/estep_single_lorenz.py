"""Alternating's partial E-step on the single-Lorenz fits of ``compare_reference.py`` (issue 23).

    python benchmarks/probes/estep_single_lorenz.py [--passes 2]

The five problems of ``benchmarks/compare_reference.py`` (seeds 43–47, B = 4, T = 128, explicit
midpoint, σ_w = 0.1, σ_v = 0.5, guesses θ·(1 + U(−0.1, 0.1))), fitted in one process by
``Alternating()`` (its default smoother, ``LMSmoother(max_steps=2)``) and by
``Alternating(smoother=LMSmoother())`` (smoothing to convergence every epoch), each pass
alternating the two. Prints per variant the median fit time (the first fit of the process left
out: it compiles), and from the last pass the epochs, convergence, final J and θ of each seed.

Backs: ``benchmarks/README.md`` ("Issue 23 on a quiet machine": the partial E-step on the
single-Lorenz fits — the same epochs, J and θ, median fit 0.642 → 0.564 s) and the
``Alternating`` docstring.
"""

import argparse
import os
import pathlib
import sys
import tempfile
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
import compare_reference as cr  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--passes", type=int, default=2)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    path = pathlib.Path(tempfile.mkdtemp()) / "problems.npz"
    seeds = list(range(43, 48))
    cr.make_problems(path, seeds, 4, 128, 100)
    data = np.load(path)
    true = common.true_lorenz(
        1, key=jax.random.PRNGKey(4), m=2, coupling=False, integrator="midpoint"
    )
    variants = {
        "partial E-step: Alternating()": ceemx.Alternating(),
        "full E-step: LMSmoother()": ceemx.Alternating(smoother=ceemx.LMSmoother()),
    }
    rows: dict[str, list] = {name: [] for name in variants}
    print(f"load {os.getloadavg()[0]:.2f}")
    for p in range(args.passes):
        for name, solver in variants.items():
            for s in seeds:
                th = data[f"seed{s}/theta0"]
                guess = ceemx.systems.CoupledLorenz(
                    *(jnp.asarray([v]) for v in th[:3]),
                    true.C,
                    dt=true.dt,
                    integrator="midpoint",
                    process_noise=cr.SIGMA_W,
                    obs_noise=cr.SIGMA_V,
                )
                t0 = time.perf_counter()
                res = ceemx.fit(
                    guess,
                    ceemx.Trajectories(jnp.asarray(data[f"seed{s}/y"])),
                    solver=solver,
                    trainable=common.LORENZ_PARAMS,
                    max_epochs=100,
                    progress=False,
                )
                res.states.block_until_ready()
                theta = [float(res.system.sigma[0]), float(res.system.rho[0]),
                         float(res.system.beta[0])]  # fmt: skip
                rows[name].append(
                    (
                        p,
                        s,
                        time.perf_counter() - t0,
                        res.epochs,
                        res.converged,
                        float(res.history[-1]["J"]),
                        theta,
                    )  # fmt: skip
                )
    for name, rs in rows.items():
        warm = [r[2] for r in rs if (r[0], r[1]) != (0, seeds[0])]
        last = [r for r in rs if r[0] == args.passes - 1]
        print(f"{name}: median fit {np.median(warm):.3f} s; epochs {[r[3] for r in last]}; "
              f"converged {[r[4] for r in last]}")  # fmt: skip
        print("   J", [round(r[5], 4) for r in last])
        print("   θ", [[round(x, 3) for x in r[6]] for r in last])
    print(f"load {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
