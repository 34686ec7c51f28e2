r"""A simulated positioning stage with friction its user's physics lacks: a test of ``fit_hybrid``.

A carriage of mass m on a guide, driven by a force u and held on a position reference by a PID
controller that reads a noisy position sensor. The guide's friction is Stribeck + Coulomb +
viscous with a smooth sign,

.. math::

    F_f(v) = \bigl(F_c + (F_s - F_c)\,e^{-(v/v_s)^2}\bigr)\tanh(v/ε) + b\,v,

and a constant force offset c (cable drag, a slight slope):

.. math::

    \dot p = v, \qquad m\,\dot v = u - F_f(v) - c, \qquad y = p + e.

:class:`StribeckMass` is that plant as a ceemx system (the truth); :class:`ViscousMass` is the
physics its user writes — mass, viscous friction and the offset, no Coulomb or Stribeck term.
:func:`friction_positioning` simulates the closed loop and returns what a user would have: a
training record and a test record (:class:`FrictionRecords`), each the force the plant saw (u,
N) and the measured position (y, m), sampled at 1 ms; the two follow different references (a
multisine for training, filtered random noise for the test), so a model scored on the test
record runs through motions it was not trained on. A free run of a model on a record is
driven by the recorded force (open loop, as on a real positioning benchmark): a model whose
friction is wrong drifts.

The simulation runs on the host in plain Python floats (the loop is sequential: each force
depends on the last measurement) with the plant integrated exactly as :class:`StribeckMass`
integrates it (RK4, two substeps per sample, the force held over the sample), so the truth model
reproduces the noise-free plant to rounding. Random numbers come from one
``numpy.random.Generator`` seeded by ``seed``: the records are a deterministic function of the
arguments.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

from ceemx.data.trajectories import Trajectories
from ceemx.models.constraints import param
from ceemx.models.system import AbstractContinuousSystem

__all__ = [
    "TRUE_PARAMETERS",
    "FrictionRecords",
    "StribeckMass",
    "ViscousMass",
    "friction_positioning",
    "stribeck_friction",
]

#: The plant's parameters (SI: kg, N·s/m, N, N, N, m/s, m/s).
TRUE_PARAMETERS: dict[str, float] = {
    "mass": 2.0,
    "viscous": 10.0,
    "offset": 0.5,
    "coulomb": 4.0,
    "static": 6.0,
    "stribeck_velocity": 0.02,
    "smoothing": 0.002,
}

DT = 1e-3  # s
SUBSTEPS = 2  # RK4 steps per sample, as both models integrate
OBS_NOISE = 1e-5  # m: the position sensor's noise (10 µm)
FORCE_NOISE = 0.02  # N: a white force disturbance per sample (the process noise)
N_INIT = 20  # measured outputs that set a free run's initial state

# the controller: PID on the measured position, bandwidth ≈ 8 Hz for the 2 kg carriage
_KP, _KI, _KD = 5000.0, 50000.0, 140.0  # N/m, N/(m·s), N·s/m
_DERIVATIVE_CUTOFF = 2 * math.pi * 50.0  # rad/s: the first-order filter on the derivative
_WARMUP = 1000  # samples simulated (the reference faded in) and discarded


def stribeck_friction(v, coulomb, static, stribeck_velocity, smoothing, viscous, xp: Any = jnp):
    """F_f(v) = (F_c + (F_s − F_c) exp(−(v/v_s)²)) tanh(v/ε) + b v (``xp``: ``jnp`` or ``math``)."""
    level = coulomb + (static - coulomb) * xp.exp(-((v / stribeck_velocity) ** 2))
    return level * xp.tanh(v / smoothing) + viscous * v


class _AbstractCarriage(AbstractContinuousSystem):
    """A carriage on a guide: m v̇ = u − friction(v) − c, ṗ = v, y = p.

    State (position [m], velocity [m/s]), input the force [N], output the position [m]; the
    subclasses give the friction.
    """

    mass: Float[ArrayLike, ""] = param(positive=True)
    viscous: Float[ArrayLike, ""] = param(positive=True)
    offset: Float[ArrayLike, ""] = param(default=0.0)

    @property
    def state_dim(self) -> int:
        """The state dimension n = 2: position and velocity."""
        return 2

    @property
    def obs_dim(self) -> int:
        """The output dimension m = 1: the measured position."""
        return 1

    @property
    def control_dim(self) -> int:
        """The number of inputs p = 1: the force."""
        return 1

    def friction(self, v: Float[Array, ""]) -> Float[ArrayLike, ""]:
        """The guide's friction force at velocity v [N]."""
        raise NotImplementedError

    def vector_field(
        self, x: Float[Array, " 2"], u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " 2"]:
        """(v, (u − friction(v) − c)/m)."""
        return jnp.stack([x[1], (u[0] - self.friction(x[1]) - self.offset) / self.mass])

    def observe(
        self, x: Float[Array, " 2"], u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " 1"]:
        """The position."""
        return x[:1]

    def linear_observation(self, u, t):
        """``(C, d)`` with y = C x + d: the position is measured."""
        dtype = jnp.result_type(self.mass)
        return jnp.array([[1.0, 0.0]], dtype=dtype), jnp.zeros((1,), dtype=dtype)

    def default_state_mean(self) -> Float[Array, " 2"]:
        """A typical state (at rest at the origin)."""
        return jnp.zeros((2,), dtype=jnp.result_type(self.mass))


