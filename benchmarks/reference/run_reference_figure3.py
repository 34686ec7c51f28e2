"""The authors' CE-EM (`ceem` 0.0.4) on ceemx's Figure-3 problem (6 coupled Lorenz), epoch by epoch.

Run with the reference environment's Python (``benchmarks/reference/setup.sh``)::

    benchmarks/reference/.venv/bin/python \
        benchmarks/reference/run_reference_figure3.py PROBLEM.npz OUT.json

The problem file (written by ``benchmarks/compare_reference_figure3.py``) is already in the
authors' state ordering (all x₁, then all x₂, then all x₃): ``y`` (B, T, m), ``C``, ``H0``,
``sigma0``/``rho0``/``beta0`` (K,), ``x_init`` (B, T, n), ``dt``, ``epochs``, and for the
time-to-ε runs ``budget_s``, ``eps_stop``, ``truth_*`` and ``test`` (the fit then also stops
after ``budget_s`` seconds or once ε(θ) ≤ ``eps_stop``). The fit follows
their ``experiments/lorenz/convergence_experiment_ceem.py`` through the 0.0.4 API: ``LorenzSystem``
with ``method="rk4"``, unit-weight observation and dynamics criteria per trajectory, smoothing by
SciPy trust-region least squares with ``tr_rho = 0.01`` in ``min(4, B)`` joblib workers, learning
of (σ, ρ, β, H) on the dynamics criterion by PyTorch L-BFGS. Writes θ and the wall time after
every epoch.
"""

import json
import pathlib
import sys
import tempfile
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
from ceem.systems import LorenzSystem


def main(problem_path: str, out_path: str) -> None:
    torch.set_default_dtype(torch.float64)
    logger.setup(tempfile.mkdtemp(prefix="ceem-ref-"), format_strs=["csv"], action="d")
    d = np.load(problem_path)
    y = torch.tensor(d["y"])
    B, T, m = y.shape
    system = LorenzSystem(
        torch.tensor(d["sigma0"]),
        torch.tensor(d["rho0"]),
        torch.tensor(d["beta0"]),
        torch.tensor(d["H0"]),
        torch.tensor(d["C"]),
        float(d["dt"]),
        method="rk4",
    )
    n = system.xdim
    t = torch.arange(T, dtype=torch.float64).unsqueeze(0).repeat(B, 1)
    smoothing = []
    for b in range(B):
        obs = GaussianObservationCriterion(torch.ones(m), t[b : b + 1], y[b : b + 1])
        dyn = GaussianDynamicsCriterion(torch.ones(n), t[b : b + 1])
        smoothing.append(GroupSOSCriterion([obs, dyn]))
    learning = [GaussianDynamicsCriterion(torch.ones(n), t)]
    params = [list(system.parameters())]
    record: dict = {"theta": [], "epoch_s": [], "eps": []}
    clock = {"t": 0.0, "stop": False}
    budget = float(d["budget_s"]) if "budget_s" in d else float("inf")
    eps_stop = float(d["eps_stop"]) if "eps_stop" in d else 0.0
    truth = None
    if "test" in d:
        sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
        from compare_reference_figure3 import epsilon  # numpy only

        truth = {k: d["truth_" + k] for k in ("sigma", "rho", "beta", "H")}

    def on_epoch(epoch):
        now = time.perf_counter()
        record["epoch_s"].append(now - clock["t"])
        clock["t"] = now
        record["theta"].append(
            {
                "sigma": system._sigmas.detach().reshape(-1).tolist(),
                "rho": system._rhos.detach().reshape(-1).tolist(),
                "beta": system._betas.detach().reshape(-1).tolist(),
                "H": system._H.detach().reshape(n, n).tolist(),
            }
        )
        if truth is not None:
            e = epsilon(record["theta"][-1], truth, d["test"])
            record["eps"].append(e)
            clock["stop"] = e <= eps_stop or now - clock["t0"] > budget

    ceem = CEEM(
        smoothing,
        learning,
        params,
        ["torch_minimize"],
        [on_epoch],
        lambda e: clock["stop"],
        parallel=min(4, B),
    )
    clock["t"] = clock["t0"] = t0 = time.perf_counter()
    ceem.train(
        xs=torch.tensor(d["x_init"]),
        sys=system,
        nepochs=int(d["epochs"]),
        smooth_solver_kwargs={"verbose": 0, "tr_rho": 0.01},
        learner_opt_kwargs={"method": "LBFGS"},
    )
    record["total_s"] = time.perf_counter() - t0
    with open(out_path, "w") as f:
        json.dump(record, f)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
