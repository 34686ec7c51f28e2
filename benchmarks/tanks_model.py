"""The cascaded tanks' model: its structure one change at a time, further variants, and the
level sensor's jumps. Every choice is made on validation (fitted on the first 80 % of the
training record, scored by the official protocol on the held-out rest); the test record is scored
after. Data: ``CEEMX_DATA``.

    python benchmarks/tanks_model.py structure [VARIANT ...] [--test | --test-only]
    python benchmarks/tanks_model.py variants VARIANT [VARIANT ...] [--oe] [--test | --test-only]
    python benchmarks/tanks_model.py sensor [--fits] [--cv] [--others] [--refit]

``structure``: the tanks' physics model with one ingredient changed at a time
(:data:`TANK_VARIANTS`, default all: the lower tank's overflow, the process noise, the pump's
dead zone, exponents, sensor offset or overflow level fixed, a staged start), fitted by JointLM;
each with the range of the hidden upper-tank level over the free run; ``--test`` also fits the
whole training record and scores the test record.

``variants``: the library's ``CascadedTanks`` with one further change (:data:`MORE_VARIANTS`:
smaller process noise, outflow exponents up to 2, a laminar term beside the power law, learned
overflow-gate sharpness, an upper outflow hole above the floor, a pump saturation); ``--oe``
refines the CE fit by Levenberg–Marquardt on the free-run output error over the free parameters
and the initial state (``OE_ITERS`` iterations, default 60) and scores again.

``sensor``: every one-sample fall of the measured level by more than 0.3 V in both records (the
level cannot fall that fast, and nothing like it happens on the way up), and the share of the
physics model's squared test error carried by the samples around them (``BEFORE`` before,
``AFTER`` after each jump). ``--fits``: two models of a sensor with memory, a third state z on
the reading, y = softmin(x₂ + c + z, 10) — ``film`` (a wetting film that builds while the level
falls above a collapse level L and drains below it; ``film-drain`` with a learned slow drain) and
``relay`` (switched on above H, off below L) — started from the physics fit with z = 0, validation
then test. ``--cv``: the physics model and those variants by 4-fold blocked cross-validation on
the training record. ``--others``: the input delayed by 1 or 2 samples, and a Student-t
observation noise (ν = 2) of scale 0.02 or 0.1 V. ``--refit``: the experiment's hybrid against
the same hybrid refitted on the whole training record for the chosen epoch count and 1.25 times
it (test scores only; nothing is chosen by them).

Backs: ``docs/results.md`` (the tanks' structure, further variants, the tanks' sensor) and the
``CascadedTanks`` model.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import hand_tuned as fits  # noqa: E402  (the former hand-tuned procedure)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from hand_tuned import Plan, Settings  # noqa: E402

import ceemx  # noqa: E402
from ceemx import datasets  # noqa: E402
from ceemx.datasets import REGISTRY  # noqa: E402
from ceemx.identification.problem import trainable_mask  # noqa: E402
from ceemx.models.constraints import param  # noqa: E402
from ceemx.systems.gray_box import (  # noqa: E402
    CascadedTanks,
    _AbstractSISO,
    smooth_power,
    soft_min,
)

# ``structure``: the tanks' structure one ingredient at a time.


class _Tanks(_AbstractSISO):
    """``CascadedTanks`` with its two new ingredients switchable (``CascadedTanks`` = both on)."""

    k1: jax.Array = param(positive=True)
    k2: jax.Array = param(positive=True)
    k3: jax.Array = param(positive=True)
    k4: jax.Array = param(positive=True)
    h: jax.Array = param(positive=True)
    phi: jax.Array = param(lower=0.0, upper=1.0)
    h2: jax.Array = param(positive=True)
    offset: jax.Array = param()
    u0: jax.Array = param()
    a1: jax.Array = param(lower=0.1, upper=1.0)
    a2: jax.Array = param(lower=0.1, upper=1.0)
    lower_overflow: bool = eqx.field(static=True, default=True)
    dead_zone: bool = eqx.field(static=True, default=True)

    @property
    def state_dim(self) -> int:
        return 2

    def vector_field(self, x, u, t):
        s1, s2 = smooth_power(x[0], self.a1), smooth_power(x[1], self.a2)
        inflow = self.k4 * (u[0] - self.u0)
        if self.dead_zone:
            inflow = self.k4 * jax.nn.softplus(5.0 * (u[0] - self.u0)) / 5.0
        gate = jax.nn.sigmoid(5.0 * (x[0] - self.h))
        into_lower = self.k2 * s1 + self.phi * inflow * gate
        if self.lower_overflow:
            into_lower = into_lower * (1 - jax.nn.sigmoid(10.0 * (x[1] + self.offset - self.h2)))
        return jnp.stack([inflow * (1 - gate) - self.k1 * s1, into_lower - self.k3 * s2])

    def observe(self, x, u, t):
        return soft_min(x[1:] + self.offset, 10.0, 10.0)


_PARAMS = ("k1", "k2", "k3", "k4", "h", "phi", "h2", "offset", "u0", "a1", "a2")

#: name → (process noise, switches of ``_Tanks``, fields kept at their default, fields fixed in a
#: first stage): "before" is the model and setting before the lower overflow and the pump's dead
#: zone; "chosen" the library's CascadedTanks with the experiment's setting (best validation).
_LINEAR = dict(dead_zone=False)
TANK_VARIANTS: dict[str, tuple[float, dict, tuple[str, ...], tuple[str, ...]]] = {
    "before": (0.05, dict(lower_overflow=False, dead_zone=False), ("h2",), ()),
    "lower-overflow": (0.05, _LINEAR, (), ()),
    "lower-overflow-torricelli": (0.05, _LINEAR, ("a1", "a2"), ()),
    "lower-overflow-no-offset": (0.05, _LINEAR, ("offset",), ()),
    "lower-overflow-h10": (0.05, _LINEAR, ("h",), ()),
    "lower-overflow-0.02": (0.02, _LINEAR, (), ()),
    "lower-overflow-0.01": (0.01, _LINEAR, (), ()),
    "lower-overflow-0.005": (0.005, _LINEAR, (), ()),
    "lower-overflow-0.002": (0.002, _LINEAR, (), ()),
    "lower-overflow-torricelli-0.005": (0.005, _LINEAR, ("a1", "a2"), ()),
    "no-lower-overflow-0.005": (0.005, dict(lower_overflow=False, dead_zone=False), ("h2",), ()),
    "dead-zone-0.005": (0.005, {}, (), ()),
    "dead-zone-0.005-staged": (0.005, {}, (), ("a1", "a2")),
    "dead-zone-0.002": (0.002, {}, (), ()),
    "chosen": (0.001, {}, (), ()),
}


#: The cascaded tanks' registry entry (its hand-chosen settings: ``hand_tuned.HAND``).
TANKS = REGISTRY["cascaded_tanks"]


def _plan(ds) -> Plan:
    """The experiment's plan of the cascaded tanks on their records ``ds``."""
    return fits.make_plan(TANKS.name, Settings(), ds)


