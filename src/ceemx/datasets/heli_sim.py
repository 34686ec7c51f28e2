"""A documented helicopter-like dataset: a rigid body whose forces depend on hidden wake states.

The Stanford helicopter dataset used in §4.2 of the paper cannot be downloaded here, so this module
generates a stand-in with the same interface and the same difficulty in kind: the measured state
and the controls at time t do not determine the accelerations at time t, because the forces also
depend on unobserved induced-flow (wake) states with time constants from 0.15 s to several seconds.
The design is fixed and written down in ``docs/helicopter_benchmark.md``; it was fixed before any
model was scored on it.

Everything here is host-side NumPy in float64; the random numbers come from one
``numpy.random.Generator`` seeded by ``seed``, so the data are a deterministic function of
``(seed, n_train, n_valid, n_test, steps, dt)`` (bit for bit with the same NumPy build).

Model (mass-normalised, body axes x forward, y right, z down; full equations and the reasoning in
``docs/helicopter_benchmark.md``):

* State: body velocity ``v = (u, v, w)`` [m/s], body rates ``ω = (p, q, r)`` [rad/s], gravity in
  body axes ``g_b`` (attitude, hidden), and five hidden wake states ``z``: ``z1`` uniform induced
  inflow [m/s] (τ 0.15–0.25 s), ``z2, z3`` inflow gradients / wake skew [m/s] (τ 0.7 s), ``z4``
  vortex-ring / recirculation intensity (τ 0.8 s rising, 4 s decaying), ``z5`` wake swirl
  (τ 5 s in hover, shorter with speed).
* Thrust ``T = (18 + 20 col)(1 + 0.003 μ²)(1 − 0.5 z4 − 0.25 z5) − 2.5 φ − 0.3 (z2² + z3²)`` with
  ``φ = z1 − w`` the flow through the disk; dynamic Glauert inflow
  ``ż1 = (9 (T/g)/√(μ² + φ² + 1) − z1)/τ1``; quasi-static flapping ``a1``, ``b1`` from cyclic,
  blow-back, rates and ``z2``, ``z3``.
* Specific force ``F`` (thrust tilt, quadratic drag, tail rotor, fin in the swirl, download in the
  wash) and moments (hub stiffness, damping, wake asymmetry, torque reaction, tail rotor);
  ``ω̇ = I⁻¹(τ − ω × Iω)``, ``v̇ = F + g_b − ω × v``, ``ġ_b = −ω × g_b``.
* A pilot (attitude/rate/climb/yaw-rate feedback with a random schedule of manoeuvres: holds,
  flips, rolls, pirouettes, tic-tocs, collective pumps) plus band-limited random excitation sets
  the four controls, saturated by ``tanh``; a light band-limited gust moves the air.

Recorded per step (sampled every ``dt``, controls held over the step): ``u_t`` = (col, lon, lat,
ped, measured u, v, w, p, q, r) and ``y_t`` = (X, Y, Z, ṗ, q̇, ṙ) at time t, the accelerometer's
specific force and the angular accelerations, both with sensor noise.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ceemx.datasets.helicopter import HelicopterData, normalise_splits

__all__ = [
    "CONTROL_NAMES",
    "HIDDEN_NAMES",
    "INPUT_NAMES",
    "OUTPUT_NAMES",
    "helicopter_like",
    "simulate_flights",
]

G = 9.81
INERTIA = np.array([1.0, 1.8, 1.5])
CONTROL_NAMES = ("col", "lon", "lat", "ped")
INPUT_NAMES = (*CONTROL_NAMES, "u", "v", "w", "p", "q", "r")
OUTPUT_NAMES = ("ax", "ay", "az", "p_dot", "q_dot", "r_dot")
HIDDEN_NAMES = ("inflow", "inflow_lon", "inflow_lat", "vortex_ring", "swirl")

_SUBSTEPS = 4  # RK4 steps per sample (h = dt / 4 = 5 ms)
_WARMUP_S = 5.0  # simulated and discarded at the start of each flight
_CHUNKS_PER_FLIGHT = 4
_U_NOISE = np.array([0.05, 0.05, 0.05, 0.02, 0.02, 0.02])  # velocity [m/s], rate [rad/s] sensors
_Y_NOISE = np.array([0.15, 0.15, 0.15, 0.1, 0.1, 0.1])  # accelerometer, angular acceleration
_GUST_STD = 0.3  # m/s, band-limited (0.3 Hz)


def _derivatives(
    s: np.ndarray, c: np.ndarray, gust: np.ndarray
) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Time derivative of the state and the recorded outputs.

    Args:
        s: (14, F) state: v (3), ω (3), g_b (3), z (5).
        c: (4, F) saturated controls.
        gust: (3, F) air velocity in body axes.


    Returns:
        ``(ds, y)``: the (14, F) derivative and the six (F,) outputs (specific force X, Y, Z and
        angular accelerations ṗ, q̇, ṙ).
    """
    u, v, w = s[0] - gust[0], s[1] - gust[1], s[2] - gust[2]
    p, q, r = s[3], s[4], s[5]
    gx, gy, gz = s[6], s[7], s[8]
    z1, z2, z3, z4, z5 = s[9], s[10], s[11], s[12], s[13]
    col, lon, lat, ped = c[0], c[1], c[2], c[3]

    mu2 = u * u + v * v
    speed = np.sqrt(mu2 + w * w)
    vc = -w  # climb rate
    flow = z1 + vc  # total flow through the disk
    T = (18.0 + 20.0 * col) * (1.0 + 0.003 * mu2) * (1.0 - 0.5 * z4 - 0.25 * z5) - 2.5 * flow
    T = T - 0.3 * (z2 * z2 + z3 * z3)
    a1 = 0.2 * lon - 0.02 * u - 0.05 * q + 0.08 * z2
    b1 = 0.2 * lat - 0.02 * v - 0.05 * p + 0.08 * z3
    sa, sb = np.sin(a1), np.sin(b1)

    # Tail rotor: thrust weakened in the main rotor's recirculating wake; fin in the wake swirl.
    n_tr = 12.0 * ped * (1.0 - 0.4 * np.tanh(z4))
    X = T * sa - 0.03 * speed * u
    Y = T * sb - 0.06 * speed * v - 0.25 * n_tr - 2.0 * z5
    Z = -T * np.cos(a1) * np.cos(b1) - 0.08 * speed * w + 0.1 * z1 * np.abs(z1)

    torque = 0.6 + 0.05 * T * flow  # main rotor torque (profile + induced power)
    L = 25.0 * b1 + 0.3 * T * sb - 2.0 * p + 0.4 * z1 * z3 + 3.0 * z4 * z3
    M = -45.0 * a1 - 0.3 * T * sa - 3.0 * q + 3.0 * z4 * z2 + 0.02 * u * (0.5 * z1 - z2)
    N = n_tr - torque - 1.5 * r - 3.0 * z5 + 0.3 * z5 * u / (1.0 + np.abs(u))
    Ix, Iy, Iz = INERTIA
    p_dot = (L - (Iz - Iy) * q * r) / Ix
    q_dot = (M - (Ix - Iz) * r * p) / Iy
    r_dot = (N - (Iy - Ix) * p * q) / Iz

    # Wake states: nonlinear targets, state-dependent and asymmetric time constants.
    denom = np.sqrt(mu2 + flow * flow + 1.0)
    tau1 = 0.15 + 0.1 * np.exp(-mu2 / 25.0)
    dz1 = (9.0 * (T / G) / denom - z1) / tau1
    dz2 = (z1 * u / denom + 0.3 * q - z2) / 0.7
    dz3 = (z1 * v / denom + 0.3 * p - z3) / 0.7
    vrs = np.exp(-((flow / 2.5) ** 2) - mu2 / 36.0) + 0.6 * np.tanh((p * p + q * q) / 4.0)
    target4 = np.minimum(vrs, 1.0)
    dz4 = (target4 - z4) / np.where(target4 > z4, 0.8, 4.0)
    target5 = np.tanh(0.12 * T * flow - 1.7) + 0.5 * np.tanh(r / 2.0)
    dz5 = (target5 - z5) * (1.0 + mu2 / 100.0) / 5.0

    ds = np.empty_like(s)
    ds[0] = X + gx - (q * s[2] - r * s[1])
    ds[1] = Y + gy - (r * s[0] - p * s[2])
    ds[2] = Z + gz - (p * s[1] - q * s[0])
    ds[3], ds[4], ds[5] = p_dot, q_dot, r_dot
    ds[6] = -(q * gz - r * gy)
    ds[7] = -(r * gx - p * gz)
    ds[8] = -(p * gy - q * gx)
    ds[9], ds[10], ds[11], ds[12], ds[13] = dz1, dz2, dz3, dz4, dz5
    return ds, (X, Y, Z, p_dot, q_dot, r_dot)


