"""Subspace identification of linear state-space models from many trajectories (N4SID).

The model is the innovation form of a linear-Gaussian system,

    x_{t+1} = A x_t + B u_t + w_t,    y_t = C x_t + D u_t + v_t,    cov([w; v]) = [[Q, S], [Sᵀ, R]],

identified by the combined deterministic–stochastic N4SID of Van Overschee & De Moor (Automatica
30(1), 1994), extended to a batch of independent trajectories. Everything is host NumPy/SciPy
(float64); nothing here knows about EM, systems or data containers.

**Data matrix.** With horizon k, each window of 2k consecutive samples of one trajectory is one
column of the block-Hankel matrix

    H = [U_{0|2k−1}; Y_{0|2k−1}],   r = 2k(p + m) rows,

whose block row i holds u_{c+i} (resp. y_{c+i}) in column c. Trajectory b contributes
T_b − 2k + 1 columns; the columns of all trajectories are placed side by side (no window ever
straddles two trajectories), N = Σ_b (T_b − 2k + 1) columns in all. Past and future are
U_p = U_{0|k−1}, U_f = U_{k|2k−1}, W_p = [U_p; Y_p], Y_f = Y_{k|2k−1}.

**Compression.** Hᵀ = Q̃ R̃ (thin QR, Q̃ᵀQ̃ = I) gives H = L Q̃ᵀ with L = R̃ᵀ (r × r). Inner products
of data rows are those of the rows of L (H Hᵀ = L Lᵀ), so every row-space projection below is done
on the rows of L and Q̃ is never formed. R̃ is accumulated trajectory by trajectory,
R̃ ← triu(qr([R̃; H_bᵀ])), in O(r² + r·chunk) memory whatever N is.

**Oblique projections.** O_k = Y_f /_{U_f} W_p: write the projection of Y_f onto the row space of
[U_f; W_p] as Θ_U U_f + Θ_W W_p and keep Θ_W W_p. Likewise O_{k−1} = Y_f⁻ /_{U_f⁻} W_p⁺ with the
border moved one block later (Y_f⁻ = Y_{k+1|2k−1}, U_f⁻ = U_{k+1|2k−1}, W_p⁺ = [U_{0|k}; Y_{0|k}]).

**Order and observability.** The weighted SVD W₁ O_k W₂ / √N = U Σ Vᵀ (``weighting``: N4SID
W₁ = W₂ = I; MOESP W₂ = Π_{U_f⊥}; CVA additionally W₁ = (Y_f Π_{U_f⊥} Y_fᵀ / N)^{−1/2}) is
truncated to ``order`` = n singular values, and Γ_k = W₁⁻¹ U₁ Σ₁^{1/2} is the extended
observability matrix [C; CA; …; CA^{k−1}] in a balanced basis; Γ_{k−1} drops its last block row.

**State sequence and system matrices.** X_k = Γ_k⁺ O_k and X_{k+1} = Γ_{k−1}⁺ O_{k−1} are
Kalman-filter state sequences; the least-squares regression

    [X_{k+1}; Y_{k|k}] = [[A, B], [C, D]] [X_k; U_{k|k}] + [ρ_w; ρ_v]

gives A, B, C, D, and the residual covariance ρρᵀ/N gives Q, R, S (the innovation form:
Q ≈ K R Kᵀ, S ≈ K R with the Kalman gain K = S R⁻¹). Finally, each trajectory's initial state x₀
(the state at its first sample) is the least-squares fit of its simulated output error,
y_t − D u_t − Σ_{s<t} C A^{t−1−s} B u_s = C A^t x₀ + e_t (:mod:`ceemx.lib.output_error`, which
also refits B, D and x₀ to that error for a simulation model).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from jaxtyping import Float

from ceemx.lib.output_error import initial_states, spectral_radius, stabilize

__all__ = ["SubspaceResult", "default_horizon", "n4sid"]


@dataclasses.dataclass(frozen=True)
class SubspaceResult:
    """The output of :func:`n4sid` (NumPy float64 arrays).

    Attributes:
        A: (n, n) state transition.
        B: (n, p) input matrix.
        C: (m, n) observation matrix.
        D: (m, p) feedthrough.
        Q: (n, n) covariance of the state-equation residual ρ_w (innovation form: ≈ K R Kᵀ, rank
            ≤ m).
        R: (m, m) covariance of the output-equation residual ρ_v (the innovation covariance).
        S: (n, m) cross-covariance E[ρ_w ρ_vᵀ].
        K: (n, m) Kalman gain S R⁺ of the innovation form x_{t+1} = A x + B u + K e,
            y = C x + D u + e.
        singular_values: (k·m,) singular values of W₁ O_k W₂ / √N, largest first (choose the order
            from their gap).
        state_cov: (n, n) second moment X_k X_kᵀ / N of the estimated state sequence.
        x0: (B, n) least-squares initial state of every trajectory (``None`` when not estimated).
        horizon: the horizon k used.
        num_columns: N, the number of block-Hankel columns (windows) over all trajectories.
        stabilized: whether the regression's A was unstable and was replaced by its stable
            projection (:func:`~ceemx.lib.output_error.stabilize`; ``n4sid(..., stable=True)``).
    """

    A: Float[np.ndarray, "n n"]
    B: Float[np.ndarray, "n p"]
    C: Float[np.ndarray, "m n"]
    D: Float[np.ndarray, "m p"]
    Q: Float[np.ndarray, "n n"]
    R: Float[np.ndarray, "m m"]
    S: Float[np.ndarray, "n m"]
    K: Float[np.ndarray, "n m"]
    singular_values: Float[np.ndarray, " km"]
    state_cov: Float[np.ndarray, "n n"]
    x0: Float[np.ndarray, "B n"] | None
    horizon: int
    num_columns: int
    stabilized: bool = False


def default_horizon(order: int, obs_dim: int) -> int:
    """The default horizon k = max(10, ⌈2n/m⌉ + 1) (before shortening for short trajectories).

    k ≥ ⌈n/m⌉ + 1 is required (Γ_{k−1} must have rank n); twice that lets the past windows of
    length k carry the Kalman-filter state well for noisy data, and 10 is a floor that keeps the
    bias of finite-horizon filters small for the low-order, many-output systems of the paper while
    keeping r = 2k(m + p) moderate.
    """
    return max(10, math.ceil(2 * order / obs_dim) + 1)


def _as_list(name: str, value, dim_name: str) -> list[np.ndarray]:
    """A list of (T_b, d) float64 arrays from a (T, d) array, a (B, T, d) array or a sequence."""
    if isinstance(value, np.ndarray) or hasattr(value, "__array__"):
        arr = np.asarray(value)
        if arr.ndim == 2:
            items = [arr]
        elif arr.ndim == 3:
            items = list(arr)
        else:
            raise ValueError(
                f"`{name}` must be a (T, {dim_name}) or (B, T, {dim_name}) array or a sequence of "
                f"(T_b, {dim_name}) arrays; got an array of shape {arr.shape}."
            )
    elif isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        items = [np.asarray(v) for v in value]
    else:
        raise ValueError(
            f"`{name}` must be an array or a sequence of arrays; got {type(value).__name__}."
        )
    if not items:
        raise ValueError(f"`{name}` holds no trajectory.")
    out = []
    for b, a in enumerate(items):
        if a.ndim != 2:
            raise ValueError(
                f"`{name}[{b}]` must have shape (T_b, {dim_name}); got shape {a.shape}."
            )
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"`{name}[{b}]` must be real numbers; got dtype {a.dtype}.")
        a = a.astype(np.float64)
        if not np.all(np.isfinite(a)):
            t, j = (int(i) for i in np.argwhere(~np.isfinite(a))[0])
            raise ValueError(
                f"`{name}[{b}]` has a non-finite value {a[t, j]} at index [{t}, {j}]; N4SID "
                "needs complete records."
            )
        out.append(a)
    dims = {a.shape[1] for a in out}
    if len(dims) != 1:
        raise ValueError(f"every `{name}[b]` must have the same {dim_name}; got {sorted(dims)}.")
    return out


def _hankel_columns(u: np.ndarray, y: np.ndarray, k: int) -> np.ndarray:
    """Hᵀ of one trajectory: (T − 2k + 1, 2k(p + m)); row c is [u_c, …, u_{c+2k−1}, y_c, …]."""
    parts = []
    for a in (u, y):
        win = np.lib.stride_tricks.sliding_window_view(a, 2 * k, axis=0)  # (j, d, 2k)
        parts.append(np.swapaxes(win, 1, 2).reshape(win.shape[0], -1))
    return np.concatenate(parts, axis=1)


def _triangular(a: np.ndarray) -> np.ndarray:
    """The triangular factor R of a = Q R (Householder QR, LAPACK geqrf)."""
    return np.asarray(np.linalg.qr(a, mode="r"))


def _compress(us, ys, k: int, r: int, chunk_rows: int) -> np.ndarray:
    """Upper-triangular R̃ (r × r) with Hᵀ = Q̃ R̃, accumulated over chunks of windows."""
    rfac: np.ndarray = np.zeros((0, r))
    buf: list[np.ndarray] = []
    rows = 0
    for u, y in zip(us, ys, strict=True):
        block = _hankel_columns(u, y, k)
        buf.append(block)
        rows += block.shape[0]
        if rows >= chunk_rows:
            rfac = _triangular(np.vstack([rfac, *buf]))[:r]
            buf, rows = [], 0
    if buf:
        rfac = _triangular(np.vstack([rfac, *buf]))[:r]
    if rfac.shape[0] < r:  # fewer windows than rows: pad with zero rows (rank-deficient factor)
        rfac = np.vstack([rfac, np.zeros((r - rfac.shape[0], r))])
    return rfac


def _coefficients(target: np.ndarray, basis: np.ndarray, rcond: float) -> np.ndarray:
    """Minimum-norm Θ with Θ·basis ≈ target (rows are vectors; singular values < rcond·max cut)."""
    if basis.shape[0] == 0:
        return np.zeros((target.shape[0], 0))
    coef = np.linalg.lstsq(basis.T, target.T, rcond=rcond)[0]
    return coef.T


def _oblique(target: np.ndarray, along: np.ndarray, onto: np.ndarray, rcond: float) -> np.ndarray:
    """Target /_along onto: the onto-part of the projection on the rows of [along; onto]."""
    coef = _coefficients(target, np.vstack([along, onto]), rcond)
    return coef[:, along.shape[0] :] @ onto


def _perp(a: np.ndarray, basis: np.ndarray, rcond: float) -> np.ndarray:
    """The rows of a with their projection on the rows of basis removed (a Π_{basis⊥})."""
    if basis.shape[0] == 0:
        return a
    return a - _coefficients(a, basis, rcond) @ basis


def _trajectories(y, u) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``y`` and ``u`` as lists of (T_b, m) and (T_b, p) float64 arrays of matching lengths."""
    ys = _as_list("y", y, "m")
    if u is None:
        return ys, [np.zeros((a.shape[0], 0)) for a in ys]
    us = _as_list("u", u, "p")
    if len(us) != len(ys):
        raise ValueError(f"`u` has {len(us)} trajectories but `y` has {len(ys)}.")
    for b, (ub, yb) in enumerate(zip(us, ys, strict=True)):
        if ub.shape[0] != yb.shape[0]:
            raise ValueError(
                f"`u[{b}]` has {ub.shape[0]} time steps but `y[{b}]` has {yb.shape[0]}."
            )
    return ys, us