def _physics_guess():
    """The experiment's physical guess (its options and hand-chosen process noise)."""
    m = TANKS.model
    return m.factory(
        dtype=jnp.float64, **m.options, process_noise=fits.HAND[TANKS.name].process_noise
    )


def _tanks_guess(scale, switches):
    lib = TANKS.model.factory(dtype=jnp.float64, process_noise=scale)
    guess = _Tanks(
        **{k: getattr(lib, k) for k in _PARAMS},
        **switches,
        dt=lib.dt,
        substeps=lib.substeps,
        process_noise=lib.process_noise,
        obs_noise=lib.obs_noise,
    )
    if switches == {}:  # this model is the library's
        x, u = jnp.array([9.0, 9.9]), jnp.array([3.0])
        assert jnp.allclose(guess.vector_field(x, u, 0), lib.vector_field(x, u, 0), rtol=1e-12)
    return guess


def structure(names: list[str], test: bool, validation: bool = True) -> None:
    """``structure``: validation (fit part → held-out tail) and, with ``test``, test (whole record
    → test record) of each variant of :data:`TANK_VARIANTS`."""
    ds = datasets.cascaded_tanks()
    fit_data, val = fits.split(_plan(ds))
    runs = [("validation", fit_data, val)] * validation
    runs += [("test", ds.train, ds.tests["test"])] * test

    def fit(guess, data, fixed):
        free = eqx.tree_at(
            lambda m: [getattr(m, n) for n in fixed], trainable_mask(guess), [False] * len(fixed)
        )
        return ceemx.fit(guess, data, solver=ceemx.JointLM(), max_epochs=200, trainable=free)

    for name in names or list(TANK_VARIANTS):
        scale, switches, fixed, staged = TANK_VARIANTS[name]
        guess = _tanks_guess(scale, switches)
        for part, data, record in runs:
            t0 = time.perf_counter()
            start = fit(guess, data, (*fixed, *staged)).system if staged else guess
            system = fit(start, data, fixed).system
            s = ceemx.benchmark_score(system, record, ds.n_init)
            params = {k: round(float(getattr(system, k)), 4) for k in _PARAMS}
            print(
                f"{name} {part}: {float(s.rmse[0, 0]):.4f} V, hidden level in "
                f"[{float(s.x_sim[..., 0].min()):.3g}, {float(s.x_sim[..., 0].max()):.3g}] V, "
                f"fit {time.perf_counter() - t0:.0f} s; {params}",
                flush=True,
            )