class ViscousMass(_AbstractCarriage):
    """The user's physics: m v̇ = u − b v − c, ṗ = v, y = p (no Coulomb or Stribeck friction).

    State (position [m], velocity [m/s]); input the force [N]; output the position [m].

    Attributes:
        mass: m [kg], positive.
        viscous: b [N·s/m], positive.
        offset: c [N], a constant force.
    """

    def friction(self, v: Float[Array, ""]) -> Float[ArrayLike, ""]:
        """The viscous friction b v."""
        return self.viscous * v

    @classmethod
    def guess(cls, **kwargs: Any) -> ViscousMass:
        """A plausible guess, not the truth: m = 1.5 kg, b = 5 N·s/m, c = 0.

        The sensor's noise is known (10 µm); the process noise is set at the same scale, as the
        gray-box models of the real datasets set theirs. ``kwargs`` override any field.
        """
        options: dict[str, Any] = dict(dt=DT, substeps=SUBSTEPS)
        options.update(process_noise=OBS_NOISE, obs_noise=OBS_NOISE)
        params = {"mass": 1.5, "viscous": 5.0, "offset": 0.0}
        return cls(**{**params, **options, **kwargs})


class StribeckMass(_AbstractCarriage):
    """The plant: m v̇ = u − F_f(v) − c, ṗ = v, y = p (module notes; F_f: :func:`stribeck_friction`).

    Attributes:
        mass: m [kg], positive.
        viscous: b [N·s/m], positive.
        offset: c [N].
        coulomb: F_c [N], fixed.
        static: F_s [N], fixed.
        stribeck_velocity: v_s [m/s], fixed.
        smoothing: ε [m/s] of the smooth sign, fixed.
    """

    coulomb: Float[ArrayLike, ""] = param(fixed=True, default=0.0)
    static: Float[ArrayLike, ""] = param(fixed=True, default=0.0)
    stribeck_velocity: Float[ArrayLike, ""] = param(fixed=True, default=1.0)
    smoothing: Float[ArrayLike, ""] = param(fixed=True, default=1e-3)

    def friction(self, v: Float[Array, ""]) -> Float[ArrayLike, ""]:
        """F_f(v), :func:`stribeck_friction`."""
        return stribeck_friction(
            v, self.coulomb, self.static, self.stribeck_velocity, self.smoothing, self.viscous
        )

    @classmethod
    def truth(cls, **kwargs: Any) -> StribeckMass:
        """The plant at :data:`TRUE_PARAMETERS`, its noise as simulated (``kwargs`` override)."""
        m = TRUE_PARAMETERS["mass"]
        velocity_noise = FORCE_NOISE * DT / m
        options: dict[str, Any] = dict(dt=DT, substeps=SUBSTEPS, obs_noise=OBS_NOISE)
        options["process_noise"] = (velocity_noise * 1e-3, velocity_noise)
        return cls(**{**TRUE_PARAMETERS, **options, **kwargs})


@dataclass(frozen=True)
class FrictionRecords:
    """What :func:`friction_positioning` returns.

    Attributes:
        train: the training record: u the force [N], y the measured position [m].
        test: the test record (another reference signal).
        truth: the plant as a ceemx system (:meth:`StribeckMass.truth`).
        guess: the user's physics at its guess (:meth:`ViscousMass.guess`).
        n_init: measured outputs that set a free run's initial state.
        reference: the references tracked, ``{"train": (T,), "test": (T,)}`` [m].
        states: the plant's true states, ``{"train": (T, 2), "test": (T, 2)}``.
    """

    train: Trajectories
    test: Trajectories
    truth: StribeckMass
    guess: ViscousMass
    n_init: int
    reference: dict[str, np.ndarray]
    states: dict[str, np.ndarray]


def _multisine(rng: np.random.Generator, T: int) -> np.ndarray:
    """A random-phase multisine, 0.05–2 Hz in 0.05 Hz steps, amplitudes ∝ 1/f, std 5 cm."""
    t = np.arange(T) * DT
    f = 0.05 * np.arange(1, 41)
    phase = rng.uniform(0.0, 2 * np.pi, f.size)
    r = (np.sin(2 * np.pi * f[:, None] * t[None, :] + phase[:, None]) / f[:, None]).sum(axis=0)
    return 0.05 * r / r.std()