def _check_order(order, m: int, weighting: str) -> int:
    """The number of states n = ``order``, checked with the outputs (m ≥ 1) and ``weighting``."""
    if m == 0:
        raise ValueError("`y` must have at least one output (m ≥ 1).")
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1:
        raise ValueError(f"`order` must be a positive integer; got {order!r}.")
    if weighting not in ("n4sid", "moesp", "cva"):
        raise ValueError(f"`weighting` must be 'n4sid', 'moesp' or 'cva'; got {weighting!r}.")
    return int(order)


def _horizon(horizon, ys: list[np.ndarray], n: int, m: int) -> int:
    """The horizon k: ``horizon`` checked against n and the lengths, or the default shortened."""
    shortest = min(a.shape[0] for a in ys)
    k_min = math.ceil(n / m) + 1
    if horizon is None:
        k = min(default_horizon(n, m), shortest // 2)
        if k < k_min:
            raise ValueError(
                f"`order` = {n} needs a horizon k ≥ {k_min} (with m = {m} outputs) and so "
                f"trajectories of at least {2 * k_min} steps; the shortest has {shortest}."
            )
        return k
    if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)):
        raise ValueError(f"`horizon` must be an integer; got {horizon!r}.")
    k = int(horizon)
    if (k - 1) * m < n:
        raise ValueError(
            f"`order` = {n} is too large for `horizon` = {k} with m = {m} outputs: N4SID "
            f"needs (k − 1)·m ≥ n, i.e. k ≥ {k_min}."
        )
    for b, a in enumerate(ys):
        if a.shape[0] < 2 * k:
            raise ValueError(
                f"trajectory {b} has {a.shape[0]} steps; `horizon` = {k} needs at least "
                f"2k = {2 * k}."
            )
    return k