# ``variants``: further variants of the library's model, and the output-error refinement.

A_HI = 2.0  # exponent upper bound of the wide class


def _make(a_hi: float):
    class T(_AbstractSISO):
        k1: jax.Array = param(positive=True)
        k2: jax.Array = param(positive=True)
        k3: jax.Array = param(positive=True)
        k4: jax.Array = param(positive=True)
        h: jax.Array = param(positive=True)
        phi: jax.Array = param(lower=0.0, upper=1.0)
        h2: jax.Array = param(positive=True)
        offset: jax.Array = param()
        u0: jax.Array = param()
        a1: jax.Array = param(lower=0.1, upper=a_hi)
        a2: jax.Array = param(lower=0.1, upper=a_hi)
        # extras (frozen unless the variant frees them)
        kl1: jax.Array = param(positive=True, default=1e-3)  # laminar part, upper outflow
        kl2: jax.Array = param(positive=True, default=1e-3)  # laminar part, lower outflow
        bo: jax.Array = param(positive=True, default=5.0)  # upper overflow gate sharpness
        bl: jax.Array = param(positive=True, default=10.0)  # lower rim gate sharpness
        d1: jax.Array = param(default=0.0)  # upper outflow hole level (outflow ∝ (x1-d1)^a)
        usat: jax.Array = param(positive=True, default=50.0)  # pump saturation (flow units u)
        mixed: bool = eqx.field(static=True, default=False)
        hole: bool = eqx.field(static=True, default=False)
        pumpsat: bool = eqx.field(static=True, default=False)

        @property
        def state_dim(self) -> int:
            return 2

        def vector_field(self, x, u, t):
            x1 = x[0] - self.d1 if self.hole else x[0]
            if self.hole:  # no outflow below the hole: smooth ramp
                x1 = jax.nn.softplus(20.0 * x1) / 20.0
            s1, s2 = smooth_power(x1, self.a1), smooth_power(x[1], self.a2)
            pu = jax.nn.softplus(5.0 * (u[0] - self.u0)) / 5.0
            if self.pumpsat:
                pu = soft_min(pu, self.usat, 5.0)
            inflow = self.k4 * pu
            gate = jax.nn.sigmoid(self.bo * (x[0] - self.h))
            out1 = self.k1 * s1
            to2 = self.k2 * s1
            out2 = self.k3 * s2
            if self.mixed:
                out1 = out1 + self.kl1 * x1
                to2 = to2 + self.kl1 * (self.k2 / self.k1) * x1
                out2 = out2 + self.kl2 * x[1]
            into_lower = to2 + self.phi * inflow * gate
            rim = jax.nn.sigmoid(self.bl * (x[1] + self.offset - self.h2))
            return jnp.stack([inflow * (1 - gate) - out1, into_lower * (1 - rim) - out2])

        def observe(self, x, u, t):
            return soft_min(x[1:] + self.offset, 10.0, 10.0)

    return T