def _filtered_noise(rng: np.random.Generator, T: int) -> np.ndarray:
    """White noise through a critically damped 0.7 Hz second-order filter, std 2.5 cm.

    A reference that wanders with no fixed frequencies (the training record's is a multisine),
    at speeds within the training record's (up to ≈ 0.3 m/s).
    """
    w = 2 * np.pi * 0.7
    drive = rng.standard_normal(T)
    r, dr = np.zeros(T), 0.0
    for i in range(1, T):  # r̈ = w²(drive − r) − 2w ṙ, semi-implicit Euler at dt
        dr += DT * (w * w * (drive[i - 1] - r[i - 1]) - 2 * w * dr)
        r[i] = r[i - 1] + DT * dr
    return 0.025 * r / r.std()


def _closed_loop(
    reference: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The PID loop on the plant: (force u, measured position y, true states), each (T, ·).

    At sample t the sensor reads y_t = p_t + e_t, the controller sets u_t from it, and the plant
    integrates over the sample with u_t held, plus a white force disturbance.
    """
    p = TRUE_PARAMETERS
    m, c = p["mass"], p["offset"]
    args = (p["coulomb"], p["static"], p["stribeck_velocity"], p["smoothing"], p["viscous"])

    def accel(v: float, force: float) -> float:
        return (force - stribeck_friction(v, *args, xp=math) - c) / m

    T = reference.size
    e = OBS_NOISE * rng.standard_normal(T)
    w = FORCE_NOISE * DT / m * rng.standard_normal(T)
    u, y, x = np.empty(T), np.empty(T), np.empty((T, 2))
    pos = vel = integral = derivative = 0.0
    last = 0.0
    h = DT / SUBSTEPS
    alpha = DT * _DERIVATIVE_CUTOFF / (1 + DT * _DERIVATIVE_CUTOFF)
    for t in range(T):
        x[t] = pos, vel
        meas = pos + e[t]
        error = reference[t] - meas
        integral += error * DT
        derivative += alpha * ((meas - last) / DT - derivative) if t else 0.0
        last = meas
        force = _KP * error + _KI * integral - _KD * derivative
        u[t], y[t] = force, meas
        for _ in range(SUBSTEPS):  # RK4, as AbstractContinuousSystem.dynamics
            k1p, k1v = vel, accel(vel, force)
            k2p, k2v = vel + 0.5 * h * k1v, accel(vel + 0.5 * h * k1v, force)
            k3p, k3v = vel + 0.5 * h * k2v, accel(vel + 0.5 * h * k2v, force)
            k4p, k4v = vel + h * k3v, accel(vel + h * k3v, force)
            pos += h / 6 * (k1p + 2 * k2p + 2 * k3p + k4p)
            vel += h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        vel += w[t]
    return u, y, x


def _record(reference: np.ndarray, rng: np.random.Generator):
    """One record after a warm-up with the reference faded in: (Trajectories, states)."""
    fade = np.concatenate([np.sin(0.5 * np.pi * np.arange(_WARMUP) / _WARMUP) ** 2, [1.0]])
    lead = np.concatenate([reference[0] * fade[:-1], reference])
    u, y, x = _closed_loop(lead, rng)
    u, y, x = u[_WARMUP:], y[_WARMUP:], x[_WARMUP:]
    data = Trajectories.from_arrays(
        y[:, None], u[:, None], dt=DT, output_names="position", output_units="m",
        input_names="force", input_units="N",
    )  # fmt: skip
    return data, x


def friction_positioning(
    seed: int = 0, n_train: int = 20_000, n_test: int = 5_000
) -> FrictionRecords:
    """The positioning stage's training and test records (module notes).

    Args:
        seed: seeds every random draw (references, noise).
        n_train: samples of the training record (multisine reference), at 1 ms.
        n_test: samples of the test record (filtered random noise).

    Returns:
        :class:`FrictionRecords`: the records, the true plant and the user's physics guess.
    """
    if n_train < 4 * N_INIT or n_test < 2 * N_INIT:
        raise ValueError(f"records too short: n_train ≥ {4 * N_INIT}, n_test ≥ {2 * N_INIT}.")
    rng = np.random.default_rng(seed)
    r_train, r_test = _multisine(rng, n_train), _filtered_noise(rng, n_test)
    train, x_train = _record(r_train, rng)
    test, x_test = _record(r_test, rng)
    return FrictionRecords(
        train=train, test=test, truth=StribeckMass.truth(), guess=ViscousMass.guess(),
        n_init=N_INIT, reference={"train": r_train, "test": r_test},
        states={"train": x_train, "test": x_test},
    )  # fmt: skip
