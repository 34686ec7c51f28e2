"""CE-EM on three real datasets (physics, hybrid, neural, linear, N4SID), official protocol.

For each dataset of :data:`ceemx.datasets.REGISTRY` (cascaded tanks, Silverbox, coupled electric
drives; files in ``../shared/data`` or downloaded): its continuous-time gray-box model
(:mod:`ceemx.systems.gray_box`: cascaded tanks with Torricelli outflows, overflow and sensor
saturation; the Silverbox Duffing oscillator; the coupled drives' belt/pulley Wiener model with
its even speed sensor) is fitted with CE-EM (the joint method by default, ``method="alternate"``
for Algorithm 1) from its physical default guess and the default start (least squares and a
smoothing pass); the ablation adds that model plus a learned term in its vector field, and a
neural state-space model without physics: the CE-EM linear model below plus a learned term in
its transition (:func:`~ceemx.experiments.real_data_fits.fit_learned`: :func:`ceemx.hybrid`,
weight decay, early stopping on the held-out tail of the training records). Linear baselines of
the same order: N4SID with offsets and a simulation refit (:func:`ceemx.baselines.fit_affine_sid`),
and that model refined by CE-EM (the joint method on A, B, C, D with a small process noise, which
brings the fit close to a simulation-error fit). All are scored by the nonlinear-benchmarks
protocol (:func:`ceemx.benchmark_score`: initial state from the first ``n_init`` test outputs,
free-run simulation over the test input, RMSE on y[n_init:]; options per dataset in its entry)
and printed beside the published results of ``shared/data/README.md``. The figure
(:func:`ceemx.plot_benchmark` per test record) shows measured and simulated test outputs, a
zoomed window, the errors and the estimated hidden state.

What differs per dataset — the model, its options and bounds, the settings chosen by hand, how a
long record is fitted — is its registry entry; this module has no dataset names. Training
records: the cascaded tanks' single 1024-sample estimation record and the coupled drives' two
400-sample records are fitted whole; the Silverbox's 65 062-sample estimation record is cut into
windows (its entry's :class:`~ceemx.datasets.registry.Windowing`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ceemx.datasets import REGISTRY
from ceemx.experiments import common
from ceemx.experiments import real_data_fits as fits
from ceemx.experiments.real_data_fits import SMOKE, Plan, Settings
from ceemx.experiments.real_data_report import json_datasets, make_tables, plot, table_row

__all__ = ["DATASETS", "NAME", "SMOKE", "Settings", "run", "run_dataset", "score_test"]

NAME = "real_data"
DATASETS = tuple(REGISTRY)


def score_test(
    system, linear, test, test_name: str, ds, learned=None, options=None
) -> dict[str, Any]:
    """Every model's free-run score on one test record, the published beside."""
    options = options or {}
    ours, score_s = fits.score(system, test, ds.n_init, ds.score_scale, options)

    def every_sample(score) -> float:
        """RMSE over the whole test record, the n_init outputs too (how most papers score)."""
        err = np.asarray(score.y_sim[0, :, 0] - test.y[0, :, 0]) * ds.score_scale
        keep = np.asarray(test.mask[0, :, 0])
        return float(np.sqrt(np.mean(err[keep] ** 2)))

    entry: dict[str, Any] = {
        "graybox_rmse": float(ours.rmse[0, 0]),
        "graybox_rmse_every_sample": every_sample(ours),
        "graybox_fit_percent": float(ours.fit_percent[0, 0]),
        "score_s": score_s,
        "y": np.asarray(test.y[0, :, 0]),
        "y_sim": np.asarray(ours.y_sim[0, :, 0]),
        "x_sim": np.asarray(ours.x_sim[0]),
    }
    if linear is not None:
        lin, _ = fits.score(linear, test, ds.n_init, ds.score_scale, options)
        entry["linear_rmse"] = float(lin.rmse[0, 0])
        entry["linear_rmse_every_sample"] = every_sample(lin)
        entry["linear_y_sim"] = np.asarray(lin.y_sim[0, :, 0])
    else:
        entry["linear_rmse"] = math.nan
    for key, model in (learned or {}).items():
        sc, _ = fits.score(model, test, ds.n_init, ds.score_scale, options)
        entry[f"{key}_rmse"] = float(sc.rmse[0, 0])
        entry[f"{key}_rmse_every_sample"] = every_sample(sc)
        entry[f"{key}_y_sim"] = np.asarray(sc.y_sim[0, :, 0])
        entry[f"{key}_x_sim"] = np.asarray(sc.x_sim[0])
    entry["published"] = [
        f"{p.rmse[test_name]:g} ({p.method.split(' (')[0]})"
        for p in ds.published
        if test_name in p.rmse
    ]
    return entry


