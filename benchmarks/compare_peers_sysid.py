"""Parameter estimation on the Table-1 setting: ceemx against EKF-likelihood and output-error fits.

Problem (paper §4.1.1, ``ceemx.experiments.table1``): one Lorenz attractor, y = C x + v with a
known C ∈ R^{2×3} (``PRNGKey(4)``), RK4, dt = 0.04, T = 128, one trajectory per seed,
x₁ ~ N((−6, −6, 24), 2.5² I), process noise σ_w, observation noise σ_v (the rows of Table 1);
θ = (σ, ρ, β) is estimated from the starting guess θ·(1 + U(−0.1, 0.1)) that
``common.lorenz_problem`` draws per seed. Every method sees the same data and the same start θ:

- ``ceemx``: ``warm_start`` then ``ceemx.fit(..., solver=ceemx.JointLM())`` with the likelihood
  weighting (process noise σ_w, observation noise σ_v; ``table1.fit_one`` with
  ``method="joint"``), ≤ 100 iterations, ``rtol = 1e-10``. The time covers warm start + fit.
- ``ekf_lbfgs``: maximum likelihood under the extended Kalman filter's marginal likelihood
  (dynamax ``extended_kalman_filter(...).marginal_loglik``, prior N((−6, −6, 24), 2.5² I), Q =
  σ_w² I, R = σ_v² I at their true values), over log θ (positivity), by ``optax.lbfgs`` (zoom line
  search, memory 10) in one jitted ``lax.while_loop``: ≤ 200 iterations, stop when the gradient
  norm of the per-observation negative log-likelihood falls below 1e-9. One compile serves all
  settings and seeds (the data, start and noise scales are arguments).
- ``jax_sysid``: Bemporad's ``jax_sysid.models.Model`` (nx = 3, ny = 2, a zero input nu = 1),
  state function = the same RK4 Lorenz step with θ as its parameter, output C x, fitted by
  output-error (simulation-error) minimisation, ``sum((ŷ − y)²)/T``, with its L-BFGS-B
  (``jaxopt.ScipyMinimize``, ≤ 1000 iterations, no Adam phase), training x₁ too, started from
  ceemx's warm-start state at t = 1 (the same information ceemx starts from). Its L2
  regularisations are switched off (``rho_th = rho_x0 = 0``): the defaults 0.01 / 0.001 would
  pull θ and x₁ toward 0 against a data term of ≈ 2 σ_v². jax-sysid builds and jits its loss
  inside ``fit``, so every call compiles again: its "steady" time includes a compile.

Reported per method, setting and seed: the estimates of σ, ρ, β, their relative errors,
iterations, time of each call. Per method: the first call in the process (compile included) and
the steady median over the other calls (calls alternate between methods; the first seed of each
setting is repeated ``--reps`` times). A peer that is not importable is skipped with a message and
recorded under ``"absent"``. Results: ``benchmarks/results/compare_peers_sysid.json``.

    bash benchmarks/peers/setup.sh
    benchmarks/peers/.venv/bin/python benchmarks/compare_peers_sysid.py [--smoke] [--out FILE]

(``--smoke``: one setting, one seed, one repetition.)

Backs: ``benchmarks/README.md`` (parameter estimation against EKF-likelihood L-BFGS and
jax-sysid), ``README.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import pathlib
import re
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common, table1  # noqa: E402
from ceemx.identification.initialize import warm_start  # noqa: E402
from ceemx.models import with_noise  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from compare_peers import _uptime, _versions  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results" / "compare_peers_sysid.json"
PARAMS = ("sigma", "rho", "beta")
TRUTH = np.asarray(common.TRUE_PARAMS, dtype=float)
T = 128
U0 = jnp.zeros((0,))


def lorenz_with(system, theta):
    """``system`` with (σ, ρ, β) = ``theta`` (a length-3 array)."""
    return eqx.tree_at(
        lambda s: (s.sigma, s.rho, s.beta), system, (theta[0:1], theta[1:2], theta[2:3])
    )


def theta_of(system) -> np.ndarray:
    return np.asarray([float(getattr(system, p)[0]) for p in PARAMS])


# ------------------------------------------------------------------------------------- ceemx


def ceemx_fit(problem, sw: float, sv: float) -> dict:
    system = with_noise(problem.init_system, sw, sv)
    x_init = warm_start(system, problem.data)
    res = ceemx.fit(
        system,
        problem.data,
        x_init,
        solver=ceemx.JointLM(rtol=1e-10),
        trainable=common.LORENZ_PARAMS,
        max_epochs=100,
        progress=False,
    )
    jax.block_until_ready(res.states)
    return {
        "theta": theta_of(res.system),
        "iterations": int(res.epochs),
        "converged": bool(res.converged),
    }


# --------------------------------------------------------------------- EKF likelihood + L-BFGS


def make_ekf_lbfgs(template, *, max_iter: int = 200, tol: float = 1e-9):
    """A jitted EKF-likelihood L-BFGS fit ``(problem, σ_w, σ_v) → record``, or ``None`` and why."""
    try:
        import optax
        import optax.tree_utils as otu
        from dynamax.nonlinear_gaussian_ssm import (  # pyright: ignore[reportMissingImports]
            ParamsNLGSSM,
            extended_kalman_filter,
        )
    except ImportError as err:
        return None, f"dynamax/optax not importable ({err})"
    prior = common.lorenz_initial_prior(1)
    m1, P1 = prior.mean, prior.noise.covariance()  # pyright: ignore[reportAttributeAccessIssue]
    n, m = template.state_dim, template.obs_dim

    def nll(z, y, sw, sv):
        system = lorenz_with(template, jnp.exp(z))
        params = ParamsNLGSSM(
            initial_mean=m1,
            initial_covariance=P1,
            dynamics_function=lambda x: system.dynamics(x, U0, 0),
            dynamics_covariance=sw**2 * jnp.eye(n),
            emission_function=lambda x: system.observe(x, U0, 0),
            emission_covariance=sv**2 * jnp.eye(m),
        )
        ll = jax.vmap(lambda yy: extended_kalman_filter(params, yy).marginal_loglik)(y)
        return -jnp.sum(ll) / y.size * m  # per observation vector

    @jax.jit
    def run(y, theta0, sw, sv):
        fun = lambda z: nll(z, y, sw, sv)  # noqa: E731
        opt = optax.lbfgs()
        value_and_grad = optax.value_and_grad_from_state(fun)
        z0 = jnp.log(theta0)

        def step(carry):
            z, state = carry
            value, grad = value_and_grad(z, state=state)
            updates, state = opt.update(grad, state, z, value=value, grad=grad, value_fn=fun)
            return optax.apply_updates(z, updates), state

        def cond(carry):
            _, state = carry
            it = otu.tree_get(state, "count")
            g = otu.tree_norm(otu.tree_get(state, "grad"))
            return (it == 0) | ((it < max_iter) & (g >= tol) & jnp.isfinite(g))

        z, state = jax.lax.while_loop(cond, step, (z0, opt.init(z0)))
        g = otu.tree_norm(otu.tree_get(state, "grad"))
        return (
            jnp.exp(jnp.asarray(z)),
            otu.tree_get(state, "count"),
            g,
            otu.tree_get(state, "value"),
        )

    def fit(problem, sw: float, sv: float) -> dict:
        th, it, g, v = run(problem.data.y, jnp.asarray(theta_of(problem.init_system)), sw, sv)
        th = np.asarray(jax.block_until_ready(th))
        return {
            "theta": th,
            "iterations": int(it),
            "converged": bool(float(g) < tol),
            "grad_norm": float(g),
            "nll_per_step": float(v),
        }

    return fit, None


# ------------------------------------------------------------------------ jax-sysid output error


def make_jax_sysid(template):
    """jax-sysid's output-error fit; ``None`` and why if absent."""
    try:
        from jax_sysid.models import Model  # pyright: ignore[reportMissingImports]
    except ImportError as err:
        return None, f"jax-sysid not importable ({err})"

    def state_fcn(x, u, params):
        return lorenz_with(template, params[0]).dynamics(x, U0, 0)

    def output_fcn(x, u, params):
        return template.observe(x, U0, 0)

    def fit(problem, sw: float, sv: float) -> dict:
        system = with_noise(problem.init_system, sw, sv)
        x1 = np.asarray(warm_start(system, problem.data)[0, 0])  # B = 1
        y = np.asarray(problem.data.y[0])
        model = Model(template.state_dim, template.obs_dim, 1, state_fcn, output_fcn)
        model.loss(rho_x0=0.0, rho_th=0.0)
        model.optimization(adam_epochs=0, lbfgs_epochs=1000, iprint=-1)
        model.init(params=[theta_of(problem.init_system)], x0=x1)
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            model.fit(y, np.zeros((y.shape[0], 1)))
        found = re.search(r"done in (\d+) iterations", buf.getvalue())
        return {
            "theta": np.asarray(model.params[0], dtype=float).reshape(-1),
            "iterations": int(found.group(1)) if found else -1,
            "converged": None,
            "loss": float(model.Jopt),
            "state_saturated": bool(model.sat_activated),
            "x1": np.asarray(model.x0).tolist(),
        }

    return fit, None


