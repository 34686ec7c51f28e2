"""Textbook EM for a linear-Gaussian state-space model, in plain NumPy float64.

A reference to compare the library against, written for clarity rather than speed
(Shumway & Stoffer 1982; Ghahramani & Hinton 1996).

Model (no inputs), for t = 1..T and B independent trajectories sharing all parameters::

    x_1 ~ N(mu0, P0)
    x_{t+1} = A x_t + w_t,   w_t ~ N(0, Q)
    y_t     = C x_t + v_t,   v_t ~ N(0, R)

mu0 and P0 are known and never updated; EM updates full A, C, Q and R.
"""

import numpy as np

_LOG_2PI = np.log(2.0 * np.pi)


def _sym(M):
    return 0.5 * (M + M.swapaxes(-1, -2))


def kalman_smoother(y, A, C, Q, R, mu0, P0):
    """Kalman filter then Rauch-Tung-Striebel smoother for one trajectory ``y`` of shape (T, m).

    Returns a dict with
      ``mean``  (T, n)       E[x_t | y_{1:T}]
      ``cov``   (T, n, n)    Cov(x_t | y_{1:T})
      ``cross`` (T-1, n, n)  Cov(x_{t+1}, x_t | y_{1:T})  (row block t+1, column block t)
      ``loglik``             log p(y_{1:T}), exact, from the innovations.
    """
    y = np.asarray(y, dtype=np.float64)
    A, C, Q, R = (np.asarray(M, dtype=np.float64) for M in (A, C, Q, R))
    mu0 = np.asarray(mu0, dtype=np.float64)
    P0 = np.asarray(P0, dtype=np.float64)
    T, m = y.shape
    n = A.shape[0]

    x_pred = np.zeros((T, n))  # E[x_t | y_{1:t-1}]
    P_pred = np.zeros((T, n, n))  # Cov(x_t | y_{1:t-1})
    x_filt = np.zeros((T, n))  # E[x_t | y_{1:t}]
    P_filt = np.zeros((T, n, n))  # Cov(x_t | y_{1:t})
    loglik = 0.0

    # Forward pass: Kalman filter.
    for t in range(T):
        if t == 0:
            x_pred[t] = mu0
            P_pred[t] = P0
        else:
            x_pred[t] = A @ x_filt[t - 1]
            P_pred[t] = _sym(A @ P_filt[t - 1] @ A.T + Q)

        e = y[t] - C @ x_pred[t]  # innovation
        S = _sym(C @ P_pred[t] @ C.T + R)  # innovation covariance
        K = np.linalg.solve(S, C @ P_pred[t]).T  # gain P C^T S^{-1}  (S, P symmetric)
        x_filt[t] = x_pred[t] + K @ e
        P_filt[t] = _sym(P_pred[t] - K @ C @ P_pred[t])

        _, logdet_S = np.linalg.slogdet(S)
        loglik += -0.5 * (m * _LOG_2PI + logdet_S + e @ np.linalg.solve(S, e))

    # Backward pass: RTS smoother.
    x_smooth = np.zeros((T, n))
    P_smooth = np.zeros((T, n, n))
    cross = np.zeros((max(T - 1, 0), n, n))
    x_smooth[T - 1] = x_filt[T - 1]
    P_smooth[T - 1] = P_filt[T - 1]
    for t in range(T - 2, -1, -1):
        # J_t = P^f_t A^T (P^p_{t+1})^{-1}
        J = np.linalg.solve(P_pred[t + 1], A @ P_filt[t]).T
        x_smooth[t] = x_filt[t] + J @ (x_smooth[t + 1] - x_pred[t + 1])
        P_smooth[t] = _sym(P_filt[t] + J @ (P_smooth[t + 1] - P_pred[t + 1]) @ J.T)
        # Cov(x_{t+1}, x_t | y_{1:T}) = P^s_{t+1} J_t^T
        cross[t] = P_smooth[t + 1] @ J.T

    return {"mean": x_smooth, "cov": P_smooth, "cross": cross, "loglik": float(loglik)}