def _num_windows(ys: list[np.ndarray], k: int, r: int) -> int:
    """N, the windows of 2k steps over all trajectories (at least the r data rows)."""
    N = sum(a.shape[0] - 2 * k + 1 for a in ys)
    if N < r:
        raise ValueError(
            f"too few data: {N} windows of 2k = {2 * k} steps for r = 2k(m + p) = {r} data rows; "
            "give more or longer trajectories or a smaller `horizon`."
        )
    return N


@dataclasses.dataclass(frozen=True)
class _Rows:
    """The rows of L (H = L Q̃ᵀ) that stand for the block rows of U_{0|2k−1} and Y_{0|2k−1}."""

    L: np.ndarray
    k: int
    p: int
    m: int

    def u(self, a: int, b: int) -> np.ndarray:
        """U_{a|b−1}."""
        return self.L[a * self.p : b * self.p]

    def y(self, a: int, b: int) -> np.ndarray:
        """Y_{a|b−1}."""
        first = 2 * self.k * self.p
        return self.L[first + a * self.m : first + b * self.m]

    def past(self, b: int) -> np.ndarray:
        """W_{0|b−1} = [U_{0|b−1}; Y_{0|b−1}]."""
        return np.vstack([self.u(0, b), self.y(0, b)])


def _cva_weights(Yf: np.ndarray, Uf: np.ndarray, scale: float, rcond: float):
    """CVA's W₁ = (Y_f Π_{U_f⊥} Y_fᵀ / N)^{−1/2} and its inverse (pseudo-inverse roots)."""
    yf_perp = _perp(Yf, Uf, rcond) * scale
    evals, evecs = np.linalg.eigh(yf_perp @ yf_perp.T)
    keep = evals > rcond * max(float(evals.max()), np.finfo(float).tiny)
    root = np.sqrt(np.where(keep, evals, 0.0))
    inv_root = np.where(keep, 1.0 / np.where(keep, root, 1.0), 0.0)
    return (evecs * inv_root) @ evecs.T, (evecs * root) @ evecs.T


