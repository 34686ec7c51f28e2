"""Laplace EM on one long record, piece by piece: the figures behind the coarse start.

    python benchmarks/probes/laplace_long_parts.py gradient [T]          # default T = 100 000
    python benchmarks/probes/laplace_long_parts.py coarse [T] [SIZE ...]  # 10 000 5 000 2 500
    python benchmarks/probes/laplace_long_parts.py escape

``gradient``: at the mass–spring–damper record of ``benchmarks/laplace_long_record.py`` (θ after
3 quasi-Newton epochs), the Laplace posterior (E-step from converged states) and the θ-gradient
of Q by cubature, each compiled then timed (median of 5).
``coarse``: quasi-Newton Laplace EM with ``coarse_start`` = each SIZE (median of 3 steady fits:
time, epochs on the record, the coarse fit's epochs), and the coarse θ alone — the first SIZE
samples fitted, then the record from their θ with ``coarse_start=None``, so with EM's metric as
the curvature's start: its epochs.
``escape``: ``fit(noise="learn")`` with JointLM on the stiff model of ``tests/stiff_model.py``
(process noise guessed 100× too small) with and without ``estimate_noise``'s decade escape
(``_ESCAPES`` 3 / 0): wall time (the first of each compiles), posterior evaluations, evidence.

Backs: ``benchmarks/README.md`` ("Coarse start and fewer dynamics evaluations"),
``docs/design.md`` (Laplace EM, noise without guessing). Record ``uptime``.
"""

import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [
    os.path.dirname(HERE),
    os.path.join(os.path.dirname(os.path.dirname(HERE)), "tests"),
]

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import laplace_long_record as llr  # noqa: E402

import ceemx  # noqa: E402

TRAINABLE = lambda s: (s.k, s.c, s.process_noise, s.obs_noise)  # noqa: E731


def qn(start, data, coarse):
    """A quasi-Newton Laplace EM fit with the given ``coarse_start``."""
    solver = ceemx.LaplaceEM(acceleration="quasi_newton", coarse_start=coarse)
    return ceemx.fit(start, data, solver=solver, trainable=TRAINABLE)


def median_time(f, reps=5):
    """Median wall time of ``f()`` (results blocked on) after one untimed call."""
    jax.block_until_ready(f())
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def gradient(T):
    from ceemx.identification.problem import FitProblem
    from ceemx.identification.solvers.laplace_qn import q_derivatives
    from ceemx.inference.posterior import E_STEP_SMOOTHER, gaussian_posterior

    start, data = llr.problem(T)
    r = llr.laplace_qn_fit(start, data, max_epochs=3)
    problem, theta = FitProblem.create(r.system, data, trainable=TRAINABLE)
    e = gaussian_posterior(E_STEP_SMOOTHER, problem.build(theta), r.states, data)
    post = median_time(
        lambda: gaussian_posterior(E_STEP_SMOOTHER, problem.build(theta), r.states, data).states
    )
    grad = median_time(lambda: q_derivatives(problem, theta, e, hessian=False)[1])
    print(f"T {T}: posterior {1e3 * post:.1f} ms, gradient of Q {1e3 * grad:.1f} ms")


def coarse(T, sizes):
    start, data = llr.problem(T)
    for size in sizes:
        qn(start, data, size)
        times, r = [], None
        for _ in range(3):
            t0 = time.perf_counter()
            r = qn(start, data, size)
            times.append(time.perf_counter() - t0)
        first = {k: v for k, v in r.history[0].items() if k.startswith("coarse")}
        window = qn(start, data.head(size), None)
        theta_only = qn(window.system, data, None)
        print(
            f"coarse_start {size}: {statistics.median(times):.2f} s, {r.epochs} epochs "
            f"({first}); the coarse θ with EM's metric: {theta_only.epochs} epochs",
            flush=True,
        )


def escape():
    import stiff_model as sm

    import ceemx.identification.analysis.noise_estimate as noise

    _, data, _ = sm.simulate(jax.random.PRNGKey(0), B=2, T=1000)
    guess = sm.make(sm.perturbed(jax.random.PRNGKey(1)), process_std=sm.PROCESS_STD * 0.01)
    counting = noise.residual_moments
    calls = [0]

    def counted(*a, **k):
        calls[0] += 1
        return counting(*a, **k)

    for escapes in (3, 0, 3, 0):
        calls[0] = 0
        noise._ESCAPES, noise.residual_moments = escapes, counted
        t0 = time.perf_counter()
        r = ceemx.fit(guess, data, solver=ceemx.JointLM(), noise="learn", max_epochs=300)
        noise.residual_moments = counting
        print(
            f"escapes {escapes}: {time.perf_counter() - t0:.1f} s, {calls[0]} evaluations, "
            f"log-evidence {r.noise_rounds[-1]['log_evidence']:.6f}",
            flush=True,
        )


if __name__ == "__main__":
    mode, rest = sys.argv[1], [int(a) for a in sys.argv[2:]]
    T = rest[0] if rest else 100_000
    if mode == "gradient":
        gradient(T)
    elif mode == "coarse":
        coarse(T, rest[1:] or [10_000, 5_000, 2_500])
    elif mode == "escape":
        escape()
    else:
        raise SystemExit(__doc__)