def e_step(y, A, C, Q, R, mu0, P0):
    """Smooth every trajectory of ``y`` (B, T, m) and sum the EM sufficient statistics.

    Returns a dict with
      ``S11`` = sum_b sum_{t=1}^{T-1} E[x_{t+1} x_{t+1}^T]
      ``S10`` = sum_b sum_{t=1}^{T-1} E[x_{t+1} x_t^T]
      ``S00`` = sum_b sum_{t=1}^{T-1} E[x_t x_t^T]
      ``Sxx`` = sum_b sum_{t=1}^{T} E[x_t x_t^T]
      ``Syx`` = sum_b sum_{t=1}^{T} y_t E[x_t]^T
      ``Syy`` = sum_b sum_{t=1}^{T} y_t y_t^T
      ``N_dyn`` = B (T-1), ``N_obs`` = B T, ``loglik`` = sum_b log p(y_b).
    """
    y = np.asarray(y, dtype=np.float64)
    B, T, m = y.shape
    n = np.asarray(A).shape[0]
    S11 = np.zeros((n, n))
    S10 = np.zeros((n, n))
    S00 = np.zeros((n, n))
    Sxx = np.zeros((n, n))
    Syx = np.zeros((m, n))
    Syy = np.zeros((m, m))
    loglik = 0.0
    for b in range(B):
        sm = kalman_smoother(y[b], A, C, Q, R, mu0, P0)
        mean, cov, cross = sm["mean"], sm["cov"], sm["cross"]
        loglik += sm["loglik"]
        # E[x_t x_t^T] = P^s_t + m_t m_t^T
        Exx = cov + np.einsum("ti,tj->tij", mean, mean)
        # E[x_{t+1} x_t^T] = Cov(x_{t+1}, x_t) + m_{t+1} m_t^T
        Ex1x0 = cross + np.einsum("ti,tj->tij", mean[1:], mean[:-1])
        S11 += Exx[1:].sum(axis=0)
        S00 += Exx[:-1].sum(axis=0)
        S10 += Ex1x0.sum(axis=0)
        Sxx += Exx.sum(axis=0)
        Syx += y[b].T @ mean
        Syy += y[b].T @ y[b]
    return {
        "S11": S11,
        "S10": S10,
        "S00": S00,
        "Sxx": Sxx,
        "Syx": Syx,
        "Syy": Syy,
        "N_dyn": B * (T - 1),
        "N_obs": B * T,
        "loglik": float(loglik),
    }


def m_step(stats):
    """Closed-form maximisers (A, C, Q, R) of the expected complete-data log-likelihood."""
    S11, S10, S00 = stats["S11"], stats["S10"], stats["S00"]
    Sxx, Syx, Syy = stats["Sxx"], stats["Syx"], stats["Syy"]
    # A = S10 S00^{-1}   (S00 symmetric)
    A_new = np.linalg.solve(S00, S10.T).T
    Q_new = _sym((S11 - A_new @ S10.T) / stats["N_dyn"])
    # C = Syx Sxx^{-1}   (Sxx symmetric)
    C_new = np.linalg.solve(Sxx, Syx.T).T
    R_new = _sym((Syy - C_new @ Syx.T) / stats["N_obs"])
    return A_new, C_new, Q_new, R_new


def expected_complete_loglik(stats, A, C, Q, R):
    """E[log p(x, y | A, C, Q, R)] from the E-step moments, dropping the x_1 term and constants.

    The x_1 term depends only on mu0, P0 (known), so it does not affect the M-step.
    """
    S11, S10, S00 = stats["S11"], stats["S10"], stats["S00"]
    Sxx, Syx, Syy = stats["Sxx"], stats["Syx"], stats["Syy"]
    dyn = S11 - A @ S10.T - S10 @ A.T + A @ S00 @ A.T  # sum E[(x_{t+1}-A x_t)(.)^T]
    obs = Syy - C @ Syx.T - Syx @ C.T + C @ Sxx @ C.T  # sum E[(y_t - C x_t)(.)^T]
    _, logdet_Q = np.linalg.slogdet(Q)
    _, logdet_R = np.linalg.slogdet(R)
    return float(
        -0.5 * stats["N_dyn"] * logdet_Q
        - 0.5 * np.trace(np.linalg.solve(Q, dyn))
        - 0.5 * stats["N_obs"] * logdet_R
        - 0.5 * np.trace(np.linalg.solve(R, obs))
    )


def em_step(y, A, C, Q, R, mu0, P0):
    """One EM iteration on ``y`` (B, T, m).

    Returns (A_new, C_new, Q_new, R_new, total log-likelihood at the old parameters).
    """
    stats = e_step(y, A, C, Q, R, mu0, P0)
    A_new, C_new, Q_new, R_new = m_step(stats)
    return A_new, C_new, Q_new, R_new, stats["loglik"]


def kalman_em(y, A, C, Q, R, mu0, P0, iterations):
    """Run ``iterations`` EM steps.

    Returns a list of dicts, one per iteration k = 1..iterations, with keys ``A, C, Q, R``
    (parameters after the k-th M-step) and ``loglik`` (sum_b log p(y_b) at the parameters
    before the k-th M-step).
    """
    history = []
    for _ in range(iterations):
        A, C, Q, R, loglik = em_step(y, A, C, Q, R, mu0, P0)
        history.append({"A": A, "C": C, "Q": Q, "R": R, "loglik": loglik})
    return history
