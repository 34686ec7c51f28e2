"""Least-squares refits of a linear model to its free-run simulation error, (A, C) fixed.

With (A, C) fixed, a linear model's free-run output

    y_t = C Aᵗ x₀ + Σ_{s<t} C A^{t−1−s} B u_s + D u_t

is linear in each trajectory's initial state x₀ and in (B, D). :func:`initial_states` fits the x₀
alone (N4SID's last step, :func:`ceemx.lib.subspace.n4sid`); :func:`stabilize` pulls A's
eigenvalues into a disc and fits B, D and every x₀ together — a simulation model rather than the
one-step predictor N4SID's regression gives. Host NumPy (float64), like the subspace method.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["initial_states", "output_powers", "spectral_radius", "stabilize"]


def spectral_radius(a: np.ndarray) -> float:
    """The spectral radius max |λ(a)| (0 for an empty matrix)."""
    return float(np.max(np.abs(np.linalg.eigvals(a)))) if a.size else 0.0


def output_powers(A: np.ndarray, C: np.ndarray, T: int) -> np.ndarray:
    """(T, m, n) C Aᵗ for t < T: the free response of the output to x₀."""
    out = np.empty((T,) + C.shape)
    power = np.eye(A.shape[0])
    for t in range(T):
        out[t] = C @ power
        power = A @ power
    return out


def initial_states(us, ys, A, B, C, D, k: int) -> np.ndarray:
    """Least-squares x₀ of every trajectory from its simulated output error (module notes).

    For an unstable A only the first steps are fitted, those where Aᵗ stays below 10⁶ (at least
    2k, k the N4SID horizon). Returns (len(ys), n).
    """
    n = A.shape[0]
    lengths = np.array([y.shape[0] for y in ys])
    T_max = int(lengths.max())
    rho = spectral_radius(A)
    if rho > 1.0 + 1e-8:  # unstable: fit on the steps where A^t stays below 1e6
        T_max = min(T_max, max(2 * k, int(math.log(1e6) / math.log(rho))))
    Bn, m = len(ys), ys[0].shape[1]
    # zero-state responses of all trajectories at once (padded with zeros past each length)
    u_pad = np.zeros((Bn, T_max, B.shape[1]))
    y_pad = np.zeros((Bn, T_max, m))
    for b, (u, y) in enumerate(zip(us, ys, strict=True)):
        t = min(T_max, y.shape[0])
        u_pad[b, :t], y_pad[b, :t] = u[:t], y[:t]
    resid = y_pad - u_pad @ D.T
    x = np.zeros((Bn, n))
    for t in range(T_max):
        resid[:, t] -= x @ C.T
        x = x @ A.T + u_pad[:, t] @ B.T
    obs = output_powers(A, C, T_max)
    x0 = np.empty((Bn, n))
    steps = np.minimum(lengths, T_max)
    for t in np.unique(steps):
        idx = np.flatnonzero(steps == t)
        lhs = obs[:t].reshape(-1, n)
        rhs = resid[idx, :t].reshape(len(idx), -1).T
        x0[idx] = np.linalg.lstsq(lhs, rhs, rcond=None)[0].T
    return x0


def stabilize(A, B, C, D, us, ys, *, radius: float = 0.999):
    """A stable simulation model near (A, B, C, D), with B, D and x₀ refitted to the data.

    A's eigenvalues are pulled into |λ| ≤ ``radius``: N4SID's least-squares A can be unstable
    on short or nonlinear records, and its free run then explodes. Each eigenvalue outside the
    disc keeps its phase and moves to the radius (conjugate pairs alike, so A stays real); the
    input matrix B, the feedthrough D and every trajectory's x₀ are then the least-squares fit of
    the free-run simulation error, which is linear in them once A and C are fixed:
    y_t = C Aᵗ x₀ + Σ_{s<t} C A^{t−1−s} B u_s + D u_t.

    Returns:
        (A, B, D, x0) as float64 arrays, x0 of shape (len(ys), n).
    """
    n, p = B.shape
    m = C.shape[0]
    lam, V = np.linalg.eig(A)
    scale = np.minimum(1.0, radius / np.maximum(np.abs(lam), 1e-300))
    A = np.real(V @ np.diag(lam * scale) @ np.linalg.inv(V))
    cols = []  # per trajectory: (T·m, n·p + m·p) regressors of vec(B), vec(D); (T·m, n) of x0
    powers = output_powers(A, C, max(y.shape[0] for y in ys))
    for u, y in zip(us, ys, strict=True):
        T = y.shape[0]
        reg = np.zeros((T, m, n * p + m * p))
        xs = np.zeros((n * p, n))  # row i·p + j: the state's response to B's entry (i, j)
        rows_q = np.arange(n)[:, None] * p + np.arange(p)[None, :]
        for t in range(T):
            reg[t, :, : n * p] = (xs @ C.T).T
            reg[t, :, n * p :] = np.kron(np.eye(m), u[t][None, :])
            xs = xs @ A.T
            xs[rows_q, np.arange(n)[:, None]] += u[t][None, :]
        cols.append((reg.reshape(T * m, -1), powers[:T].reshape(T * m, n), y.reshape(-1)))
    Bn = len(cols)
    rows = sum(c[0].shape[0] for c in cols)
    lhs = np.zeros((rows, n * p + m * p + Bn * n))
    rhs = np.zeros(rows)
    r = 0
    for b, (reg, obs, y) in enumerate(cols):
        k = reg.shape[0]
        lhs[r : r + k, : n * p + m * p] = reg
        lhs[r : r + k, n * p + m * p + b * n : n * p + m * p + (b + 1) * n] = obs
        rhs[r : r + k] = y
        r += k
    sol = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    B = sol[: n * p].reshape(n, p)
    D = sol[n * p : n * p + m * p].reshape(m, p)
    x0 = sol[n * p + m * p :].reshape(Bn, n)
    return A, B, D, x0