def _observability(Ok, Uf, Yf, *, n: int, N: int, weighting: str, rcond: float):
    """Γ_k from the SVD of W₁ O_k W₂ / √N truncated to n; returns (Γ_k, singular values)."""
    scale = 1.0 / math.sqrt(N)
    if weighting == "n4sid":
        weighted, w1_inv = Ok * scale, None
    else:
        weighted = _perp(Ok, Uf, rcond) * scale
        w1_inv = None
        if weighting == "cva":
            w1, w1_inv = _cva_weights(Yf, Uf, scale, rcond)
            weighted = w1 @ weighted
    U, sv, _ = np.linalg.svd(weighted, full_matrices=False)
    gamma = U[:, :n] * np.sqrt(sv[:n])
    if w1_inv is not None:
        gamma = w1_inv @ gamma
    return gamma, sv


def _regression(Xk, Xk1, rows: _Rows, *, N: int, rcond: float):
    """[[A, B], [C, D]] from [X_{k+1}; Y_{k|k}] ≈ Θ [X_k; U_{k|k}] and the residual covariance."""
    k = rows.k
    lhs = np.vstack([Xk1, rows.y(k, k + 1)])
    rhs = np.vstack([Xk, rows.u(k, k + 1)])
    theta = _coefficients(lhs, rhs, rcond)
    resid = lhs - theta @ rhs
    cov = resid @ resid.T / N
    return theta, 0.5 * (cov + cov.T)