@dataclass
class Fitted:
    """The models of one dataset and the summaries of their fits.

    Attributes:
        physics: the gray-box model (the physics fit :func:`ceemx.fit_hybrid` selected).
        n4sid: the N4SID model (``None`` when N4SID failed).
        learned: the other models by key (``linear_ceem``, ``hybrid``, ``neural``, and the
            held-out-tail models ``hybrid_tail``, ``neural_tail``).
        fit_info: the gray-box fit's summary.
        linear_info: N4SID's summary (with its CE-EM refinement's under ``"ceem"``).
        learned_info: the learned models' summaries by key (each with its selection record).
    """

    physics: Any
    n4sid: Any
    learned: dict[str, Any] = field(default_factory=dict)
    fit_info: dict[str, Any] = field(default_factory=dict)
    linear_info: dict[str, Any] = field(default_factory=dict)
    learned_info: dict[str, Any] = field(default_factory=dict)


def fit_models(plan: Plan, train, method: str, verbose: bool = False) -> Fitted:
    """Every model of one dataset, each selected by :func:`ceemx.fit_hybrid` (one code path).

    The gray-box guess and the N4SID model go through the same selection: the noise weighting
    and the learned term's length chosen on the held-out tail of ``train``, then refitted on
    all of it. ``method`` must be ``"joint"`` (the selection's fits are joint).
    """
    import jax.numpy as jnp

    from ceemx.baselines import with_constant_input

    if method != "joint":
        raise ValueError("real_data: the selection fits by the joint method; use method='joint'.")
    name = plan.entry.name
    say = (lambda line: print(f"[{name}] {line}", flush=True)) if verbose else None
    model = plan.entry.model
    guess = model.factory(dtype=jnp.float64, **model.options)
    sel, info = fits.fit_selected(plan, guess, fits.inputs_for(guess, train), neural=False,
                                  progress=say)  # fmt: skip
    out = Fitted(sel.physics.system, None, fit_info=fits.fit_info(sel.physics, guess))
    out.fit_info["selection"] = info["selection"]
    if plan.settings.hybrid:
        out.learned["hybrid"], out.learned["hybrid_tail"] = sel.system, sel.held_out
        out.learned_info["hybrid"] = info
    window = fits.window_of(plan, train)
    n4sid, lin_info = fits.fit_linear(
        train if window is None else train.windows(window, window // 2), guess.state_dim
    )
    out.n4sid, out.linear_info = n4sid, lin_info
    if n4sid is not None:
        read = with_constant_input(train)
        lin = fits.linear_guess(n4sid, read, plan.settings)
        nsel, ninfo = fits.fit_selected(plan, lin, read, neural=True, progress=say)
        A = np.asarray(getattr(nsel.physics.system, "A"))  # noqa: B009  (a LinearSystem)
        out.linear_info = {
            **lin_info,
            "ceem": {
                **fits.fit_info(nsel.physics),
                "spectral_radius": float(np.max(np.abs(np.linalg.eigvals(A)))),
            },
        }
        out.learned["linear_ceem"] = nsel.physics.system
        if plan.settings.hybrid:
            out.learned["neural"], out.learned["neural_tail"] = nsel.system, nsel.held_out
            out.learned_info["neural"] = ninfo
    return out


def _hidden_ranges(per_test: dict[str, dict], idx: int) -> None:
    """The hidden state's range over each test record, per model (added to the entries)."""
    for e in per_test.values():
        for key in ("", "hybrid_"):
            if f"{key}x_sim" in e:
                h = e[f"{key}x_sim"][:, idx]
                e[f"{key or 'graybox_'}hidden_range"] = [float(h.min()), float(h.max())]


def _print_dataset(name: str, plan: Plan, fitted: Fitted, per_test: dict[str, dict]) -> None:
    fit_info = fitted.fit_info
    state = "converged" if fit_info["converged"] else "not converged"
    chosen = fit_info["selection"]
    print(
        f"[{name}] process noise: physics × {chosen['physics_factor']:.3g}, hybrid × "
        f"{chosen['factor']:.3g} ({chosen['process_noise']:.3g}) chosen of "
        f"{len(chosen['candidates'])} candidates",
        flush=True,
    )
    print(
        f"[{name}] {fit_info['epochs']} epochs ({state}),"
        f" fit {fit_info['wall_s']:.1f} s (first epoch {fit_info['first_epoch_s']:.1f} s, then "
        f"{fit_info['steady_epoch_s']:.3f} s/epoch); parameters {fit_info['parameters']}",
        flush=True,
    )
    for t, e in per_test.items():
        print(
            f"[{name}] {t}: {plan.entry.model.hidden[0]} over the free run: physics "
            f"{e['graybox_hidden_range']}, hybrid {e.get('hybrid_hidden_range')}",
            flush=True,
        )
    ceem_info = fitted.linear_info.get("ceem")
    if ceem_info:
        print(
            f"[{name}] linear: N4SID, then CE-EM {ceem_info['epochs']} iterations, "
            f"{ceem_info['wall_s']:.1f} s (spectral radius {ceem_info['spectral_radius']:.4f})",
            flush=True,
        )
    for key, info in fitted.learned_info.items():
        print(
            f"[{name}] {key}: {info['weights']} weights, best epoch {info['best_epoch']} of "
            f"{info['epochs']} (validation RMSE {info['validation_rmse']:.4g}), "
            f"{info['wall_s']:.1f} s",
            flush=True,
        )


def run_dataset(name: str, *, settings: Settings, method: str, verbose: bool) -> dict[str, Any]:
    """Fit, score and tabulate one dataset; returns its results (figure data included)."""
    plan = fits.make_plan(name, settings)
    ds = plan.data
    train = fits.training_data(plan)
    tests = fits.test_records(plan)
    t0 = time.perf_counter()
    fitted = fit_models(plan, train, method, verbose)
    fit_s = time.perf_counter() - t0
    options = dict(plan.settings.score_options)
    per_test = {
        t: score_test(fitted.physics, fitted.n4sid, test, t, ds, fitted.learned, options)
        for t, test in tests.items()
    }
    _hidden_ranges(per_test, plan.entry.model.hidden[1])
    if verbose:
        _print_dataset(name, plan, fitted, per_test)
    return {
        "dataset": name,
        "train_shape": list(train.y.shape),
        "n_init": ds.n_init,
        "fit_s": fit_s,
        "fit": fitted.fit_info,
        "linear": fitted.linear_info,
        "learned": fitted.learned_info,
        "tests": per_test,
        "rows": [table_row(name, t, e, ds.score_unit) for t, e in per_test.items()],
        "unit": ds.score_unit,
        "scale": ds.score_scale,
    }


def _dataset_names(dataset: str | None) -> tuple[str, ...]:
    """The datasets of a run: all of the registry's, or ``dataset`` (checked)."""
    names = DATASETS if dataset is None else (dataset,)
    for n in names:
        if n not in DATASETS:
            raise ValueError(f"unknown dataset {n!r}; choose from {', '.join(DATASETS)}.")
    return names


def run(
    *,
    smoke: bool = False,
    out=None,
    seeds: int | Sequence[int] | None = None,
    method: str | None = None,
    max_epochs: int | None = None,
    dataset: str | None = None,
    settings: Settings | None = None,
    verbose: bool = True,
) -> dict[str, Any]:
    """Fit and score the gray-box models (all datasets, or ``dataset``); write table and figure.

    Args:
        smoke: short records and few epochs (what the tests run).
        out: output folder (default ``results/real_data``).
        seeds: unused (the fits are deterministic); accepted for the CLI's uniformity.
        method: ``"joint"`` (default) or ``"alternate"`` (Algorithm 1).
        max_epochs: bound on iterations/epochs per fit (default: each entry's hand-chosen one).
        dataset: one of :data:`DATASETS` (default: all of them).
        settings: budgets (default :class:`Settings` or :data:`SMOKE`).
        verbose: print progress and the table.
    """
    from ceemx.evaluation.report import output_dir, save_json, save_text

    common.enable_x64()
    del seeds
    method = "joint" if method is None else method
    if method != "joint":
        raise ValueError(
            f"real_data: `method` must be 'joint' (the selection's fits are joint); got {method!r}."
        )
    names = _dataset_names(dataset)
    settings = settings or (SMOKE if smoke else Settings())
    if max_epochs is not None:
        settings = dataclasses.replace(settings, max_epochs=max_epochs)
    outdir = output_dir(out, f"results/{NAME}")
    t0 = time.perf_counter()
    results = [run_dataset(n, settings=settings, method=method, verbose=verbose) for n in names]
    wall = time.perf_counter() - t0
    text = make_tables(results, method=method, wall=wall)
    plot(results, outdir / f"{NAME}.png")
    summary = {
        "experiment": NAME,
        "method": method,
        "settings": settings.__dict__,
        "wall_s": wall,
        "datasets": json_datasets(results),
        "table": text,
    }
    save_json(outdir / "results.json", summary)
    save_text(outdir / "table.md", text)
    if verbose:
        print(text, flush=True)
    return summary
