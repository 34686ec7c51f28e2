"""ceemx against the authors' code (`ceem` 0.0.4) on identical problems, side by side.

Single-Lorenz identification end to end on the paper's Figure-2 setting (σ_w = 0.1, σ_v = 0.5,
B = 4, T = 128, dt = 0.04, explicit-midpoint integration as the authors' Lorenz class, x₁ ~
N((−6, −6, 24), 5 I) as their script, a known C ∈ R^{2×3}, initial guess θ·(1 + U(−0.1, 0.1))):
ceemx generates the data and the initial guesses (5 seeds) and saves them (``.npz``); then, for
each of ``--reps`` repetitions, alternately

- the reference: one process of the reference environment fits the 5 problems with the authors'
  protocol (``benchmarks/reference/run_reference.py``);
- ceemx: one fresh process (cold: import and JIT compile included, no persistent compilation
  cache) fits the same 5 problems with ``JointLM`` and with ``Alternating`` (Algorithm 1, LM
  learner), the likelihood weighting (the true noise scales).

Reported: per-fit wall time (median over seeds × repetitions; ceemx's first fit of a process
apart — it carries the compile — and the process wall time with imports), the ratio reference /
ceemx, and the estimates of each. ``uptime`` load before and after each run is recorded; the
machine is shared. Results: ``benchmarks/results/compare_reference.json``.

    bash benchmarks/reference/setup.sh                 # once: the reference environment
    python benchmarks/compare_reference.py             # 5 seeds × 3 repetitions
    python benchmarks/compare_reference.py --smoke     # seconds; skips the reference if absent

``--cache DIR``: ceemx's persistent compilation cache in DIR; run twice (the first run fills it)
for the warm-cache first fit, written to ``benchmarks/results/compare_reference_warm_cache.json``.

``authors-protocol``: Table 1's seed 0 (σ_w = 0.001, σ_v = 0.01, the paper's weighting) fitted by
ceemx's Algorithm 1 with the authors' protocol one ingredient at a time — integrator, x₁ spread,
learner (LM, Nelder–Mead, Nelder–Mead at 1e-12), ρ_θ, ρ_x — from warm-started states; each line
prints epochs, σ, ρ, β and the final J (no reference needed)::

    python benchmarks/compare_reference.py authors-protocol

Backs: ``benchmarks/README.md`` (the single-Lorenz rows against the authors' code), ``README.md``,
``docs/results.md`` (Table 1 under the authors' protocol).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
REF_PYTHON = HERE / "reference" / ".venv" / "bin" / "python"
REF_DRIVER = HERE / "reference" / "run_reference.py"
RESULTS = HERE / "results" / "compare_reference.json"
RESULTS_WARM = HERE / "results" / "compare_reference_warm_cache.json"
SIGMA_W, SIGMA_V = 0.1, 0.5
X1_STD = 5.0**0.5  # the authors' Px0 = 5 I


def load() -> float:
    """The 1-minute load average."""
    return float(os.getloadavg()[0])


def make_problems(path: pathlib.Path, seeds, B: int, T: int, max_epochs: int) -> None:
    """ceemx draws the data and initial guesses; both implementations read this file."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from ceemx.experiments import common

    true = common.true_lorenz(
        1, key=jax.random.PRNGKey(4), m=2, coupling=False, integrator="midpoint"
    )
    arrays = {"seeds": np.asarray(seeds)}
    for s in seeds:
        p = common.lorenz_problem(
            s, true, B=B, T=T, sigma_w=SIGMA_W, sigma_v=SIGMA_V, coupling=False, x1_std=X1_STD
        )
        g = p.init_system
        arrays.update(
            {
                f"seed{s}/y": np.asarray(p.data.y),
                f"seed{s}/C": np.asarray(true.C),
                f"seed{s}/dt": np.asarray(true.dt),
                f"seed{s}/theta0": np.asarray([g.sigma[0], g.rho[0], g.beta[0]]),
                f"seed{s}/truth": np.asarray([10.0, 28.0, 8.0 / 3.0]),
                f"seed{s}/wstd": np.asarray(SIGMA_W),
                f"seed{s}/ystd": np.asarray(SIGMA_V),
                f"seed{s}/max_epochs": np.asarray(max_epochs),
            }
        )
    np.savez(path, **arrays)


