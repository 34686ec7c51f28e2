"""Every public entry point checks its keyword options at entry, naming the option.

Each case below was accepted before (``smooth(covariance="False")`` turned covariances on,
``fit(checkpoint_mismatch="bogus")`` ran, ``simulate(num_steps=-1, u=...)`` simulated u's T
steps), failed with a raw error naming no option (``fit(callbacks=[3])``: "'int' object is not
callable"; ``fit(checkpoint=3)``), or failed late: integer options past 2**31 - 1 wrapped or
overflowed in JAX's int32 (``particle_filter(n_particles=2**31)``: "Python integer 2147483648 out
of bounds for int32"), ``fit(max_epochs=2**31)`` ran on without end, and ``hybrid(width=2**31)``
aborted the Python process inside XLA. Every call here is refused before any compute.
"""

import os
import pathlib
import re

import jax
import numpy as np
import pytest

import ceemx
from ceemx.identification import hybrid_builder
from ceemx.infra.options import INT32_MAX, check_path
from ceemx.systems import LinearSystem

T = 6
A, C, B_, D = np.array([[0.9]]), np.eye(1), np.ones((1, 1)), np.zeros((1, 1))
SYSTEM = LinearSystem(A, C, B_, D, process_noise=0.1, obs_noise=0.1)
U = np.linspace(-1.0, 1.0, T).reshape(1, T, 1)
DATA = ceemx.Trajectories(np.sin(np.arange(T, dtype=float)).reshape(1, T, 1), U)
X = np.zeros((1, T, 1))
KEY = jax.random.PRNGKey(0)
PRIOR = ceemx.GaussianPrior(np.zeros(1), ceemx.DiagonalGaussian(1.0, 1))
BIG = 2**31  # one past INT32_MAX


def _never(*args, **kwargs):
    raise AssertionError("an option check ran after compute started")


CALLS = {
    "fit": lambda **kw: ceemx.fit(SYSTEM, DATA, X, **{"max_epochs": 1, "progress": False, **kw}),
    "smooth": lambda **kw: ceemx.smooth(SYSTEM, DATA, X, **kw),
    "simulate": lambda **kw: ceemx.simulate(
        SYSTEM, KEY, np.zeros((1, 1)), kw.pop("num_steps", T), U, **kw
    ),
    "free_run": lambda **kw: ceemx.free_run(SYSTEM, np.zeros((1, 1)), U, **kw),
    "predict_k_step": lambda **kw: ceemx.predict_k_step(SYSTEM, DATA, **kw),
    "estimate_initial_state": lambda **kw: ceemx.estimate_initial_state(SYSTEM, DATA, 3, **kw),
    "benchmark_score": lambda **kw: ceemx.benchmark_score(SYSTEM, DATA, 3, **kw),
    "residual_diagnostics": lambda **kw: ceemx.residual_diagnostics(SYSTEM, DATA, X, **kw),
    "estimate_noise": lambda **kw: ceemx.estimate_noise(SYSTEM, DATA, X, **kw),
    "warm_start": lambda **kw: ceemx.warm_start(SYSTEM, DATA, **kw),
    "learn": lambda **kw: ceemx.learn(SYSTEM, X, DATA, **kw),
    "particle_filter": lambda **kw: ceemx.particle_filter(SYSTEM, DATA, initial=PRIOR, **kw),
    "hybrid": lambda **kw: ceemx.hybrid(SYSTEM, DATA, states=X, **kw),
    "EarlyStopping": lambda **kw: ceemx.EarlyStopping(DATA, 3, **kw),
    "perturb": lambda **kw: ceemx.perturb(KEY, SYSTEM, **kw),
    "enable_compilation_cache": lambda **kw: ceemx.enable_compilation_cache(**kw),
    "plot_benchmark": lambda **kw: ceemx.plot_benchmark(
        np.sin(np.arange(50.0)), np.zeros(50), **kw
    ),
}