T1, T2 = _make(1.0), _make(A_HI)
BASE = ("k1", "k2", "k3", "k4", "h", "phi", "h2", "offset", "u0", "a1", "a2")
EXTRA = ("kl1", "kl2", "bo", "bl", "d1", "usat")

# name → (class, process noise, static switches, extra fields freed, base fields frozen,
#         initial values)
MORE_VARIANTS = {
    "chosen": (T1, 0.001, {}, (), (), {}),
    "noise5e-4": (T1, 0.0005, {}, (), (), {}),
    "noise2e-4": (T1, 0.0002, {}, (), (), {}),
    "wide-a": (T2, 0.001, {}, (), (), {}),
    "mixed": (T1, 0.001, dict(mixed=True), ("kl1", "kl2"), ("a1", "a2"), {}),
    "mixed-free-a": (T1, 0.001, dict(mixed=True), ("kl1", "kl2"), (), {}),
    "betas": (T1, 0.001, {}, ("bo", "bl"), (), {}),
    "hole": (T1, 0.001, dict(hole=True), ("d1",), (), {}),
    "pumpsat": (T1, 0.001, dict(pumpsat=True), ("usat",), (), dict(usat=8.0)),
}

CONSTR = {  # for the OE refinement: name → (kind, lo, hi)
    **{
        k: ("pos", 0, 0)
        for k in ("k1", "k2", "k3", "k4", "h", "h2", "kl1", "kl2", "bo", "bl", "usat")
    },
    "phi": ("int", 0.0, 1.0),
    "offset": ("free", 0, 0),
    "u0": ("free", 0, 0),
    "d1": ("free", 0, 0),
}


def guess_for(name):
    """(guess, trainable mask, free fields) of a :data:`MORE_VARIANTS` entry."""
    cls, scale, sw, freed, frozen, init = MORE_VARIANTS[name]
    lib = TANKS.model.factory(dtype=jnp.float64, process_noise=scale)
    vals = {k: getattr(lib, k) for k in BASE}
    g = cls(
        **vals,
        **{k: jnp.asarray(v, jnp.float64) for k, v in init.items()},
        **sw,
        dt=lib.dt,
        substeps=lib.substeps,
        process_noise=lib.process_noise,
        obs_noise=lib.obs_noise,
    )
    fixed = [k for k in EXTRA if k not in freed] + list(frozen)
    mask = eqx.tree_at(
        lambda m: [getattr(m, n) for n in fixed], trainable_mask(g), [False] * len(fixed)
    )
    free = [k for k in BASE + EXTRA if k not in fixed]
    return g, mask, free


def a_bounds(system):
    return (0.1, 1.0) if type(system) is T1 else (0.1, A_HI)


OE_ITERS = int(os.environ.get("OE_ITERS", "60"))


