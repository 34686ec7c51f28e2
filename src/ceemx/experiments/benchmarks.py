"""CE-EM on three real benchmarks (physics, hybrid, neural, linear, N4SID), official protocol.

For each dataset (``../shared/data``; loaders :mod:`ceemx.datasets`): the continuous-time gray-box
model of :mod:`ceemx.systems.benchmarks` (cascaded tanks with Torricelli outflows, overflow and
sensor saturation; the Silverbox Duffing oscillator; the coupled drives' belt/pulley Wiener
model with its even speed sensor) is fitted with CE-EM (the joint method by default,
``method="alternate"`` for Algorithm 1) from its physical default guess and the default start
(least squares and a smoothing pass); the ablation adds that model plus a learned term in its
vector field, and a neural state-space model without physics: the CE-EM linear model below plus
a learned term in its transition (:func:`_fit_learned`: :func:`ceemx.hybrid`, weight decay,
early stopping on the held-out tail of the training records). Linear baselines of the same
order: N4SID with offsets and a simulation refit (:func:`ceemx.baselines.fit_affine_sid`), and
that model refined by CE-EM (:func:`_refine_linear`: the joint method on A, B, C, D with a small
process noise, which brings the fit close to a simulation-error fit). All are scored by the
nonlinear-benchmarks protocol (:func:`ceemx.benchmark_score`: initial state from the first
``n_init`` test outputs, free-run simulation over the test input, RMSE on y[n_init:]; options
per dataset in :data:`SCORE_OPTIONS`) and printed beside the published results of
``shared/data/README.md``. The figure (:func:`ceemx.plot_benchmark` per test record) shows
measured and simulated test outputs, a zoomed window, the errors and the estimated hidden state.

Training records: the cascaded tanks' single 1024-sample estimation record and the coupled
drives' two 400-sample records are fitted whole; the Silverbox's 65 062-sample estimation record
is cut into windows (``Settings.silverbox_samples`` from its start, windows of
``Settings.window`` with half overlap).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ceemx.experiments import common

NAME = "benchmarks"
DATASETS = ("cascaded_tanks", "silverbox", "coupled_electric_drives")
#: Model options per dataset: a first-order hold where the input is band-limited and sampled
#: at a few samples per period of the dynamics (Silverbox: ≈ 9 samples per period). Process
#: noises below the models' defaults: a stiffer dynamics weight makes the CE fit closer to a
#: simulation-error fit, which is what the benchmarks score (the noise the Laplace evidence
#: learns lets the states absorb the data instead).
MODEL_OPTIONS: dict[str, dict[str, Any]] = {
    # selected on the held-out tail of the training record
    "cascaded_tanks": {"process_noise": 0.001},
    "silverbox": {"hold": "foh", "process_noise": 1e-4},
    "coupled_electric_drives": {"process_noise": 0.002},
}
#: Options of :func:`ceemx.benchmark_score` per dataset (every model's test and validation
#: scores, N4SID's included). The drives' sensor is sign-insensitive: the window's simulation
#: error has a minimum per sign of the belt speed, and the default start (a weak-dynamics
#: smoothing pass) can end in the wrong one (set 2's test: 0.275 vs 0.177 for one fitted
#: model); two starts, the better window error kept (docs/results.md).
SCORE_OPTIONS: dict[str, dict[str, Any]] = {
    "cascaded_tanks": {},
    "silverbox": {},
    "coupled_electric_drives": {"warm_process_noise": (1.0, None)},
}
#: (process, observation) noise std of the linear baseline's CE-EM refinement, × std(y): a small
#: process noise makes the CE fit close to a simulation-error (output-error) fit. Tanks' test:
#: N4SID 1.88 V → 0.699 V (the published best linear approximation: 0.75 V); 1e-4 gave 0.673 V,
#: 1e-2 0.870 V (fixed here, not selected on the test record).
LINEAR_NOISE = (1e-3, 0.05)
#: (label of the hidden state, its index in x) per dataset, for the figure.
HIDDEN = {
    "cascaded_tanks": ("upper-tank level x₁ [V]", 0),
    "silverbox": ("scaled velocity ẏ/ω [V]", 1),
    "coupled_electric_drives": ("belt state x₂", 1),
}


@dataclass(frozen=True)
class Settings:
    """Budgets of one run."""

    max_epochs: int = 200
    silverbox_samples: int = 8192
    window: int = 512
    test_samples: int | None = None  # None: the whole official test records
    #: the ablation's models beside the gray-box (physics only) and N4SID
    hybrid: bool = True
    #: joint iterations of the learned models (early stopping usually ends them sooner; the
    #: Silverbox neural model still improved at 200: multisine 1.94 mV after 30, 0.44 after 100,
    #: 0.33 after 200)
    hybrid_epochs: int = 200
    width: int = 16
    depth: int = 1
    prior_std: float = 1.0
    patience: int = 5
    #: the tail of each training record held out for early stopping (never the test records)
    validation_fraction: float = 0.2


SMOKE = Settings(
    max_epochs=3, silverbox_samples=1024, window=256, test_samples=300, hybrid_epochs=2
)
#: Physical bounds of the hidden states (the learned models must respect them): tank levels ≥ 0.
BOUNDS: dict[str, dict[str, Any]] = {
    "cascaded_tanks": {"lower": 0.0},
    "silverbox": {},
    "coupled_electric_drives": {},
}
#: The equations a learned term enters (None: all): Silverbox's missing physics is a force, in
#: the velocity equation of its (position, velocity) state.
TARGETS: dict[str, Any] = {
    "cascaded_tanks": True,
    "silverbox": (1,),
    "coupled_electric_drives": True,
}


def _model(name: str):
    from ceemx.systems import benchmarks as gb

    return {
        "cascaded_tanks": gb.CascadedTanks,
        "silverbox": gb.Silverbox,
        "coupled_electric_drives": gb.CoupledDrives,
    }[name].default


def _training_data(name: str, ds, settings: Settings):
    if name != "silverbox":
        return ds.train
    record = ds.train[:, : settings.silverbox_samples]
    return record.windows(settings.window, settings.window // 2)


def _split(name: str, ds, settings: Settings):
    """(fit records, validation records) for the learned models, both from the training data.

    The tail ``validation_fraction`` of every training record is held out (for Silverbox: the
    estimation-record samples after those fitted, cut into the same windows); the official test
    records are never used.
    """
    if name == "silverbox":
        fit = _training_data(name, ds, settings)
        a = settings.silverbox_samples
        b = a + max(int(settings.validation_fraction * a), 2 * ds.n_init)
        return fit, ds.train[:, a:b]
    train = ds.train
    cut = train.num_steps - max(int(settings.validation_fraction * train.num_steps), 2 * ds.n_init)
    return train[:, :cut], train[:, cut - ds.n_init :]


def _learned_starts(name: str, ds, settings: Settings, method: str, physics, refined):
    """The fits the learned models start from, none of which has seen the validation records.

    Early stopping scores each epoch on the tail of the training records (:func:`_split`); a
    start fitted on the whole record has seen that tail, which makes its own validation score
    optimistic and stops the learned model at or near the start. So the starts are the physics
    and the CE-EM linear fits of the fit part alone (Silverbox: its validation samples lie after
    the fitted ones already, the full fits are the starts). Returns (physics fit, linear fit or
    ``None``).
    """
    import jax.numpy as jnp

    if name == "silverbox":
        return physics, refined
    fit_part, _ = _split(name, ds, settings)
    start, _ = _fit_graybox(name, fit_part, settings, method, jnp.float64)
    if refined is None:
        return start, None
    n4sid, _ = _fit_linear(fit_part, start.system.state_dim)
    return start, None if n4sid is None else _refine_linear(n4sid, fit_part, settings)[0]


def _fit_learned(name, base, states, ds, settings: Settings, *, neural: bool, observation=False):
    """A learned term on ``base``, trained by the joint method with early stopping.

    ``neural=False``: the hybrid (the physics fit plus a learned term in its vector field, the
    physical state bounds); ``neural=True``: the neural state-space model (the CE-EM linear
    model plus a learned term in its transition; no physics, no bounds). ``observation``: a
    learned term in the observation too (not used by the experiment; the probes' variant).
    """
    import jax.numpy as jnp

    from ceemx import JointLM, fit, hybrid, weight_decay
    from ceemx.evaluation.early_stopping import EarlyStopping

    reads = _reads(base)
    fit_data, val = _split(name, ds, settings)
    fit_data, val = reads(fit_data), reads(val)  # ``states`` are the fit part's (_learned_starts)
    model = hybrid(
        base,
        fit_data,
        states=states,
        dynamics=True if neural else TARGETS[name],
        observation=observation,
        width=settings.width,
        depth=settings.depth,
        prior_std=settings.prior_std,
        **({} if neural else BOUNDS[name]),
    )
    stopper = EarlyStopping(
        val, ds.n_init, patience=settings.patience, start=model, score_options=SCORE_OPTIONS[name]
    )
    t0 = time.perf_counter()
    result = fit(
        model,
        fit_data,
        jnp.asarray(states),
        solver=JointLM(),
        trainable=model.trainable("both"),
        log_prior=weight_decay,
        max_epochs=settings.hybrid_epochs,
        callbacks=[stopper],
        diagnose=False,
    )
    wall = time.perf_counter() - t0
    result = stopper.restore(result)
    return result.system, {
        "epochs": len(result.history),
        "best_epoch": stopper.best_epoch,
        "validation_rmse": stopper.best_rmse,
        "wall_s": wall,
        "weights": int(sum(np.size(w) for w in _net_leaves(result.system))),
    }


def _net_leaves(system):
    import equinox as eqx
    import jax.tree_util as jtu

    terms = (system.dynamics_term, system.observation_term)
    return jtu.tree_leaves(
        eqx.filter([t.net for t in terms if t is not None], eqx.is_inexact_array)
    )


def _inputs_for(system, data):
    """The data as the system reads it: [u_t, u_{t+1}] under a first-order hold."""
    from ceemx.data.trajectories import Trajectories, foh_inputs

    if getattr(system, "hold", "zoh") != "foh":
        return data
    out = foh_inputs(data)
    assert isinstance(out, Trajectories)
    return out


def _reads(system):
    """How ``system`` reads a record (a function of the record).

    The linear models and hybrids of them: with the constant input channel of
    :func:`ceemx.baselines.with_constant_input`; the rest: :func:`_inputs_for`.
    """
    from ceemx.baselines import with_constant_input
    from ceemx.systems import LinearSystem

    if isinstance(getattr(system, "physics", system), LinearSystem):
        return with_constant_input
    return lambda data: _inputs_for(system, data)


def _score(system, test, n_init: int, scale: float, options: dict[str, Any]):
    from ceemx.evaluation.metrics import benchmark_score

    t0 = time.perf_counter()
    s = benchmark_score(system, _reads(system)(test), n_init, scale=scale, **options)
    return s, time.perf_counter() - t0


def _fit_graybox(name: str, train, settings: Settings, method: str, dtype):
    from ceemx import JointLM, fit
    from ceemx.identification.problem import trainable_mask

    guess = _model(name)(dtype=dtype, **MODEL_OPTIONS[name])
    solver = JointLM() if method == "joint" else common.make_solver("alternate")
    data = _inputs_for(guess, train)
    t0 = time.perf_counter()
    result = fit(guess, data, solver=solver, max_epochs=settings.max_epochs)
    wall = time.perf_counter() - t0
    epoch_s = [h["time"] for h in result.history]
    learned = trainable_mask(guess)
    params = {
        f.name: float(np.asarray(getattr(result.system, f.name)))
        for f in dataclasses.fields(result.system)
        if getattr(learned, f.name, False) is True and np.ndim(getattr(result.system, f.name)) == 0
    }
    return result, {
        "epochs": len(result.history),
        "converged": bool(result.converged),
        "wall_s": wall,
        "first_epoch_s": epoch_s[0] if epoch_s else math.nan,
        "steady_epoch_s": float(np.median(epoch_s[1:])) if len(epoch_s) > 1 else math.nan,
        "parameters": params,
        "J": float(result.history[-1]["J"]) if result.history else math.nan,
    }


def _fit_linear(train, order: int):
    """The linear baseline: N4SID of the same order, affine and refitted for simulation.

    :func:`ceemx.baselines.fit_affine_sid` (plain N4SID free-ran the tanks to 532.5 V).
    """
    from ceemx.baselines import fit_affine_sid

    t0 = time.perf_counter()
    try:
        model = fit_affine_sid(train, state_dim=order)
    except ValueError as e:  # too little data for the horizon, etc.
        return None, {"error": str(e), "wall_s": time.perf_counter() - t0}
    radius = float(np.max(np.abs(np.linalg.eigvals(np.asarray(model.A)))))
    return model, {"wall_s": time.perf_counter() - t0, "spectral_radius": radius}


def _refine_linear(n4sid, train, settings: Settings):
    """N4SID's model refined by CE-EM (:func:`ceemx.baselines.refine_linear`, :data:`LINEAR_NOISE`).

    Returns the fit result (its states start the neural model) and its summary.
    """
    from ceemx.baselines import refine_linear, with_constant_input

    t0 = time.perf_counter()
    result = refine_linear(
        n4sid,
        with_constant_input(train),
        process_noise=LINEAR_NOISE[0],
        obs_noise=LINEAR_NOISE[1],
        max_epochs=settings.max_epochs,
    )
    A = np.asarray(getattr(result.system, "A"))  # noqa: B009  (a LinearSystem)
    return result, {
        "epochs": len(result.history),
        "converged": bool(result.converged),
        "wall_s": time.perf_counter() - t0,
        "spectral_radius": float(np.max(np.abs(np.linalg.eigvals(A)))),
    }


def _test_records(ds, settings: Settings) -> dict:
    """The official test records, cut to ``settings.test_samples`` when set."""
    tests = dict(ds.tests)
    if settings.test_samples is not None:
        tests = {k: v[:, : settings.test_samples] for k, v in tests.items()}
    return tests


def _score_test(
    system, linear, test, test_name: str, ds, learned=None, options=None
) -> dict[str, Any]:
    """Every model's free-run score on one test record, the published beside."""
    options = options or {}
    ours, score_s = _score(system, test, ds.n_init, ds.score_scale, options)

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
        lin, _ = _score(linear, test, ds.n_init, ds.score_scale, options)
        entry["linear_rmse"] = float(lin.rmse[0, 0])
        entry["linear_rmse_every_sample"] = every_sample(lin)
        entry["linear_y_sim"] = np.asarray(lin.y_sim[0, :, 0])
    else:
        entry["linear_rmse"] = math.nan
    for key, model in (learned or {}).items():
        sc, _ = _score(model, test, ds.n_init, ds.score_scale, options)
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


def _table_row(name: str, test_name: str, entry: dict[str, Any], unit: str) -> list[str]:
    """One row of the results table: every model's RMSE and up to three published ones."""

    def cell(key):
        value = entry.get(f"{key}_rmse")
        return "—" if value is None else f"{value:.4g}"

    return [
        name,
        test_name,
        cell("graybox"),
        cell("hybrid"),
        cell("neural"),
        cell("linear_ceem"),
        cell("linear"),
        "; ".join(entry["published"][:3]) or "—",
        unit,
    ]


def run_dataset(name: str, *, settings: Settings, method: str, verbose: bool) -> dict[str, Any]:
    """Fit, score and tabulate one dataset; returns its results (figure data included)."""
    import jax.numpy as jnp

    from ceemx import datasets

    ds = getattr(datasets, name)()
    train = _training_data(name, ds, settings)
    tests = _test_records(ds, settings)
    result, fit_info = _fit_graybox(name, train, settings, method, jnp.float64)
    linear, lin_info = _fit_linear(train, result.system.state_dim)
    learned, learned_info = {}, {}
    refined, ceem_info = None, {}
    if linear is not None:
        refined, ceem_info = _refine_linear(linear, train, settings)
        lin_info = {**lin_info, "ceem": ceem_info}
        learned["linear_ceem"] = refined.system
    if settings.hybrid:
        start, linear_start = _learned_starts(name, ds, settings, method, result, refined)
        learned["hybrid"], learned_info["hybrid"] = _fit_learned(
            name, start.system, start.states, ds, settings, neural=False
        )
        if linear_start is not None:
            learned["neural"], learned_info["neural"] = _fit_learned(
                name, linear_start.system, linear_start.states, ds, settings, neural=True
            )
    per_test = {
        t: _score_test(result.system, linear, test, t, ds, learned, SCORE_OPTIONS[name])
        for t, test in tests.items()
    }
    idx = HIDDEN[name][1]
    for e in per_test.values():  # the hidden state's range over the test record, per model
        for key in ("", "hybrid_"):
            if f"{key}x_sim" in e:
                h = e[f"{key}x_sim"][:, idx]
                e[f"{key or 'graybox_'}hidden_range"] = [float(h.min()), float(h.max())]
    out = {
        "dataset": name,
        "train_shape": list(train.y.shape),
        "n_init": ds.n_init,
        "fit": fit_info,
        "linear": lin_info,
        "learned": learned_info,
        "tests": per_test,
        "rows": [_table_row(name, t, e, ds.score_unit) for t, e in per_test.items()],
        "unit": ds.score_unit,
        "scale": ds.score_scale,
    }
    if verbose:
        state = "converged" if fit_info["converged"] else "not converged"
        print(
            f"[{name}] {fit_info['epochs']} epochs ({state}),"
            f" fit {fit_info['wall_s']:.1f} s (first epoch {fit_info['first_epoch_s']:.1f} s, then "
            f"{fit_info['steady_epoch_s']:.3f} s/epoch); parameters {fit_info['parameters']}",
            flush=True,
        )
        for t, e in per_test.items():
            print(
                f"[{name}] {t}: {HIDDEN[name][0]} over the free run: physics "
                f"{e['graybox_hidden_range']}, hybrid {e.get('hybrid_hidden_range')}",
                flush=True,
            )
        if ceem_info:
            print(
                f"[{name}] linear: N4SID, then CE-EM {ceem_info['epochs']} iterations, "
                f"{ceem_info['wall_s']:.1f} s (spectral radius {ceem_info['spectral_radius']:.4f})",
                flush=True,
            )
        for key, info in learned_info.items():
            print(
                f"[{name}] {key}: {info['weights']} weights, best epoch {info['best_epoch']} of "
                f"{info['epochs']} (validation RMSE {info['validation_rmse']:.4g}), "
                f"{info['wall_s']:.1f} s",
                flush=True,
            )
    return out


def _plot(results: list[dict], path) -> None:
    """One panel group per test record (:func:`ceemx.evaluation.plots.plot_benchmark`).

    Measured and simulated outputs over the whole record and a zoomed window, the errors, and
    the hybrid's (else the gray-box's) hidden state with its physical bound.
    """
    from ceemx.evaluation import report
    from ceemx.evaluation.plots import plot_benchmark

    plt = report.plt()
    panels = [(r, t) for r in results for t in r["tests"]]
    fig = plt.figure(figsize=(12, 4.2 * len(panels)), layout="constrained")
    subs = fig.subfigures(len(panels), 1, squeeze=False)[:, 0]
    for (r, test_name), sub in zip(panels, subs, strict=True):
        e = r["tests"][test_name]
        sims = {"gray-box": e["y_sim"]}
        labels = (("hybrid", "hybrid"), ("neural", "neural SS"), ("linear_ceem", "linear CE-EM"))
        for key, label in labels:
            if f"{key}_y_sim" in e:
                sims[label] = e[f"{key}_y_sim"]
        if "linear_y_sim" in e:
            sims["N4SID"] = e["linear_y_sim"]
        label, idx = HIDDEN[r["dataset"]]
        lower = BOUNDS[r["dataset"]].get("lower")
        x = e.get("hybrid_x_sim", e["x_sim"])
        which = "hybrid" if "hybrid_x_sim" in e else "gray-box"
        plot_benchmark(
            e["y"],
            sims,
            n_init=r["n_init"],
            hidden=x[:, idx],
            hidden_label=f"{label} ({which})",
            bounds=None if lower is None else (lower, None),
            score_unit=r["unit"],
            score_scale=r.get("scale", 1.0),
            title=f"{r['dataset']} / {test_name}: free-run simulation",
            fig=sub,
        )
    report.save_figure(fig, path, dpi=90)  # six record panels: a readable, smaller file
    plt.close(fig)


def _dataset_names(dataset: str | None) -> tuple[str, ...]:
    """The datasets of a run: all three, or ``dataset`` (checked)."""
    names = DATASETS if dataset is None else (dataset,)
    for n in names:
        if n not in DATASETS:
            raise ValueError(f"unknown dataset {n!r}; choose from {', '.join(DATASETS)}.")
    return names


def make_tables(results: list[dict], *, method: str, wall: float) -> str:
    """Markdown: the scores beside the published ones, then each fit's epochs, time, parameters."""
    from ceemx.evaluation import report

    header = [
        "dataset",
        "test",
        "physics (gray-box)",
        "physics + learned term",
        "neural state space (linear + learned term)",
        "linear (CE-EM from N4SID)",
        "N4SID (affine, refitted)",
        "published",
        "unit",
    ]
    table = report.markdown_table(header, [row for r in results for row in r["rows"]])
    fits = report.markdown_table(
        ["dataset", "epochs", "converged", "fit s (compile incl.)", "s/epoch after the first",
         "parameters"],
        [
            [
                r["dataset"],
                r["fit"]["epochs"],
                r["fit"]["converged"],
                f"{r['fit']['wall_s']:.1f}",
                f"{r['fit']['steady_epoch_s']:.3f}",
                ", ".join(f"{k} = {v:.4g}" for k, v in r["fit"]["parameters"].items()),
            ]
            for r in results
        ],
    )  # fmt: skip
    learned_rows = [
        [
            r["dataset"],
            key,
            info["weights"],
            f"{info['best_epoch']} / {info['epochs']}",
            f"{info['validation_rmse']:.4g}",
            f"{info['wall_s']:.1f}",
        ]
        for r in results
        for key, info in r.get("learned", {}).items()
    ]
    learned = ""
    if learned_rows:
        learned = "\n\n" + report.markdown_table(
            ["dataset", "model", "weights", "best epoch / epochs", "validation RMSE", "fit s"],
            learned_rows,
        )
    every = "; ".join(
        f"{r['dataset']} {t}: "
        + ", ".join(
            f"{label} {e[key + '_rmse_every_sample']:.4g}"
            for key, label in (("graybox", "gray-box"), ("hybrid", "hybrid"), ("linear", "N4SID"))
            if key + "_rmse_every_sample" in e
        )
        for r in results
        for t, e in r["tests"].items()
    )
    learned += (
        "\n\nOver every test sample, the n_init outputs included (how most published "
        f"cascaded-tanks results score): {every}."
    )
    return (
        f"## CE-EM on real benchmarks (method {method}; official protocol: free-run "
        f"simulation RMSE after n_init test samples)\n\n{table}\n\n{fits}{learned}\n\n"
        "Physics + learned term: the gray-box model with a zero-initialised MLP added to its "
        "vector field (ceemx.hybrid), trained with it by the joint method, weight decay and "
        "early stopping on the held-out tail of the training record, from a physics fit of the "
        "rest of the record (the test records are never seen). Neural state space: no physics — "
        "the CE-EM linear model plus the same MLP in its transition (x⁺ = A x + B u + N(x, u)), "
        "trained and stopped the same way. "
        "N4SID: order of the gray-box model, on centred data, B, D and offsets refitted to the "
        "free-run error (ceemx.baselines.fit_affine_sid); linear (CE-EM): that model refined by "
        "the joint method with a small process noise (close to an output-error fit)."
        f"\n\nTotal wall time {wall:.1f} s."
    )


def _json_datasets(results: list[dict]) -> list[dict]:
    """The per-dataset results without the figure's arrays (as ``results.json`` holds them)."""
    return [
        {
            **{k: v for k, v in r.items() if k != "tests"},
            "tests": {
                t: {k: v for k, v in e.items() if not isinstance(v, np.ndarray)}
                for t, e in r["tests"].items()
            },
        }
        for r in results
    ]


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
        out: output folder (default ``results/benchmarks``).
        seeds: unused (the fits are deterministic); accepted for the CLI's uniformity.
        method: ``"joint"`` (default) or ``"alternate"`` (Algorithm 1).
        max_epochs: bound on iterations/epochs per fit (default ``settings.max_epochs``).
        dataset: one of :data:`DATASETS` (default: all three).
        settings: budgets (default :class:`Settings` or :data:`SMOKE`).
        verbose: print progress and the table.
    """
    from ceemx.evaluation import report

    common.enable_x64()
    del seeds
    method = "joint" if method is None else method
    if method not in ("joint", "alternate"):
        raise ValueError(f"benchmarks: `method` must be 'joint' or 'alternate'; got {method!r}.")
    names = _dataset_names(dataset)
    settings = settings or (SMOKE if smoke else Settings())
    if max_epochs is not None:
        settings = Settings(**{**settings.__dict__, "max_epochs": max_epochs})
    outdir = report.output_dir(out, "results/benchmarks")
    t0 = time.perf_counter()
    results = [run_dataset(n, settings=settings, method=method, verbose=verbose) for n in names]
    wall = time.perf_counter() - t0
    text = make_tables(results, method=method, wall=wall)
    _plot(results, outdir / "benchmarks.png")
    summary = {
        "experiment": NAME,
        "method": method,
        "settings": settings.__dict__,
        "wall_s": wall,
        "datasets": _json_datasets(results),
        "table": text,
    }
    report.save_json(outdir / "results.json", summary)
    report.save_text(outdir / "table.md", text)
    if verbose:
        print(text, flush=True)
    return summary