def _band_limited(
    rng: np.random.Generator, shape: tuple[int, int], dt: float, lo: float, hi: float
):
    """Unit-variance random signals (F, n), low-passed (2nd-order Butterworth) at a random cutoff.

    The cutoff of each row is drawn log-uniformly from [lo, hi] Hz.
    """
    from scipy import signal  # imported on use: scipy.signal alone takes 1-2 s to import

    F, n = shape
    white = rng.standard_normal((F, n + 200))
    cut = np.exp(rng.uniform(math.log(lo), math.log(hi), F))
    out = np.empty((F, n))
    for i in range(F):
        sos = np.asarray(signal.butter(2, cut[i], fs=1.0 / dt, output="sos"))
        x = np.asarray(signal.sosfilt(sos, white[i]))[200:]
        out[i] = x / (x.std() + 1e-12)
    return out


def _schedule(rng: np.random.Generator, F: int, n: int, dt: float) -> np.ndarray:
    """Piecewise-constant manoeuvre references (9, F, n), then smoothed (τ = 0.3 s).

    Rows: rate-mode weight for roll and pitch, roll and pitch attitude references [rad], roll,
    pitch and yaw rate references [rad/s], climb rate reference [m/s], extra collective.
    """
    ref = np.zeros((9, F, n))
    t_axis = np.arange(n) * dt
    for f in range(F):
        t = 0
        while t < n:
            length = int(rng.uniform(1.0, 4.0) / dt)
            sl = slice(t, min(t + length, n))
            mode = rng.choice(6, p=[0.4, 0.15, 0.1, 0.1, 0.1, 0.15])
            ref[2, f, sl] = rng.normal(0.0, 0.4)  # roll attitude
            ref[3, f, sl] = rng.normal(0.0, 0.3)  # pitch attitude (forward speed)
            ref[6, f, sl] = rng.normal(0.0, 0.5)  # yaw rate
            ref[7, f, sl] = rng.normal(0.0, 2.0)  # climb rate
            sign = rng.choice([-1.0, 1.0])
            if mode == 1:  # flip (pitch loop)
                ref[1, f, sl], ref[5, f, sl] = 1.0, sign * rng.uniform(3.0, 5.0)
            elif mode == 2:  # roll
                ref[0, f, sl], ref[4, f, sl] = 1.0, sign * rng.uniform(3.0, 5.0)
            elif mode == 3:  # pirouette
                ref[6, f, sl] = sign * rng.uniform(3.0, 6.0)
            elif mode == 4:  # tic-toc: pitch rate reversing at ~0.5-1 Hz
                freq = rng.uniform(0.5, 1.0)
                ref[1, f, sl] = 1.0
                ref[5, f, sl] = 3.0 * np.sign(np.sin(2 * np.pi * freq * t_axis[sl]))
            elif mode == 5:  # collective pump
                freq = rng.uniform(0.3, 1.5)
                ref[8, f, sl] = rng.uniform(0.3, 0.7) * np.sin(2 * np.pi * freq * t_axis[sl])
            t += length
    from scipy import signal

    a = math.exp(-dt / 0.3)
    return np.asarray(signal.lfilter([1.0 - a], [1.0, -a], ref, axis=-1))