def oe_refine(system, data, n_init, free, iters=OE_ITERS):
    """LM on the free-run output error over the free parameters and the initial state."""
    lo_a, hi_a = a_bounds(system)
    cons = {**CONSTR, "a1": ("int", lo_a, hi_a), "a2": ("int", lo_a, hi_a)}

    def to_u(k, v):
        kind, lo, hi = cons[k]
        if kind == "pos":
            return jnp.log(v)
        if kind == "int":
            p = jnp.clip((v - lo) / (hi - lo), 1e-4, 1 - 1e-4)
            return jnp.log(p / (1 - p))
        return v

    def to_c(k, z):
        kind, lo, hi = cons[k]
        if kind == "pos":
            return jnp.exp(z)
        if kind == "int":
            return lo + (hi - lo) * jax.nn.sigmoid(z)
        return z

    s0 = ceemx.benchmark_score(system, data, n_init)
    x0 = s0.x_sim[0, 0]
    z0 = jnp.concatenate([jnp.stack([to_u(k, getattr(system, k)) for k in free]), x0])
    u, y = data.u[0], data.y[0, :, 0]
    npar = len(free)

    def build(z):
        return eqx.tree_at(
            lambda m: [getattr(m, n) for n in free],
            system,
            [to_c(k, z[i]) for i, k in enumerate(free)],
        )

    def resid(z):
        sysz = build(z)

        def step(x, inp):
            ut, t = inp
            yy = sysz.observe(x, ut, t)[0]
            return sysz.dynamics(x, ut, t), yy

        _, ys = jax.lax.scan(step, z[npar:], (u, jnp.arange(u.shape[0])))
        return ys - y

    rj = jax.jit(lambda z: (resid(z), jax.jacfwd(resid)(z)))
    rf = jax.jit(resid)
    z, lam = z0, 1e-2
    r, J = rj(z)
    cost = float(r @ r)
    c_start = cost
    its = 0
    for _ in range(iters):
        its += 1
        g = J.T @ r
        H = J.T @ J
        improved = False
        for _ in range(10):
            step = jnp.linalg.solve(H + lam * jnp.diag(jnp.diag(H) + 1e-9), -g)
            rn = rf(z + step)
            cn = float(rn @ rn)
            if np.isfinite(cn) and cn < cost:
                z, lam, improved = z + step, max(lam / 3, 1e-7), True
                break
            lam *= 4
        if not improved:
            break
        r, J = rj(z)
        conv = (cost - cn) / cost < 1e-7
        cost = cn
        if conv:
            break
    n = y.shape[0]
    print(
        f"    OE: rmse on fit {np.sqrt(c_start / n):.4f} → {np.sqrt(cost / n):.4f} V "
        f"in {its} iterations",
        flush=True,
    )
    return build(z)


def report(name, part, system, record, n_init, t0, free):
    s = ceemx.benchmark_score(system, record, n_init)
    params = {k: round(float(getattr(system, k)), 4) for k in free}
    print(
        f"{name} {part}: {float(s.rmse[0, 0]):.4f} V, hidden level in "
        f"[{float(s.x_sim[..., 0].min()):.3g}, {float(s.x_sim[..., 0].max()):.3g}] V, "
        f"fit {time.perf_counter() - t0:.0f} s; {params}",
        flush=True,
    )


def variants(names, oe, test, val=True):
    """``variants``: each of :data:`MORE_VARIANTS` on validation and, with ``test``, on test."""
    ds = datasets.cascaded_tanks()
    fit_data, vrec = fits.split(_plan(ds))
    runs = [("validation", fit_data, vrec)] * val + [("test", ds.train, ds.tests["test"])] * test
    for name in names:
        g, mask, free = guess_for(name)
        for part, data, record in runs:
            t0 = time.perf_counter()
            res = ceemx.fit(g, data, solver=ceemx.JointLM(), max_epochs=200, trainable=mask)
            print(f"    J {float(res.history[-1]['J']):.2f}, epochs {len(res.history)}", flush=True)
            report(name, part, res.system, record, ds.n_init, t0, free)
            if oe:
                t1 = time.perf_counter()
                sysoe = oe_refine(res.system, data, ds.n_init, free)
                report(name + "+oe", part, sysoe, record, ds.n_init, t1, free)


# ``sensor``: the level sensor's jumps.

JUMP = 0.3  # V in one sample
BEFORE, AFTER = 30, 10
NOISE = 1e-3