def ceemx_worker(problem_path: str, out_path: str) -> None:
    """(In a fresh process.) Fit every problem with JointLM and Alternating; per-fit times."""
    t_start = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import ceemx
    from ceemx.experiments import common
    from ceemx.models import with_noise

    if os.environ.get("CEEMX_BENCH_FAST_COMPILE") == "1":  # before JAX's first computation
        from ceemx.infra.compilation import use_fast_compilation

        use_fast_compilation()
    cache = os.environ.get("CEEMX_BENCH_CACHE")
    if cache:  # a persistent compilation cache (a second run finds the programs compiled)
        ceemx.enable_compilation_cache(cache)
    t_import = time.perf_counter() - t_start
    data = np.load(problem_path)
    out: dict = {"import_s": t_import}
    true = common.true_lorenz(
        1, key=jax.random.PRNGKey(4), m=2, coupling=False, integrator="midpoint"
    )
    for method, solver in (("joint", ceemx.JointLM()), ("alternate", ceemx.Alternating())):
        fits = {}
        for s in (int(v) for v in data["seeds"]):
            y = jnp.asarray(data[f"seed{s}/y"])
            th = data[f"seed{s}/theta0"]
            guess = with_noise(
                true,
                SIGMA_W,
                SIGMA_V,
            )
            guess = ceemx.systems.CoupledLorenz(
                jnp.asarray([th[0]]),
                jnp.asarray([th[1]]),
                jnp.asarray([th[2]]),
                guess.C,
                dt=guess.dt,
                integrator="midpoint",
                process_noise=SIGMA_W,
                obs_noise=SIGMA_V,
            )
            t0 = time.perf_counter()
            res = ceemx.fit(
                guess,
                ceemx.Trajectories(y),
                solver=solver,
                trainable=common.LORENZ_PARAMS,
                max_epochs=int(data[f"seed{s}/max_epochs"]),
                progress=False,
            )
            res.states.block_until_ready()
            wall = time.perf_counter() - t0
            sys_ = res.system
            fits[str(s)] = {
                "s": wall,
                "epochs": res.epochs,
                "params": [float(sys_.sigma[0]), float(sys_.rho[0]), float(sys_.beta[0])],
            }
        out[method] = fits
    out["process_s"] = time.perf_counter() - t_start
    pathlib.Path(out_path).write_text(json.dumps(out))


def run_reference(problem: pathlib.Path, out: pathlib.Path) -> dict:
    t0 = time.perf_counter()
    proc = subprocess.run(
        [str(REF_PYTHON), str(REF_DRIVER), str(problem), str(out)],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"the reference failed:\n{proc.stderr[-4000:]}")
    rec = json.loads(out.read_text())
    return {"process_s": time.perf_counter() - t0, "fits": rec}


def run_ceemx(
    problem: pathlib.Path,
    out: pathlib.Path,
    cache: str | None = None,
    fast: bool = False,
    src: str | None = None,
) -> dict:
    env = dict(os.environ, CEEMX_COMPILATION_CACHE="0", CEEMX_BENCH_FAST_COMPILE=str(int(fast)))
    if cache:
        env["CEEMX_BENCH_CACHE"] = cache
    if src:  # ceemx from another source tree (--before-src)
        env["PYTHONPATH"] = src
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, __file__, "--worker", str(problem), str(out)], check=True, env=env
    )
    rec = json.loads(out.read_text())
    rec["wall_s"] = time.perf_counter() - t0
    return rec