def n4sid(
    y,
    u=None,
    *,
    order: int,
    horizon: int | None = None,
    weighting: str = "n4sid",
    estimate_x0: bool = True,
    rcond: float = 1e-10,
    chunk_rows: int | None = None,
    stable: bool = False,
    refit: bool = False,
) -> SubspaceResult:
    """Identify (A, B, C, D) and residual covariances from many trajectories by N4SID.

    The algorithm and its equations are in the module notes. The data should be (roughly)
    zero-mean: a constant offset is not part of the model.

    Args:
        y: outputs: a (T, m) array (one trajectory), a (B, T, m) array, or a sequence of
            (T_b, m) arrays (trajectories of different lengths).
        u: inputs with the same structure and lengths, (…, p); ``None`` for none (p = 0).
        order: n, the number of states (1 ≤ n ≤ (k − 1)·m).
        horizon: k, the number of block rows of the past and of the future. ``None``:
            :func:`default_horizon`, shortened to ⌊min_b T_b / 2⌋ for short trajectories.
        weighting: ``"n4sid"`` (W₁ = W₂ = I), ``"moesp"`` (W₂ = Π_{U_f⊥}) or ``"cva"`` (canonical
            variates) — the SVD weights that choose the state basis and the retained subspace.
        estimate_x0: also estimate each trajectory's initial state (``x0``).
        rcond: relative singular-value cutoff of the least-squares projections (rank decisions
            on noiseless data).
        chunk_rows: windows stacked before each QR update (``None``: max(4r, 4096)); memory is
            O(r·(r + chunk_rows)).
        stable: when the estimated A is unstable (spectral radius ≥ 1), replace it by its
            stable projection and refit B, D and x₀ (:func:`~ceemx.lib.output_error.stabilize`;
            ``SubspaceResult.stabilized`` says so).
        refit: always refit B, D and x₀ to the free-run simulation error at the estimated
            (A, C) (:func:`~ceemx.lib.output_error.stabilize`, which also projects an unstable
            A): N4SID's B and D are those of the one-step predictor, which on nonlinear or offset
            data can simulate far off (the cascaded tanks' order-2 model: 532 V test RMSE, 1.9 V
            refitted).

    Returns:
        A :class:`SubspaceResult` in float64.

    Raises:
        ValueError: for arrays of the wrong rank, mismatched dimensions or lengths between ``y``
            and ``u``, non-finite values (naming the trajectory and index), a non-positive
            ``order``, a horizon too short for the order ((k − 1)·m < n), a trajectory shorter
            than 2k, fewer windows N than data rows r = 2k(m + p), or an unknown ``weighting``.

    Example:
        >>> import numpy as np
        >>> from ceemx.lib.subspace import n4sid
        >>> rng = np.random.default_rng(0)
        >>> u = rng.standard_normal((4, 200, 1))
        >>> x, y = np.zeros(4), np.zeros((4, 200, 1))
        >>> for t in range(200):
        ...     y[:, t] = 0.5 * x[:, None] + u[:, t]
        ...     x = 0.9 * x + u[:, t, 0]
        >>> res = n4sid(y, u, order=1, horizon=3)
        >>> bool(abs(res.A[0, 0] - 0.9) < 1e-8)
        True
    """
    ys, us = _trajectories(y, u)
    m, p = ys[0].shape[1], us[0].shape[1]
    n = _check_order(order, m, weighting)
    k = _horizon(horizon, ys, n, m)
    r = 2 * k * (m + p)
    N = _num_windows(ys, k, r)
    chunk = max(4 * r, 4096) if chunk_rows is None else max(int(chunk_rows), 1)

    rows = _Rows(_compress(us, ys, k, r, chunk).T, k, p, m)  # the rows of L stand for data rows
    Xk, Xk1, sv = _state_sequences(rows, n=n, N=N, weighting=weighting, rcond=rcond)
    fit = _regression(Xk, Xk1, rows, N=N, rcond=rcond)
    options = dict(estimate_x0=estimate_x0, stable=stable, refit=refit)
    return _result(fit, Xk, sv, us, ys, k=k, N=N, **options)


def _result(fit, Xk, sv, us, ys, *, k: int, N: int, estimate_x0: bool, stable: bool, refit: bool):
    """The :class:`SubspaceResult` of the regression ``fit`` = (Θ, residual covariance).

    A, B, C, D are Θ's blocks and Q, R, S the covariance's (module notes); B, D and x₀ are
    refitted to the simulation error when A is unstable and ``stable`` (or always with ``refit``),
    else the x₀ alone are fitted (when ``estimate_x0``).
    """
    (theta, cov), n = fit, Xk.shape[0]
    A, B = theta[:n, :n], theta[:n, n:]
    C, D = theta[n:, :n], theta[n:, n:]
    Q, R, S = cov[:n, :n], cov[n:, n:], cov[:n, n:]
    K = S @ np.linalg.pinv(R)
    stabilized = bool((stable or refit) and spectral_radius(A) >= 1.0)
    if stabilized or refit:
        A, B, D, x0 = stabilize(A, B, C, D, us, ys)
        x0 = x0 if estimate_x0 else None
    else:
        x0 = initial_states(us, ys, A, B, C, D, k) if estimate_x0 else None
    state_cov = Xk @ Xk.T / N
    return SubspaceResult(A, B, C, D, Q, R, S, K, sv, state_cov, x0, k, N, stabilized)


def _state_sequences(rows: _Rows, *, n: int, N: int, weighting: str, rcond: float):
    """X_k and X_{k+1} from the oblique projections O_k, O_{k−1} and Γ_k; the singular values."""
    k, m = rows.k, rows.m
    Uf, Yf = rows.u(k, 2 * k), rows.y(k, 2 * k)
    Ok = _oblique(Yf, Uf, rows.past(k), rcond)
    Ok1 = _oblique(rows.y(k + 1, 2 * k), rows.u(k + 1, 2 * k), rows.past(k + 1), rcond)
    gamma, sv = _observability(Ok, Uf, Yf, n=n, N=N, weighting=weighting, rcond=rcond)
    Xk = np.linalg.pinv(gamma) @ Ok
    Xk1 = np.linalg.pinv(gamma[:-m]) @ Ok1
    return Xk, Xk1, sv