class SensorState(CascadedTanks):
    """``CascadedTanks`` with a sensor state z read on top of the level (see the module)."""

    kf: jax.Array = param(lower=0.0, upper=1.0, default=0.3)  # film per V of fall / relay Δ
    L: jax.Array = param(positive=True, default=5.5)  # collapse / switch-off level (sensor V)
    H: jax.Array = param(positive=True, default=7.0)  # switch-on level of the relay (sensor V)
    kd: jax.Array = param(positive=True, default=1e-4)  # slow drain of the film (1/s)
    kc: jax.Array = param(fixed=True, default=0.5)  # collapse / switching rate (1/s)
    beta_z: jax.Array = param(fixed=True, default=10.0)  # sharpness of the brackets (1/V)
    relay: bool = eqx.field(static=True, default=False)

    @property
    def state_dim(self) -> int:
        return 3

    def vector_field(self, x, u, t):
        d = CascadedTanks.vector_field(self, x[:2], u, t)
        v, z = x[1] + self.offset, x[2]
        if self.relay:
            on = jax.nn.sigmoid(self.beta_z * (v - self.H))
            off = jax.nn.sigmoid(self.beta_z * (self.L - v))
            dz = self.kc * (on * (self.kf - z) - off * z)
        else:
            above = jax.nn.sigmoid(self.beta_z * (v + z - self.L))
            fall = jax.nn.softplus(-20.0 * d[1]) / 20.0
            dz = self.kf * fall * above - z * (self.kc * (1 - above) + self.kd)
        return jnp.concatenate([d, dz[None]])

    def observe(self, x, u, t):
        return soft_min(x[1:2] + self.offset + x[2:3], self.y_max, self.beta_sensor)

    def default_state_mean(self):
        return jnp.asarray([5.0, 5.0, 0.0], jnp.result_type(self.k1))


#: name → (relay?, fields frozen)
SENSOR_VARIANTS = {
    "film": (False, ("kd", "H")),
    "film-drain": (False, ("H",)),
    "relay": (True, ("kd",)),
}


def jumps(y: np.ndarray) -> np.ndarray:
    """Indices i with y[i] − y[i+1] > JUMP (one-sample falls)."""
    return np.flatnonzero(-np.diff(y) > JUMP)


def physics_fit(data):
    guess = _physics_guess()
    return ceemx.fit(guess, data, solver=ceemx.JointLM(), max_epochs=200)


def part1(ds) -> None:
    for name, record in (("training", ds.train), ("test", ds.tests["test"])):
        y, u = np.asarray(record.y[0, :, 0]), np.asarray(record.u[0, :, 0])
        print(f"{name} record, one-sample falls > {JUMP} V:")
        for i in jumps(y):
            print(f"  sample {i}: {y[i]:.2f} → {y[i + 1]:.2f} V")
        rises = np.flatnonzero(np.diff(y) > JUMP)
        print(
            f"  (one-sample rises > {JUMP} V: {rises.size}, the pump at u ≥ {u[rises].min():.2f} V "
            f"there against a median {np.median(u):.2f} V: filling, not the sensor)"
        )
    test = ds.tests["test"]
    s = ceemx.benchmark_score(physics_fit(ds.train).system, test, ds.n_init)
    y, yh = np.asarray(test.y[0, :, 0]), np.asarray(s.y_sim[0, :, 0])
    err = (yh - y)[ds.n_init :]
    keep = np.ones(y.shape, bool)
    keep[: ds.n_init] = False
    for i in jumps(y):
        keep[max(i - BEFORE, 0) : i + 1 + AFTER] = False
    print(
        f"physics model on the test record: {float(s.rmse[0, 0]):.4f} V; without the "
        f"{(~keep[ds.n_init :]).sum()} samples around the jumps ({BEFORE} before, {AFTER} after): "
        f"{np.sqrt(np.mean((yh - y)[keep] ** 2)):.4f} V; their share of the squared error "
        f"{1 - np.sum((yh - y)[keep] ** 2) / np.sum(err**2):.0%}",
        flush=True,
    )