def _pilot(s: np.ndarray, ref: np.ndarray, exc: np.ndarray) -> np.ndarray:
    """Controls (4, F) from the state, the references (9, F) and the excitation (4, F)."""
    p, q, r, w = s[3], s[4], s[5], s[2]
    gx, gy, gz = s[6], s[7], s[8]
    theta = np.arcsin(np.clip(-gx / G, -1.0, 1.0))
    phi = np.arctan2(gy, gz)
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    p_cmd = ref[0] * ref[4] + (1.0 - ref[0]) * 2.5 * wrap(ref[2] - phi)
    q_cmd = ref[1] * ref[5] + (1.0 - ref[1]) * 2.5 * wrap(ref[3] - theta)
    cmd = np.stack(
        [
            0.6 * (gz / G) - 0.6 + 0.1 * (w + ref[7]) + ref[8] + 0.15 * exc[0],
            -0.4 * (q_cmd - q) + 0.12 * exc[1],
            0.4 * (p_cmd - p) + 0.12 * exc[2],
            0.17 + 0.25 * (ref[6] - r) + 0.1 * exc[3],
        ]
    )
    return np.tanh(cmd)


def simulate_flights(
    rng: np.random.Generator, n_flights: int, steps: int, dt: float = 0.02
) -> dict[str, np.ndarray]:
    """Simulate ``n_flights`` flights of ``steps`` recorded samples (after a 5 s warm-up).

    Args:
        rng: the source of randomness (initial states, schedules, excitation, gusts, noise).
        n_flights: number of independent flights, simulated together (vectorised).
        steps: recorded samples per flight.
        dt: sample period [s]; the integrator takes RK4 steps of ``dt / 4``.

    Returns:
        A dict of float64 arrays: ``u`` (F, steps, 10) and ``y`` (F, steps, 6) as recorded (with
        sensor noise), and the noise-free ``y_true`` (F, steps, 6), ``controls`` (F, steps, 4),
        ``velocity`` (F, steps, 6), ``hidden`` (F, steps, 5) wake states and ``gravity``
        (F, steps, 3).
    """
    F = n_flights
    warm = int(round(_WARMUP_S / dt))
    n = warm + steps
    exc = np.stack([_band_limited(rng, (F, n), dt, 0.3, 3.0) for _ in range(4)])
    ref = _schedule(rng, F, n, dt)
    gust = _GUST_STD * np.stack([_band_limited(rng, (F, n), dt, 0.1, 0.5) for _ in range(3)])

    s = np.zeros((14, F))
    s[0:3] = rng.normal(0.0, 1.0, (3, F))
    s[3:6] = rng.normal(0.0, 0.1, (3, F))
    tilt = rng.normal(0.0, 0.1, (2, F))
    s[6] = -G * np.sin(tilt[0])
    s[7] = G * np.sin(tilt[1]) * np.cos(tilt[0])
    s[8] = G * np.cos(tilt[1]) * np.cos(tilt[0])
    s[9] = 2.9 + rng.normal(0.0, 0.2, F)
    s[12] = 0.05
    s[13] = rng.uniform(0.3, 0.8, F)

    out_s = np.empty((steps, 14, F))
    out_c = np.empty((steps, 4, F))
    out_y = np.empty((steps, 6, F))
    h = dt / _SUBSTEPS
    for k in range(n):
        c = _pilot(s, ref[:, :, k], exc[:, :, k])
        g_k = gust[:, :, k]
        if k >= warm:
            i = k - warm
            out_s[i], out_c[i] = s, c
            out_y[i] = np.stack(_derivatives(s, c, g_k)[1])
        for _ in range(_SUBSTEPS):
            k1 = _derivatives(s, c, g_k)[0]
            k2 = _derivatives(s + (0.5 * h) * k1, c, g_k)[0]
            k3 = _derivatives(s + (0.5 * h) * k2, c, g_k)[0]
            k4 = _derivatives(s + h * k3, c, g_k)[0]
            s = s + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        s[6:9] *= G / np.sqrt((s[6:9] ** 2).sum(0))  # keep |g_b| = g exactly

    states = out_s.transpose(2, 0, 1)  # (F, steps, 14)
    controls = out_c.transpose(2, 0, 1)
    y_true = out_y.transpose(2, 0, 1)
    velocity = states[..., 0:6]
    u_meas = velocity + _U_NOISE * rng.standard_normal(velocity.shape)
    y_meas = y_true + _Y_NOISE * rng.standard_normal(y_true.shape)
    return {
        "u": np.concatenate([controls, u_meas], axis=-1),
        "y": y_meas,
        "y_true": y_true,
        "controls": controls,
        "velocity": velocity,
        "hidden": states[..., 9:14],
        "gravity": states[..., 6:9],
    }