def summarise(runs: list[dict], seeds) -> dict:
    truth = np.asarray([10.0, 28.0, 8.0 / 3.0])
    out: dict = {}
    ref = [r["reference"] for r in runs if r.get("reference")]
    if ref:
        times = [f["total_s"] for r in ref for f in r["fits"].values()]
        params = np.asarray([r["fits"][str(s)]["params"][-1] for r in ref[:1] for s in seeds])
        out["reference"] = {
            "fit_s_median": float(np.median(times)),
            "fit_s": times,
            "epochs": [r["fits"][str(s)]["epochs"] for r in ref[:1] for s in seeds],
            "process_s_median": float(np.median([r["process_s"] for r in ref])),
            "max_rel_error": float(np.max(np.abs(params / truth - 1))),
        }
    # "ceemx": this tree; "ceemx_before": --before-src, its keys suffixed "_before".
    for tag, sfx in (("ceemx", ""), ("ceemx_before", "_before")):
        if not all(tag in r for r in runs):
            continue
        for method in ("joint", "alternate"):
            # joint ran first in the process: the first alternate fit carries less compile
            cold = [r[tag][method][str(seeds[0])]["s"] for r in runs]
            warm = [r[tag][method][str(s)]["s"] for r in runs for s in seeds[1:]]
            params = np.asarray([runs[0][tag][method][str(s)]["params"] for s in seeds])
            out[method + sfx] = {
                "first_fit_s_median": float(np.median(cold)),
                "warm_fit_s_median": float(np.median(warm)) if warm else None,
                "epochs": [runs[0][tag][method][str(s)]["epochs"] for s in seeds],
                "max_rel_error": float(np.max(np.abs(params / truth - 1))),
            }
        out[f"ceemx_process_s_median{sfx}"] = float(np.median([r[tag]["process_s"] for r in runs]))
        out[f"ceemx_import_s_median{sfx}"] = float(np.median([r[tag]["import_s"] for r in runs]))
        if "reference" in out:
            ref_fit = out["reference"]["fit_s_median"]
            for method in ("joint", "alternate"):
                m = out[method + sfx]
                w = m["warm_fit_s_median"]
                m["speedup_warm"] = ref_fit / w if w else None
                m["speedup_first_fit"] = ref_fit / m["first_fit_s_median"]
            # End to end, a fresh process each side, imports included: the reference fits the
            # seeds once, ceemx twice (JointLM, then Alternating) — a ratio against double work.
            out[f"speedup_process{sfx}"] = (
                out["reference"]["process_s_median"] / out[f"ceemx_process_s_median{sfx}"]
            )
    return out