def fit_variant(name: str, data, record, n_init: int):
    """(test RMSE, max |z| over the free run, parameters) on ``record``; the system if ``None``."""
    relay, frozen = SENSOR_VARIANTS[name]
    phys = physics_fit(data)
    base = phys.system
    vals = {f.name: getattr(base, f.name) for f in dataclasses.fields(base) if f.init}
    vals["process_noise"] = jnp.full((3,), NOISE)
    g = SensorState(**vals, relay=relay)
    mask = eqx.tree_at(
        lambda m: [getattr(m, n) for n in frozen], trainable_mask(g), [False] * len(frozen)
    )
    x0 = jnp.concatenate([phys.states, jnp.zeros(phys.states.shape[:-1] + (1,))], -1)
    res = ceemx.fit(g, data, x0, solver=ceemx.JointLM(), max_epochs=200, trainable=mask)
    if record is None:
        return res.system
    s = ceemx.benchmark_score(res.system, record, n_init)
    params = {k: round(float(getattr(res.system, k)), 4) for k in ("kf", "L", "H", "kd")}
    return float(s.rmse[0, 0]), float(np.max(np.abs(s.x_sim[..., 2]))), params


def part2(ds) -> None:
    fit_part, validation = fits.split(_plan(ds))
    runs = (("validation", fit_part, validation), ("test", ds.train, ds.tests["test"]))
    for part, data, record in runs:
        t0 = time.perf_counter()
        s = ceemx.benchmark_score(physics_fit(data).system, record, ds.n_init)
        print(f"physics {part}: {float(s.rmse[0, 0]):.4f} V ({time.perf_counter() - t0:.0f} s)")
        for name in SENSOR_VARIANTS:
            t0 = time.perf_counter()
            rmse, zmax, params = fit_variant(name, data, record, ds.n_init)
            print(
                f"{name} {part}: {rmse:.4f} V, |z| ≤ {zmax:.3f} V over the free run, {params} "
                f"({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )


def fit_named(name: str, data):
    """The physics fit (``physics``) or a sensor-state variant, on ``data``."""
    if name == "physics":
        return physics_fit(data).system
    return fit_variant(name, data, None, 0)


def blocked_folds(ds, K: int = 4):
    """(fit records, held-out record) per block of the training record (``--cv``)."""
    y, u = np.asarray(ds.train.y[0]), np.asarray(ds.train.u[0])
    N = y.shape[0]
    edges = np.linspace(0, N, K + 1).astype(int)
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        pieces = [(s, e) for s, e in ((0, a), (b, N)) if e > s]
        T = max(e - s for s, e in pieces)
        Y, U = np.zeros((len(pieces), T, 1)), np.zeros((len(pieces), T, 1))
        M = np.zeros((len(pieces), T), bool)
        for i, (s, e) in enumerate(pieces):
            Y[i, : e - s], U[i, : e - s], U[i, e - s :], M[i, : e - s] = y[s:e], u[s:e], u[e - 1], 1
        fit = ceemx.Trajectories(jnp.asarray(Y), jnp.asarray(U), jnp.asarray(M))
        yield fit, ds.train[:, max(a - ds.n_init, 0) : b]


def part3(ds) -> None:
    for name in ("physics", *SENSOR_VARIANTS):
        scores = [
            float(ceemx.benchmark_score(fit_named(name, fit), held, ds.n_init).rmse[0, 0])
            for fit, held in blocked_folds(ds)
        ]
        print(
            f"{name} 4-fold blocked CV: {np.round(scores, 4).tolist()}, RMS "
            f"{np.sqrt(np.mean(np.square(scores))):.4f} V",
            flush=True,
        )


def delayed(data, d: int):
    """The record with its input delayed by d samples (the first input repeated)."""
    u = np.asarray(data.u)
    u = np.concatenate([np.repeat(u[:, :1], d, axis=1), u[:, :-d]], axis=1)
    return ceemx.Trajectories(data.y, jnp.asarray(u), data.mask)


def part4(ds) -> None:
    fit_part, validation = fits.split(_plan(ds))
    cut = ds.train.num_steps - validation.num_steps + ds.n_init
    for d in (1, 2):  # delay the whole records, then cut (the validation's window sees u_{t-d})
        train = delayed(ds.train, d)
        parts = (
            (train[:, :cut], train[:, cut - ds.n_init :]),
            (train, delayed(ds.tests["test"], d)),
        )
        scores = [
            float(ceemx.benchmark_score(physics_fit(f).system, r, ds.n_init).rmse[0, 0])
            for f, r in parts
        ]
        print(f"input delayed {d}: validation {scores[0]:.4f} V, test {scores[1]:.4f} V")
    for scale in (0.02, 0.1):
        guess = TANKS.model.factory(
            dtype=jnp.float64, process_noise=NOISE, obs_noise=ceemx.StudentT(scale, 2.0, 1)
        )
        scores = [
            float(
                ceemx.benchmark_score(
                    ceemx.fit(guess, f, solver=ceemx.JointLM(), max_epochs=200).system, r, ds.n_init
                ).rmse[0, 0]
            )
            for f, r in ((fit_part, validation), (ds.train, ds.tests["test"]))
        ]
        print(
            f"Student-t noise {scale} V, ν 2: validation {scores[0]:.4f} V, test {scores[1]:.4f} V"
        )


def part5(ds) -> None:
    plan, test = _plan(ds), ds.tests["test"]
    chosen = plan.chosen
    phys = physics_fit(ds.train)
    start, _ = fits.learned_starts(plan, "joint", phys, None)
    model, info = fits.fit_learned(plan, start.system, start.states, neural=False)
    k = info["best_epoch"]
    s = ceemx.benchmark_score(model, test, ds.n_init)
    print(f"hybrid on the fit part: best epoch {k}, test {float(s.rmse[0, 0]):.4f} V")
    for epochs in (k, round(1.25 * k)):
        h = ceemx.hybrid(
            phys.system, ds.train, states=phys.states, dynamics=TANKS.model.targets,
            width=chosen.width, depth=chosen.depth, prior_std=chosen.prior_std,
            **TANKS.model.bounds,
        )  # fmt: skip
        res = ceemx.fit(
            h, ds.train, phys.states, solver=ceemx.JointLM(), trainable=h.trainable("both"),
            log_prior=ceemx.weight_decay, max_epochs=epochs, diagnose=False,
        )  # fmt: skip
        s = ceemx.benchmark_score(res.system, test, ds.n_init)
        print(
            f"hybrid refitted on the whole record, {epochs} epochs: "
            f"test {float(s.rmse[0, 0]):.4f} V"
        )


def sensor(args: list[str]) -> None:
    """``sensor [--fits] [--cv] [--others] [--refit]``."""
    ds = datasets.cascaded_tanks()
    part1(ds)
    if "--fits" in args:
        part2(ds)
    if "--cv" in args:
        part3(ds)
    if "--others" in args:
        part4(ds)
    if "--refit" in args:
        part5(ds)


def main(argv: list[str]) -> None:
    """Run the subcommand ``argv[0]`` with the rest of ``argv``."""
    if not argv or argv[0] not in ("structure", "variants", "sensor"):
        raise SystemExit(__doc__)
    warnings.simplefilter("ignore")
    ceemx.enable_compilation_cache()  # one compilation per model structure and record length
    mode, args = argv[0], argv[1:]
    flags = {"--oe", "--test", "--test-only"}
    only = "--test-only" in args
    names = [a for a in args if a not in flags]
    if mode == "structure":
        structure(names, "--test" in args or only, not only)
    elif mode == "variants":
        variants(names, "--oe" in args, "--test" in args or only, not only)
    else:
        sensor(args)


if __name__ == "__main__":
    main(sys.argv[1:])
