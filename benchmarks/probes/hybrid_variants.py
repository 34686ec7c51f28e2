"""Variants of the benchmarks' hybrid (physics + learned term), scored on validation only.

    python benchmarks/probes/hybrid_variants.py DATASET [TARGETS] [WIDTH] [DEPTH] [PRIOR_STD]
        [--observation] [--patience N]

The experiment's hybrid (``ceemx experiment benchmarks``: the start of ``_learned_starts``, the
training and early stopping of ``_fit_learned``) with one choice changed: TARGETS the state
equations the learned term enters (``all``, default, indices such as ``1`` or ``0,1``, or
``none`` with ``--observation``: the observation term alone),
WIDTH × DEPTH of the MLP (default 16 × 1), PRIOR_STD the weight decay's σ (default 1),
``--observation`` a learned term in the observation too, ``--patience`` early stopping's (5).
Prints the best epoch and the validation RMSE (the tail of the training records); the test
records are not scored. Backs "Hybrid variants" in docs/results.md.
"""

import argparse
import dataclasses

import jax

jax.config.update("jax_enable_x64", True)
from ceemx import datasets  # noqa: E402
from ceemx.experiments import benchmarks as bm  # noqa: E402

p = argparse.ArgumentParser()
p.add_argument("dataset", choices=bm.DATASETS)
p.add_argument("targets", nargs="?", default="all")
p.add_argument("width", nargs="?", type=int, default=16)
p.add_argument("depth", nargs="?", type=int, default=1)
p.add_argument("prior_std", nargs="?", type=float, default=1.0)
p.add_argument("--observation", action="store_true")
p.add_argument("--patience", type=int, default=bm.Settings().patience)
a = p.parse_args()
special = {"all": True, "none": False}
if a.targets in special:
    bm.TARGETS[a.dataset] = special[a.targets]
else:
    bm.TARGETS[a.dataset] = tuple(int(c) for c in a.targets.split(","))
settings = dataclasses.replace(
    bm.Settings(), width=a.width, depth=a.depth, prior_std=a.prior_std, patience=a.patience
)
ds = getattr(datasets, a.dataset)()
train = bm._training_data(a.dataset, ds, settings)
physics = None
if a.dataset == "silverbox":  # its start is the full fit (its validation samples lie after it)
    physics, _ = bm._fit_graybox(a.dataset, train, settings, "joint", jax.numpy.float64)
start, _ = bm._learned_starts(a.dataset, ds, settings, "joint", physics, None)
_, info = bm._fit_learned(
    a.dataset, start.system, start.states, ds, settings, neural=False, observation=a.observation
)
print(
    f"{a.dataset} targets {a.targets} {a.width}×{a.depth} σ {a.prior_std:g} observation "
    f"{a.observation} patience {a.patience}: best epoch {info['best_epoch']} of "
    f"{info['epochs']}, validation RMSE {info['validation_rmse']:.4g}",
    flush=True,
)
