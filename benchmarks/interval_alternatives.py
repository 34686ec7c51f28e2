"""Two alternatives to the default fit's printed intervals, measured on the bank's records.

The default path's Laplace finish holds the learned noise fixed, so its Wald intervals are
conditional on it. Two ways to widen them were measured on the default-fit bank's
configurations (``benchmarks/default_fit_bank.py``: the same data, starts and noise guesses):

- ``noise-cov``: the default fit, then the θ block of the inverse Hessian of the Laplace
  log-evidence over θ *and* the noise log-scales (process, then process and observation),
  beside the θ-only one the summary prints — do the intervals carry the noise's uncertainty?
- ``sigma-w``: the default fit, then the process noise the evidence learns at its θ with the
  observation noise at the value the fit held and at values on its plateau — how far holding
  σ_v at its margin's loose end lowers σ_w.
- ``bootstrap``: Laplace EM at the true noise, then ``--boot`` refits of records simulated from
  the estimate (x₁ at its smoothed value) from the estimate; the refits' SD as the standard
  error, beside the Wald one — is a parametric bootstrap better calibrated?

Per seed: estimates, both standard errors and the z-scores (estimate − truth) / SE; at the end
the coverage of est ± 1.96 SE and the RMS z of each, over the seeds (a fit that stops at
another maximum — |z| > 10 — is left out of the RMS and said so).

Usage::

    python benchmarks/interval_alternatives.py noise-cov --model lorenz --seeds 0-20
    python benchmarks/interval_alternatives.py bootstrap --model lorenz --seeds 0-20 --boot 40
    python benchmarks/interval_alternatives.py sigma-w --model lorenz --seeds 10-16

Backs: ``docs/decisions.md`` ("After LaplaceEM the covariance is the evidence's observed
information").
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import ceemx  # noqa: E402
from ceemx.identification.analysis.uncertainty import (  # noqa: E402
    evidence_covariance,
    standard_errors_by_name,
)
from ceemx.identification.problem import FitProblem  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import default_fit_bank as bank  # noqa: E402


def _noise_cov(cfg, data, system) -> dict[str, list[float]]:
    """Standard errors of the default fit: θ only, with σ_w, with σ_w and σ_v in the Hessian."""
    r = ceemx.fit(system, data, progress=False)
    est = r.parameter_estimates()
    ses = {}
    for label, extra in (
        ("theta", ()),
        ("+w", ("process_noise",)),
        ("+w+v", ("process_noise", "obs_noise")),
    ):

        def where(s, extra=extra):
            return (*(getattr(s, p) for p in cfg.params), *(getattr(s, f) for f in extra))

        problem, theta = FitProblem.create(r.system, data, trainable=where)
        cov = evidence_covariance(
            problem, theta, r.states, None, getattr(r.solver, "smoother", None)
        )
        named = standard_errors_by_name(problem, theta, cov)
        ses[label] = [named[p][1] for p in cfg.params]
    return {"est": [est[p][0] for p in cfg.params], **ses}


def _sigma_w(cfg, data, system) -> None:
    """Print the process noise the evidence learns at the default fit's θ for given σ_v."""
    from ceemx.models.system import with_noise

    r = ceemx.fit(system, data, progress=False)
    held = float(np.sqrt(np.asarray(r.system.obs_noise.covariance())[0, 0]))
    row = []
    for sv in (held, 0.02, 0.01, 0.005, 0.001):
        trial = with_noise(r.system, obs_noise=sv)
        est, _, _ = ceemx.estimate_noise(trial, data, r.states, fields=("process_noise",))
        row.append((round(sv, 4), round(float(np.sqrt(est.process_noise.covariance()[0, 0])), 4)))
    print(f"  σ_v held at {held:.4g}; (σ_v, σ_w learned at it): {row}", flush=True)


def _bootstrap(cfg, data, start, boot: int) -> dict[str, list[float]]:
    """Wald SE of Laplace EM at the true noise against the SD of ``boot`` parametric refits."""
    r = ceemx.fit(cfg.system(start), data, solver=ceemx.LaplaceEM(), progress=False)
    est = r.parameter_estimates()
    x1 = r.states[:, 0]
    draws = []
    for b in range(boot):
        _, yb = ceemx.simulate(r.system, jax.random.PRNGKey(1000 + b), x1, data.num_steps)
        rb = ceemx.fit(r.system, yb, solver=ceemx.LaplaceEM(), progress=False)
        draws.append([rb.parameter_estimates()[p][0] for p in cfg.params])
    return {
        "est": [est[p][0] for p in cfg.params],
        "theta": [est[p][1] for p in cfg.params],
        "bootstrap": list(np.std(np.asarray(draws), axis=0, ddof=1)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("check", choices=("noise-cov", "bootstrap", "sigma-w"))
    ap.add_argument("--model", default="lorenz", choices=list(bank.CONFIGS))
    ap.add_argument("--seeds", default="0-20", help="a-b, inclusive")
    ap.add_argument("--boot", type=int, default=40)
    args = ap.parse_args()
    cfg = bank.CONFIGS[args.model]
    lo, hi = (int(s) for s in args.seeds.split("-"))
    truth = np.asarray([cfg.true[p] for p in cfg.params])
    z: dict[str, list[np.ndarray]] = {}
    for seed in range(lo, hi + 1):
        data, system, start, _ = bank.problem(cfg, seed, "alternate")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if args.check == "sigma-w":
                print(f"seed {seed}:")
                _sigma_w(cfg, data, system)
                continue
            row = (
                _noise_cov(cfg, data, system)
                if args.check == "noise-cov"
                else _bootstrap(cfg, data, start, args.boot)
            )
        est = np.asarray(row.pop("est"))
        print(f"seed {seed}: estimate {np.round(est, 5).tolist()}", flush=True)
        for label, se in row.items():
            zs = (est - truth) / np.asarray(se)
            z.setdefault(label, []).append(zs)
            print(f"  SE {label}: {np.round(se, 6).tolist()}  z {np.round(zs, 2).tolist()}")
    if not z:
        return
    print(f"\n{args.check}, {args.model}, seeds {args.seeds}: per parameter {list(cfg.params)}")
    for label, rows in z.items():
        zs = np.asarray(rows)
        kept = np.all(np.abs(zs) < 10, axis=1)
        cover = np.mean(np.abs(zs) < 1.96, axis=0)
        rms = np.sqrt(np.mean(zs[kept] ** 2, axis=0))
        print(
            f"  {label:>9}: coverage {np.round(100 * cover).astype(int).tolist()} %, RMS z "
            f"{np.round(rms, 3).tolist()} ({int((~kept).sum())} seed(s) at another maximum left "
            "out of the RMS)"
        )


if __name__ == "__main__":
    main()