# ------------------------------------------------------------------------------------- driver


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--seeds", type=int, default=None, help="seeds 0 … N−1 (default 3; smoke 1)")
    ap.add_argument("--reps", type=int, default=None, help="repeats of the first seed (default 3)")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    seeds = list(range(args.seeds if args.seeds is not None else (1 if args.smoke else 3)))
    reps = args.reps if args.reps is not None else (1 if args.smoke else 3)
    settings = [(0.01, 0.01)] if args.smoke else list(table1.SETTINGS)
    true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=table1.M, coupling=False)

    methods, absent = {"ceemx": ceemx_fit}, {}
    for name, (fn, why) in {
        "ekf_lbfgs": make_ekf_lbfgs(true),
        "jax_sysid": make_jax_sysid(true),
    }.items():
        if fn is None:
            absent[name] = why
            print(f"{name} absent ({why}; run benchmarks/peers/setup.sh and use its Python).")
        else:
            methods[name] = fn
    load0 = os.getloadavg()[0]
    uptime0 = _uptime()
    first: dict[str, float] = {}
    steady: dict[str, list[float]] = {name: [] for name in methods}
    runs: dict = {name: {} for name in methods}
    for sw, sv in settings:
        key = f"{sw:g}/{sv:g}"
        for seed in seeds:
            problem = common.lorenz_problem(
                seed, true, B=1, T=T, sigma_w=sw, sigma_v=sv, coupling=False
            )
            start = theta_of(problem.init_system)
            calls = 1 + (reps if seed == seeds[0] else 0)
            recs: dict = {}
            for _ in range(calls):  # alternate the methods
                for name, fn in methods.items():
                    t0 = time.perf_counter()
                    try:
                        rec = fn(problem, sw, sv)
                    except Exception as err:  # a peer failing is a result, not a crash
                        rec = {"theta": np.full(3, np.nan), "error": repr(err)[:300]}
                    dt = time.perf_counter() - t0
                    if name not in first:
                        first[name] = dt
                    else:
                        steady[name].append(dt)
                    recs.setdefault(name, {**rec, "times_s": []})["times_s"].append(dt)
            for name, rec in recs.items():
                th = np.asarray(rec.pop("theta"), dtype=float)
                rel = np.abs(th - TRUTH) / TRUTH
                entry = {
                    "seed": seed,
                    **dict(zip(PARAMS, th.tolist(), strict=True)),
                    "rel_error": dict(zip(PARAMS, rel.tolist(), strict=True)),
                    "max_rel_error": float(np.max(rel)),
                    "start": dict(zip(PARAMS, start.tolist(), strict=True)),
                    **rec,
                }
                runs[name].setdefault(key, []).append(entry)
                print(
                    f"[σ_w={sw:g} σ_v={sv:g} seed={seed}] {name:9s} σ={th[0]:.4f} ρ={th[1]:.4f} "
                    f"β={th[2]:.4f} max rel err {np.max(rel):.2e} it={rec.get('iterations')} "
                    f"{rec['times_s'][-1]:.2f}s"
                    + (f" ERROR {rec['error']}" if "error" in rec else ""),
                    flush=True,
                )
    summary = {}
    for name in methods:
        errs = [e["max_rel_error"] for r in runs[name].values() for e in r]
        summary[name] = {
            "first_call_s": first.get(name),
            "steady_s_median": float(np.median(steady[name])) if steady[name] else None,
            "steady_s": steady[name],
            "max_rel_error_median": float(np.nanmedian(errs)) if errs else None,
            "max_rel_error_max": float(np.nanmax(errs)) if errs else None,
            "fits_within_1pct": int(sum(e < 0.01 for e in errs)),
            "fits": len(errs),
        }
    out = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "setting": {"T": T, "B": 1, "settings": settings, "seeds": seeds, "reps": reps},
        "truth": dict(zip(PARAMS, TRUTH.tolist(), strict=True)),
        "versions": _versions(),
        "load": [load0, os.getloadavg()[0]],
        "uptime": [uptime0, _uptime()],
        "absent": absent,
        "summary": summary,
        "runs": runs,
    }
    path = pathlib.Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: out[k] for k in ("versions", "load", "absent", "summary")}, indent=1))


if __name__ == "__main__":
    main()