def helicopter_like(
    seed: int = 0,
    *,
    n_train: int = 466,
    n_valid: int = 101,
    n_test: int = 100,
    steps: int = 500,
    dt: float = 0.02,
) -> HelicopterData:
    """The helicopter-like dataset: 10 s trajectories split as in the paper (466/101/100).

    Flights of ``4 * steps`` samples are simulated (:func:`simulate_flights`), cut into
    trajectories of ``steps`` samples, shuffled and split; ``u`` and ``y`` are normalised with the
    training split's per-channel mean and standard deviation.

    Args:
        seed: seeds everything; the same arguments give the same data on any machine.
        n_train: training trajectories.
        n_valid: validation trajectories.
        n_test: test trajectories.
        steps: samples per trajectory (the paper: 500 at 50 Hz).
        dt: sample period [s].

    Returns:
        A :class:`~ceemx.datasets.HelicopterData` with 10 inputs (col, lon, lat, ped, u, v, w,
        p, q, r) and 6 outputs (body-axis specific force and angular accelerations); names are
        ``"flight{f:04d}_chunk{c}"``.

    Raises:
        ValueError: for a non-positive size or fewer than 2 steps.

    Example:
        >>> data = helicopter_like(0, n_train=4, n_valid=2, n_test=2, steps=50)
        >>> data.train.y.shape, data.train.u.shape
        ((4, 50, 6), (4, 50, 10))
    """
    if min(n_train, n_valid, n_test) < 1 or steps < 2 or dt <= 0:
        raise ValueError(
            "`n_train`, `n_valid`, `n_test` must be >= 1, `steps` >= 2 and `dt` > 0; got "
            f"{n_train}, {n_valid}, {n_test}, {steps}, {dt}."
        )
    rng = np.random.default_rng(seed)
    total = n_train + n_valid + n_test
    n_flights = -(-total // _CHUNKS_PER_FLIGHT)
    sim = simulate_flights(rng, n_flights, _CHUNKS_PER_FLIGHT * steps, dt)
    u = sim["u"].reshape(n_flights * _CHUNKS_PER_FLIGHT, steps, -1)
    y = sim["y"].reshape(n_flights * _CHUNKS_PER_FLIGHT, steps, -1)
    names = [f"flight{f:04d}_chunk{c}" for f in range(n_flights) for c in range(_CHUNKS_PER_FLIGHT)]
    order = rng.permutation(len(names))[:total]
    parts = np.split(order, [n_train, n_train + n_valid])
    return normalise_splits(
        [(u[i], y[i], tuple(names[j] for j in i)) for i in parts],
        dt=dt,
        source=f"helicopter-like generator (seed {seed})",
    )


if __name__ == "__main__":  # pragma: no cover - timing
    t0 = time.perf_counter()
    d = helicopter_like(0)
    print(f"default dataset in {time.perf_counter() - t0:.2f} s; train y {d.train.y.shape}")
