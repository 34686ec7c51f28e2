"""Run the authors' CE-EM (`ceem` 0.0.4) on a problem that ceemx generated and saved (`.npz`).

Run with the reference environment's Python (``benchmarks/reference/setup.sh``)::

    benchmarks/reference/.venv/bin/python benchmarks/reference/run_reference.py PROBLEM.npz OUT.json

The problem file holds ``seeds`` and, per seed under ``seed{s}/``, ``y`` (B, T, m), ``C``
(m, 3), ``dt``, ``theta0`` (σ, ρ, β) — the initial guess — ``truth`` (σ, ρ, β), ``wstd``,
``ystd``, ``max_epochs``. The fit follows the authors'
single-Lorenz script (``experiments/lorenz/comp_ceem.py`` of sisl/CEEM) through their package's
API (the released 0.0.4 criteria take inverse covariances, no system): explicit-midpoint
``LorenzAttractor``; per trajectory a smoothing criterion of unit-weight
observations and dynamics weighted ``wstd/ystd``, SciPy trust-region least squares with
``tr_rho = 0.001``; learning on the dynamics criterion by Nelder–Mead with ``tr_rho = 0.01``;
states started at zero; stop when the last 10 epochs' parameter errors span < 1e-4 or at
``max_epochs``. Writes (σ, ρ, β) and the wall time after every epoch, and the whole time.
"""

import json
import sys
import time

import numpy as np
import torch
from ceem import logger
from ceem.ceem import CEEM
from ceem.opt_criteria import (
    GaussianDynamicsCriterion,
    GaussianObservationCriterion,
    GroupSOSCriterion,
)
from ceem.systems import LorenzAttractor
from torch.nn.utils import parameters_to_vector


def fit_one(d) -> dict:
    """One identification of the problem arrays ``d``; the per-epoch record."""
    import tempfile

    logger.setup(tempfile.mkdtemp(prefix="ceem-ref-"), format_strs=["csv"], action="d")
    y = torch.tensor(d["y"])
    B, T, _ = y.shape
    C = torch.tensor(d["C"])
    s0, r0, b0 = (torch.tensor([float(v)]) for v in d["theta0"])
    system = LorenzAttractor(s0, r0, b0, C, float(d["dt"]), method="midpoint")
    truth = torch.tensor(d["truth"], dtype=torch.float64)
    wstd, ystd = float(d["wstd"]), float(d["ystd"])
    t = torch.arange(T, dtype=torch.float64).unsqueeze(0).repeat(B, 1)
    smoothing = []
    for b in range(B):
        obs = GaussianObservationCriterion(torch.ones(C.shape[0]), t[b : b + 1], y[b : b + 1])
        dyn = GaussianDynamicsCriterion(wstd / ystd * torch.ones(3), t[b : b + 1])
        smoothing.append(GroupSOSCriterion([obs, dyn]))
    learning = [GaussianDynamicsCriterion(torch.ones(3), t)]
    params = [list(system.parameters())]

    record = {"params": [], "epoch_s": []}
    errors: list[float] = []
    clock = {"t": time.perf_counter()}

    def on_epoch(epoch):
        now = time.perf_counter()
        record["epoch_s"].append(now - clock["t"])
        clock["t"] = now
        record["params"].append([float(system._sigma), float(system._rho), float(system._beta)])

    def stop(epoch) -> bool:
        err = float((parameters_to_vector(system.parameters()) - truth).norm())
        errors.append(err)
        last = errors[-10:]
        return len(errors) > 10 and abs(min(last) - max(last)) < 1e-4

    ceem = CEEM(smoothing, learning, params, ["scipy_minimize"], [on_epoch], stop)
    x0 = torch.zeros(B, T, 3)
    t0 = time.perf_counter()
    clock["t"] = t0
    ceem.train(
        xs=x0,
        sys=system,
        nepochs=int(d["max_epochs"]),
        smooth_solver_kwargs={"verbose": 0, "tr_rho": 0.001},
        learner_opt_kwargs={"method": "Nelder-Mead", "tr_rho": 0.01},
    )
    record["total_s"] = time.perf_counter() - t0
    record["epochs"] = len(record["params"])
    return record


def main(problem_path: str, out_path: str) -> None:
    """Fit every problem of the file (keys ``seed{i}/...``) in turn and write their records."""
    torch.set_default_dtype(torch.float64)
    data = np.load(problem_path)
    seeds = [int(s) for s in data["seeds"]]
    out = {}
    for seed in seeds:
        d = {k.split("/", 1)[1]: data[k] for k in data.files if k.startswith(f"seed{seed}/")}
        out[str(seed)] = fit_one(d)
    with open(out_path, "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