# (entry point, option, bad value, exception, what the message says after the option's name)
CASES = [
    ("fit", "diagnose", "False", TypeError, "must be True or False"),
    ("fit", "diagnose", None, TypeError, "must be True or False"),
    ("fit", "progress", 2, TypeError, "must be True, False or None"),
    ("fit", "checkpoint_mismatch", "bogus", ValueError, "must be one of 'raise', 'restart'"),
    ("fit", "checkpoint", 3, TypeError, "must be a path (str or os.PathLike) or None"),
    ("fit", "callbacks", [3], TypeError, "must be a callable"),  # `callbacks[0]`
    ("fit", "callbacks", print, TypeError, "must be a list or tuple of callables"),
    ("fit", "max_epochs", 10**30, ValueError, "must be an integer <= 2147483647"),
    ("fit", "max_epochs", BIG, ValueError, "must be an integer <= 2147483647"),
    ("smooth", "covariance", "False", TypeError, "must be True or False"),
    ("smooth", "covariance", 1, TypeError, "must be True or False"),
    ("simulate", "num_steps", -1, ValueError, "must be an integer >= 1"),
    ("simulate", "num_steps", 2.5, TypeError, "must be an integer"),
    ("simulate", "num_steps", T + 1, ValueError, f"= {T + 1} but `u` has T = {T} steps"),
    ("simulate", "process_noise", "False", TypeError, "must be True, False or a noise model"),
    ("simulate", "obs_noise", 2, TypeError, "must be True, False or a noise model"),
    ("free_run", "num_steps", 2.5, TypeError, "must be an integer"),
    ("predict_k_step", "k", BIG, ValueError, "must be in [1, 2**31 - 1]"),
    ("estimate_initial_state", "refine", "no", TypeError, "must be True or False"),
    ("estimate_initial_state", "return_status", 1, TypeError, "must be True or False"),
    ("estimate_initial_state", "smoother", 3, TypeError, "must be a ceemx.LMSmoother or None"),
    ("benchmark_score", "scale", "x", ValueError, "must be a positive scalar or (1,) vector"),
    ("residual_diagnostics", "estimate", "no", TypeError, "must be True or False"),
    ("residual_diagnostics", "factor", "x", TypeError, "must be a real number"),
    ("estimate_noise", "per_component", 1, TypeError, "must be True or False"),
    ("estimate_noise", "search", "no", TypeError, "must be True or False"),
    ("estimate_noise", "max_evaluations", BIG, ValueError, "must be an integer <= 2147483647"),
    ("estimate_noise", "smoother", 3, TypeError, "must be a ceemx.LMSmoother or None"),
    ("warm_start", "process_noise", -1.0, ValueError, "must be finite and > 0"),
    ("warm_start", "process_noise", np.nan, ValueError, "must be finite and > 0"),
    ("learn", "weights", "x", TypeError, "must be (B,) = (1,) numbers"),
    ("learn", "weights", [np.nan], ValueError, "must be (B,) = (1,) finite numbers >= 0"),
    ("particle_filter", "n_particles", BIG, ValueError, "must be an integer <= 2147483647"),
    ("hybrid", "use_input", "no", TypeError, "must be True or False"),
    ("hybrid", "bound_sharpness", True, TypeError, "must be a real number"),
    ("hybrid", "width", BIG, ValueError, "must be an integer <= 2147483647"),
    ("hybrid", "depth", 10**30, ValueError, "must be an integer <= 2147483647"),
    ("EarlyStopping", "patience", BIG, ValueError, "must be an integer <= 2147483647"),
    ("perturb", "frac", -1.0, ValueError, "must be finite and >= 0"),
    ("perturb", "where", 3, TypeError, "must be a callable or None"),
    ("enable_compilation_cache", "path", 3, TypeError, "must be a path (str or os.PathLike)"),
    ("enable_compilation_cache", "min_compile_time_s", True, TypeError, "must be a real number"),
    ("plot_benchmark", "n_init", 2.5, TypeError, "must be an integer"),
    ("plot_benchmark", "max_points", -1, ValueError, "must be an integer in [2, 2147483647]"),
    ("plot_benchmark", "zoom_fraction", -1.0, ValueError, "must be in (0, 1]"),
    ("plot_benchmark", "dt", -1.0, ValueError, "must be finite and > 0"),
]


def _message(exc, name: str, says: str):
    """The option's name in backticks then ``says`` (or, for a TypeError under the slow tier's
    jaxtyping + beartype checks of annotated functions, their message naming the parameter)."""
    pattern = rf"`{re.escape(name)}(\[0\])?` {re.escape(says)}"
    if exc is TypeError:
        pattern += f"|parameter '{re.escape(name)}'"
    return pattern


@pytest.mark.parametrize(
    "entry, name, bad, exc, says",
    CASES,
    ids=[f"{c[0]}-{c[1]}={c[2]!r:.12}" for c in CASES],
)
def test_bad_option_is_refused_at_entry_naming_it(entry, name, bad, exc, says, monkeypatch):
    # Compute starts with the solvers' and the smoother's programs: a check after them fails.
    for module, attr in [
        ("ceemx.identification.fitting.run", "run_fit"),
        ("ceemx.inference.smoother", "smooth_batch"),
        ("ceemx.identification.hybrid_builder", "warm_start_states"),
    ]:
        monkeypatch.setattr(f"{module}.{attr}", _never)
    with pytest.raises(exc, match=_message(exc, name, says)):
        CALLS[entry](**{name: bad})


def test_hybrid_too_big_for_memory_is_refused_before_any_allocation(monkeypatch):
    """``width=10**9`` aborted the process (an XLA CHECK failure, SIGABRT); 10**6 raised
    RESOURCE_EXHAUSTED after the default start's smoothing. Both are refused at entry now, with
    the estimate, before the default start (``states=None``) or any weight is drawn."""
    monkeypatch.setattr(hybrid_builder, "warm_start_states", _never)
    monkeypatch.setattr("ceemx.systems.learned_term.init_mlp", _never)
    for width in (10**6, 10**9):
        with pytest.raises(ValueError, match=rf"MLP of width {width} and depth 2.* GiB"):
            ceemx.hybrid(SYSTEM, DATA, width=width)


def test_paths_may_be_path_like(tmp_path):
    assert check_path("checkpoint", pathlib.Path(tmp_path)) == str(tmp_path)
    assert check_path("checkpoint", None, none=True) is None
    with pytest.raises(TypeError, match="`checkpoint` must be a path"):
        check_path("checkpoint", os.fsencode(str(tmp_path)))
    assert INT32_MAX == np.iinfo(np.int32).max