def authors_protocol() -> None:
    """``authors-protocol``: Table 1, seed 0, one ingredient of the authors' protocol at a time."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import ceemx
    from ceemx.experiments import common, table1
    from ceemx.identification.initialize import warm_start
    from ceemx.models import with_noise

    def run(integrator, x1_std, learner, rho_theta, rho_x, seed=0):
        true = common.true_lorenz(
            1, key=jax.random.PRNGKey(4), m=2, coupling=False, integrator=integrator
        )
        p = common.lorenz_problem(
            seed, true, B=1, T=128, sigma_w=0.001, sigma_v=0.01, coupling=False, x1_std=x1_std
        )
        s = with_noise(p.init_system, *table1.fit_noise("paper", 0.001, 0.01))
        solver = ceemx.Alternating(
            smoother=ceemx.LMSmoother(rho_x=rho_x),
            learner=learner,
            rho_theta=rho_theta,
            rtol=1e-10,
        )
        res = ceemx.fit(
            s,
            p.data,
            warm_start(s, p.data),
            solver=solver,
            trainable=common.LORENZ_PARAMS,
            max_epochs=200,
            progress=False,
        )
        t = res.system
        return (
            res.epochs,
            round(float(t.sigma[0]), 4),
            round(float(t.rho[0]), 4),
            round(float(t.beta[0]), 4),
            round(res.history[-1]["J"], 3),
        )

    LM, NM = ceemx.LMLearner(), ceemx.NelderMeadLearner()
    NM_TIGHT = ceemx.NelderMeadLearner(rtol=1e-12, atol=1e-12)
    print("rk4, 2.5, LM, 0, 0        ", run("rk4", 2.5, LM, 0.0, 0.0))
    print("midpoint, 2.5, LM, 0, 0   ", run("midpoint", 2.5, LM, 0.0, 0.0))
    print("rk4, 5, LM, 0, 0          ", run("rk4", 5.0, LM, 0.0, 0.0))
    print("rk4, 2.5, NM, 0, 0        ", run("rk4", 2.5, NM, 0.0, 0.0))
    print("rk4, 2.5, LM, 0.01, 0.001 ", run("rk4", 2.5, LM, 0.01, 0.001))
    print("rk4, 2.5, NM 1e-12, 0.01  ", run("rk4", 2.5, NM_TIGHT, 0.01, 0.001))


def main() -> None:
    if sys.argv[1:2] == ["authors-protocol"]:
        authors_protocol()
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--out", default=None, help="JSON (default by --cache: see above)")
    ap.add_argument(
        "--cache",
        default=None,
        help="ceemx's persistent compilation cache folder (default: none, every run compiles); "
        "run twice to measure a warm cache",
    )
    ap.add_argument(
        "--fast-compile",
        action="store_true",
        help="the ceemx process calls ceemx.infra.compilation.use_fast_compilation() first "
        "(what the ceemx command does)",
    )
    ap.add_argument(
        "--before-src",
        default=None,
        help="also run ceemx from this source tree in each repetition, right after the current "
        "one: before/after in the same run",
    )
    ap.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        ceemx_worker(*args.worker)
        return
    seeds = list(range(43, 43 + (1 if args.smoke else args.seeds)))
    B, T, max_epochs = (2, 32, 3) if args.smoke else (4, 128, 100)
    reps = 1 if args.smoke else max(args.reps, 1)
    have_ref = REF_PYTHON.exists()
    if not have_ref:
        print(
            f"reference environment absent ({REF_PYTHON}): run benchmarks/reference/setup.sh; "
            "measuring ceemx only."
        )
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        problem = tmp / "problems.npz"
        make_problems(problem, seeds, B, T, max_epochs)
        runs = []
        for rep in range(reps):
            rec: dict = {"rep": rep, "load_before": load()}
            if have_ref:
                rec["reference"] = run_reference(problem, tmp / f"ref{rep}.json")
            rec["ceemx"] = run_ceemx(
                problem, tmp / f"ceemx{rep}.json", args.cache, args.fast_compile
            )
            if args.before_src:  # the earlier tree, right after, in the same repetition
                rec["ceemx_before"] = run_ceemx(
                    problem,
                    tmp / f"before{rep}.json",
                    args.cache,
                    args.fast_compile,
                    args.before_src,
                )
            rec["load_after"] = load()
            runs.append(rec)
            print(f"rep {rep}: load {rec['load_before']:.2f} → {rec['load_after']:.2f}", flush=True)
    summary = summarise(runs, seeds)
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": {"cores": os.cpu_count(), "cpu": _cpu()},
        "setting": {
            "B": B,
            "T": T,
            "seeds": seeds,
            "sigma_w": SIGMA_W,
            "sigma_v": SIGMA_V,
            "reps": reps,
            "integrator": "midpoint",
            "fast_compile": bool(args.fast_compile),
            "cache": bool(args.cache),
            "before_src": args.before_src,
        },
        "summary": summary,
        "runs": runs,
    }
    out = pathlib.Path(args.out or (RESULTS_WARM if args.cache else RESULTS))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(json.dumps(summary, indent=1))


def _cpu() -> str:
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


if __name__ == "__main__":
    main()
