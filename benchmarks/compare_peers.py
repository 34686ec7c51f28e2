"""State estimation at known θ: ceemx's MAP smoother against dynamax's extended Kalman smoother.

Problem (issue 12): the single-Lorenz Figure-2 system (σ_w = 0.1, σ_v = 0.5, known C ∈ R^{2×3},
RK4, dt = 0.04), B = 16 trajectories of T = 128 steps drawn by ceemx, θ at the truth. Both run
in one process on one JAX (the peers' environment, ``benchmarks/peers/setup.sh``), both
``jit``-compiled and ``vmap``-ped over the trajectories:

- ceemx: ``ceemx.smooth`` (batched LM on the MAP objective, block-tridiagonal solves) from the
  least-squares start ``ceemx.initialize.from_observations`` (timed apart);
- dynamax: ``extended_kalman_smoother`` with the same prior N((−6, −6, 24), 2.5² I), f, g, Q, R.

Reported per method: compile time (first call − steady), steady-state time (median of ≥ 5
calls, alternating the two methods), RMSE of the state estimates against the simulated states,
ceemx's LM iterations; ``uptime`` load. Results: ``benchmarks/results/compare_peers.json``.
Without dynamax (``benchmarks/peers/.venv`` absent, or not importable) the script measures
ceemx alone and says so.

    bash benchmarks/peers/setup.sh
    benchmarks/peers/.venv/bin/python benchmarks/compare_peers.py [--smoke]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.initialize import from_observations  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results" / "compare_peers.json"


def problem(B: int, T: int):
    true = common.true_lorenz(
        1, key=jax.random.PRNGKey(4), m=2, coupling=False, process_noise=0.1, obs_noise=0.5
    )
    p = common.lorenz_problem(43, true, B=B, T=T, sigma_w=0.1, sigma_v=0.5, coupling=False)
    prior = common.lorenz_initial_prior(1)
    import equinox as eqx

    system = eqx.tree_at(lambda s: s.initial_prior, true, prior, is_leaf=lambda v: v is None)
    return system, p


def dynamax_smoother(system, data):
    """A jitted, vmapped dynamax EKS of ``system``; ``None`` when dynamax is absent."""
    try:
        from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM, extended_kalman_smoother
    except ImportError:
        return None
    u0 = jnp.zeros((0,))
    n = system.state_dim
    params = ParamsNLGSSM(
        initial_mean=system.initial_prior.mean,
        initial_covariance=system.initial_prior.noise.covariance(),
        dynamics_function=lambda x: system.dynamics(x, u0, 0),
        dynamics_covariance=system.process_noise.covariance(),
        emission_function=lambda x: system.observe(x, u0, 0),
        emission_covariance=system.obs_noise.covariance(),
    )
    del n

    @jax.jit
    def run(y):
        return jax.vmap(lambda yy: extended_kalman_smoother(params, yy).smoothed_means)(y)

    return run


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    jax.block_until_ready(out)
    return time.perf_counter() - t0, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    B, T = (2, 32) if args.smoke else (16, 128)
    reps = 2 if args.smoke else max(args.reps, 5)
    system, p = problem(B, T)
    data, truth = p.data, p.states
    smoother = ceemx.LMSmoother()

    def ours(x0):
        return ceemx.smooth(system, data, x0, smoother)

    peer = dynamax_smoother(system, data)
    if peer is None:
        print("dynamax absent (run benchmarks/peers/setup.sh and use its Python): ceemx only.")
    load0 = os.getloadavg()[0]
    t_init, x0 = timed(lambda: from_observations(system, data))
    first_ours, sol = timed(ours, x0)
    first_peer = None
    if peer is not None:
        first_peer, _ = timed(peer, data.y)
    steady_ours, steady_peer = [], []
    for _ in range(reps):
        steady_ours.append(timed(ours, x0)[0])
        if peer is not None:
            steady_peer.append(timed(peer, data.y)[0])
    rmse = lambda x: float(jnp.sqrt(jnp.mean((x - truth) ** 2)))  # noqa: E731
    out = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "setting": {"B": B, "T": T, "sigma_w": 0.1, "sigma_v": 0.5},
        "jax": jax.__version__,
        "load": [load0, os.getloadavg()[0]],
        "ceemx": {
            "compile_s": first_ours - float(np.median(steady_ours)),
            "steady_s_median": float(np.median(steady_ours)),
            "steady_s": steady_ours,
            "init_s": t_init,
            "iterations_max": int(jnp.max(sol.iterations)),
            "rmse": rmse(sol.states),
        },
    }
    if peer is not None:
        means = peer(data.y)
        out["dynamax"] = {
            "compile_s": first_peer - float(np.median(steady_peer)),
            "steady_s_median": float(np.median(steady_peer)),
            "steady_s": steady_peer,
            "rmse": rmse(means),
        }
        out["time_ratio_ceemx_over_dynamax"] = (
            out["ceemx"]["steady_s_median"] / out["dynamax"]["steady_s_median"]
        )
    path = pathlib.Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "date"}, indent=1))


if __name__ == "__main__":
    main()
