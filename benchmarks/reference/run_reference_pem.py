"""The authors' Particle EM (`ceem` 0.0.4, ``faPF`` + ``SAEMTrainer``) on ceemx's Figure-2 problem.

Run with the reference environment's Python (``benchmarks/reference/setup.sh``)::

    benchmarks/reference/.venv/bin/python \
        benchmarks/reference/run_reference_pem.py PROBLEM.npz OUT.json

The problem file (written by ``benchmarks/particle_em.py``) holds ``y`` (B, T, m), ``C`` (m, 3),
``sigma0``/``rho0``/``beta0`` (1,) (ceemx's initial guess), ``dt``, ``sigma_w``, ``sigma_v``,
``n_particles``, ``n_smoothed``, ``epochs``, ``integrator`` and ``seed``. A single Lorenz
attractor has the same state ordering (x, y, z) in both codes. The fit follows the authors'
Figure-2 Particle-EM script through the 0.0.4 API: ``LorenzAttractor(σ, ρ, β, C, dt,
method=integrator)`` (their default is ``"midpoint"``; ``"rk4"`` matches ceemx's data),
``faPF(N, system, Q=σ_w² I, R=σ_v² I, Px0=5 I, x0mean=(−6, −6, 24), FFBSi_N=N_s)``,
``SAEMTrainer(fapf, y, gamma_sched=lambda k: 0.8, max_k=epochs)`` with its default optimizer
(10 Adam steps, lr 0.01, per epoch) and no cut-off of the stored draws.

Recorded per epoch: wall time (callback to callback, so it includes the trainer's own Q̂
logging), the E-step (``filter`` + ``FFBSi``) and the M-step (the optimizer) timed by wrappers
around the instance's methods and the optimizer, and (σ, ρ, β) after the epoch.
"""

import json
import sys
import tempfile
import time

import numpy as np
import torch
from ceem import logger
from ceem.particleem import SAEMTrainer, faPF, torchoptimizer
from ceem.systems import LorenzAttractor


def main(problem_path: str, out_path: str) -> None:
    torch.set_default_dtype(torch.float64)
    logger.setup(tempfile.mkdtemp(prefix="ceem-ref-pem-"), format_strs=["csv"], action="d")
    d = np.load(problem_path)
    torch.manual_seed(int(d["seed"]))
    y = torch.tensor(d["y"])
    system = LorenzAttractor(
        torch.tensor(d["sigma0"]),
        torch.tensor(d["rho0"]),
        torch.tensor(d["beta0"]),
        torch.tensor(d["C"]),
        float(d["dt"]),
        method=str(d["integrator"]),
    )
    n = 3
    m = y.shape[-1]
    fapf = faPF(
        int(d["n_particles"]),
        system,
        Q=float(d["sigma_w"]) ** 2 * torch.eye(n),
        R=float(d["sigma_v"]) ** 2 * torch.eye(m),
        Px0=5.0 * torch.eye(n),
        x0mean=torch.tensor([[-6.0, -6.0, 24.0]]),
        FFBSi_N=int(d["n_smoothed"]),
    )
    split = {"e": 0.0, "m": 0.0}

    def timed(fn, slot):
        def wrapper(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                split[slot] += time.perf_counter() - t

        return wrapper

    # instance attributes shadow the methods SAEMTrainer.train calls (self._fapf.filter, .FFBSi)
    fapf.filter = timed(fapf.filter, "e")
    fapf.FFBSi = timed(fapf.FFBSi, "e")
    trainer = SAEMTrainer(
        fapf,
        y,
        gamma_sched=lambda k: 0.8,
        optimizer=timed(torchoptimizer, "m"),  # the default optimizer, timed
        max_k=int(d["epochs"]),
    )
    record: dict = {"theta": [], "epoch_s": [], "e_step_s": [], "m_step_s": []}
    clock = {"t": 0.0}

    def on_epoch(k):
        now = time.perf_counter()
        record["epoch_s"].append(now - clock["t"])
        record["e_step_s"].append(split["e"])
        record["m_step_s"].append(split["m"])
        split["e"] = split["m"] = 0.0
        record["theta"].append(
            {
                "sigma": float(system._sigma.detach().reshape(-1)[0]),
                "rho": float(system._rho.detach().reshape(-1)[0]),
                "beta": float(system._beta.detach().reshape(-1)[0]),
            }
        )
        clock["t"] = time.perf_counter()  # the callback's own time is not counted

    record["torch_threads"] = torch.get_num_threads()
    clock["t"] = t0 = time.perf_counter()
    trainer.train(list(system.parameters()), callbacks=[on_epoch])
    record["total_s"] = time.perf_counter() - t0
    with open(out_path, "w") as f:
        json.dump(record, f)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
