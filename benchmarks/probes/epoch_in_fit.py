"""The Figure-3 Algorithm-1 epoch inside a fit: time, its split and page faults, with this
session's three fixes undone one at a time (issue 23, "Every row in one run").

    python benchmarks/probes/epoch_in_fit.py [--variants NAME ...] [--epochs 12]

6 coupled Lorenz, B = 8, T = 128, the paper's weighting, states at truth + N(0, 1) (as
``benchmarks/probes/algorithm1_epoch.py``), ``ceemx.Alternating`` with ``LMSmoother(max_steps=2)``.
Each variant runs in a fresh process (the BLAS limit and allocator state are per process): a
compiling 2-epoch fit, then a fit of ``--epochs`` epochs; printed are the median epoch time,
smoothing and learning (epochs 3 onwards, from the history), the minor page faults per epoch
(``getrusage``, the long fit less the short one), ε(θ) after the last epoch and the load.

Variants (each is the current code with one thing changed):

- ``default``: as shipped;
- ``no-blas-limit``: ``CEEMX_BLAS_THREADS=0`` (SciPy's OpenBLAS keeps its own threads);
- ``rows-at-once``: the learner's θ-Jacobian rows all in one chunk (``ROWS_CHUNK_BYTES`` 1 GB:
  50 MB arrays, fresh pages every call);
- ``smoother-unchunked``: ``LMSmoother(batch_chunk=None)`` (38 MB of temporaries);
- ``gram-one-product``: each chunk's RᵀR as one product (``GRAM_BLOCK_MIN`` above P), not the
  upper column blocks;
- ``before``: the first three undone.

Backs: ``ceemx/infra/runtime.py``, ``ceemx/identification/learning/gauss_newton.py``
(``ROWS_CHUNK_BYTES``), ``ceemx/inference/smoother.py`` (``AUTO_CHUNK_BYTES``) and
``benchmarks/README.md`` ("Every row in one run").
"""

import argparse
import json
import os
import subprocess
import sys

VARIANTS = {
    "default": {},
    "no-blas-limit": {"blas": False},
    "rows-at-once": {"rows": False},
    "smoother-unchunked": {"chunk": False},
    "gram-one-product": {"gram": False},
    "before": {"blas": False, "rows": False, "chunk": False},
}


def worker(name: str, epochs: int) -> dict:
    v = {"blas": True, "rows": True, "chunk": True, "gram": True, **VARIANTS[name]}
    if not v["blas"]:
        os.environ["CEEMX_BLAS_THREADS"] = "0"
    import resource
    import statistics

    import jax

    jax.config.update("jax_enable_x64", True)
    import ceemx
    from ceemx.evaluation import metrics as ev
    from ceemx.experiments import common, figure3
    from ceemx.identification.learning import gauss_newton
    from ceemx.models import with_noise

    if not v["rows"]:
        gauss_newton.ROWS_CHUNK_BYTES = 2**30
    if not v["gram"]:
        gauss_newton.GRAM_BLOCK_MIN = 2**30
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from compare_reference_figure3 import figure3_problem

    true, p, x_init = figure3_problem()
    pn, on, rho_x = figure3.fit_setup("paper")
    system = with_noise(p.init_system, pn, on)
    smoother = ceemx.LMSmoother(
        rho_x=rho_x, max_steps=2, batch_chunk="auto" if v["chunk"] else None
    )
    solver = ceemx.Alternating(smoother=smoother, rtol=0.0)

    def run(n, callbacks=()):
        return ceemx.fit(
            system, p.data, x_init, solver=solver, trainable=common.LORENZ_PARAMS_H,
            max_epochs=n, progress=False, callbacks=list(callbacks),
        )  # fmt: skip

    def faults():
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

    run(2)
    f0 = faults()
    run(2)
    f1 = faults()
    eps = ev.DynamicsErrorCallback(true)
    res = run(epochs, [eps])
    f2 = faults()
    h = res.history[2:]
    return {
        "variant": name,
        "epoch_s": statistics.median(e["time"] for e in h),
        "smooth_s": statistics.median(e["smooth_time"] for e in h),
        "learn_s": statistics.median(e["learn_time"] for e in h),
        "faults_per_epoch": ((f2 - f1) - (f1 - f0)) / (epochs - 2),
        "eps_last": res.history[-1]["eps"],
        "load": os.getloadavg()[0],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    ap.add_argument("--epochs", type=int, default=12)
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.epochs)))
        return
    for name in args.variants:
        out = subprocess.run(
            [sys.executable, __file__, "--worker", name, "--epochs", str(args.epochs)],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(
            f"{name:20s} epoch {r['epoch_s']:.3f} s (smoothing {r['smooth_s']:.3f}, learning "
            f"{r['learn_s']:.3f}), {r['faults_per_epoch']:.0f} page faults/epoch, "
            f"ε {r['eps_last']:.4g}, load {r['load']:.2f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
