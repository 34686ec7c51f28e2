"""State estimation at known θ: ceemx's MAP smoother against two extended Kalman smoothers.

Problem: the single-Lorenz Figure-2 system (σ_w = 0.1, σ_v = 0.5, known C ∈ R^{2×3},
RK4, dt = 0.04), B = 16 trajectories of T = 128 steps drawn by ceemx, θ at the truth. All run
in one process on one JAX (the peers' environment, ``benchmarks/peers/setup.sh``), all
``jit``-compiled and ``vmap``-ped over the trajectories:

- ceemx: ``ceemx.smooth`` (batched LM on the MAP objective, block-tridiagonal solves) from the
  least-squares start ``ceemx.identification.initialize.from_observations`` (timed apart);
- dynamax: ``extended_kalman_smoother`` with the same prior N((−6, −6, 24), 2.5² I), f, g, Q, R;
- cuthbert: the linearised-moments (square-root) Kalman filter and smoother of
  ``cuthbert.gaussian.moments`` with Jacobian linearisation at the filtering / predicted means,
  i.e. the extended Kalman filter and RTS smoother, same prior, f, g, Q, R (a dummy unobserved
  x₀ whose transition returns the prior puts cuthbert's "x₀ unobserved" convention onto ours).

Reported per method: compile time (first call − steady), steady-state time (median of ≥ 5
calls, alternating the methods), RMSE of the state estimates against the simulated states, the
largest difference to ceemx's states (and cuthbert's to dynamax's: the same EKS, so ≈ 0),
ceemx's LM iterations; load (``os.getloadavg``, ``uptime``) and versions. Results:
``benchmarks/results/compare_peers.json``. A peer that is not importable (``benchmarks/peers/.venv``
absent or incomplete) is skipped with a message and listed under ``"absent"`` with the reason.
Parameter estimation against the peers is ``compare_peers_sysid.py``.

    bash benchmarks/peers/setup.sh
    benchmarks/peers/.venv/bin/python benchmarks/compare_peers.py [--smoke] [--out FILE]

Backs: ``benchmarks/README.md`` (the smoother against dynamax and cuthbert), ``README.md``.
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
from ceemx.identification.initialize import from_observations  # noqa: E402

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
        from dynamax.nonlinear_gaussian_ssm import (  # pyright: ignore[reportMissingImports]
            ParamsNLGSSM,
            extended_kalman_smoother,
        )
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


def cuthbert_smoother(system):
    """A jitted, vmapped cuthbert EKS of ``system`` and ``None``, or ``None`` and why it is absent.

    cuthbert's linearised-moments filter (``cuthbert.gaussian.moments``, square-root form) with
    the Jacobians of f at the previous filtering mean and of g at the predicted mean is the EKF, and
    its smoother (f linearised at the filtering means) the extended RTS smoother. cuthbert's filter
    starts from an unobserved x₀ and observes x₁ … x_T; ceemx and dynamax observe x₁ … x_T with
    x₁ ~ prior. We therefore prepend a dummy x₀ ~ N(0, I) whose first "transition" returns the
    prior (mean m₁, Cholesky factor of P₁, Jacobian 0) regardless of x₀, and drop x₀ afterwards.
    """
    try:
        import cuthbert  # pyright: ignore[reportMissingImports]
        from cuthbert.gaussian import moments  # pyright: ignore[reportMissingImports]
    except ImportError as err:
        return None, f"cuthbert not importable ({err})"
    u0 = jnp.zeros((0,))
    n = system.state_dim
    m1 = system.initial_prior.mean
    chol_p1 = jnp.linalg.cholesky(system.initial_prior.noise.covariance())
    chol_q = jnp.linalg.cholesky(system.process_noise.covariance())
    chol_r = jnp.linalg.cholesky(system.obs_noise.covariance())

    def dynamics_params(state, inputs):
        first = inputs["first"]

        def mean_chol(x):
            fx = system.dynamics(x, u0, 0)
            return jnp.where(first, m1, fx), jnp.where(first, chol_p1, chol_q)

        return mean_chol, state.mean

    def observation_params(state, inputs):
        def mean_chol(x):
            return system.observe(x, u0, 0), chol_r

        return mean_chol, state.mean, inputs["y"]

    filt = moments.build_filter(
        jnp.zeros(n), jnp.eye(n), dynamics_params, observation_params, associative=False
    )
    smoo = moments.build_smoother(dynamics_params)

    def one(y):
        T = y.shape[0]
        inputs = {"y": y, "first": jnp.arange(T) == 0}
        init = filt.init_prepare()
        fs = cuthbert.filter(filt, inputs, init)
        ss = cuthbert.smoother(smoo, fs)
        return ss.mean[1:]

    return jax.jit(jax.vmap(one)), None


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    jax.block_until_ready(out)
    return time.perf_counter() - t0, out


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
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

    peers, absent = {}, {}
    dyn = dynamax_smoother(system, data)
    if dyn is None:
        absent["dynamax"] = "dynamax not importable"
    else:
        peers["dynamax"] = dyn
    cut, why = cuthbert_smoother(system)
    if cut is None:
        absent["cuthbert"] = why
    else:
        peers["cuthbert"] = cut
    for name, why in absent.items():
        print(f"{name} absent ({why}; run benchmarks/peers/setup.sh and use its Python): skipped.")
    load0 = os.getloadavg()[0]
    t_init, x0 = timed(lambda: from_observations(system, data))
    first_ours, sol = timed(ours, x0)
    first = {name: timed(fn, data.y)[0] for name, fn in peers.items()}
    steady_ours: list[float] = []
    steady: dict[str, list[float]] = {name: [] for name in peers}
    for _ in range(reps):  # alternate the methods
        steady_ours.append(timed(ours, x0)[0])
        for name, fn in peers.items():
            steady[name].append(timed(fn, data.y)[0])
    rmse = lambda x: float(jnp.sqrt(jnp.mean((x - truth) ** 2)))  # noqa: E731
    out = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "setting": {"B": B, "T": T, "sigma_w": 0.1, "sigma_v": 0.5},
        "jax": jax.__version__,
        "versions": _versions(),
        "load": [load0, os.getloadavg()[0]],
        "uptime": _uptime(),
        "ceemx": {
            "compile_s": first_ours - float(np.median(steady_ours)),
            "steady_s_median": float(np.median(steady_ours)),
            "steady_s": steady_ours,
            "init_s": t_init,
            "iterations_max": int(jnp.max(sol.iterations)),
            "rmse": rmse(sol.states),
        },
        "absent": absent,
    }
    for name, fn in peers.items():
        med = float(np.median(steady[name]))
        means = fn(data.y)
        out[name] = {
            "compile_s": first[name] - med,
            "steady_s_median": med,
            "steady_s": steady[name],
            "rmse": rmse(means),
            "max_abs_diff_to_ceemx": float(jnp.max(jnp.abs(means - sol.states))),
        }
        out[f"time_ratio_ceemx_over_{name}"] = out["ceemx"]["steady_s_median"] / med
    if "dynamax" in peers and "cuthbert" in peers:  # the same EKS: the two should agree
        out["cuthbert"]["max_abs_diff_to_dynamax"] = float(
            jnp.max(jnp.abs(peers["cuthbert"](data.y) - peers["dynamax"](data.y)))
        )
    path = pathlib.Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "date"}, indent=1))


PACKAGES = ("ceemx", "jax", "dynamax", "cuthbert", "optax", "jax-sysid", "jaxopt", "scipy")


def _versions(names=PACKAGES) -> dict[str, str]:
    """Installed versions of ``names`` ("absent" when not installed)."""
    from importlib import metadata

    out = {}
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


def _uptime() -> str:
    import subprocess

    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


if __name__ == "__main__":
    main()
