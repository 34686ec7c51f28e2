"""Data parallelism over the trajectory axis (:mod:`ceemx.data.sharding`, ``fit(devices=...)``).

The multi-device test runs in a subprocess: ``--xla_force_host_platform_device_count`` must be in
``XLA_FLAGS`` before JAX starts its backend, and this process already has one CPU device.
"""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.data.sharding import batch_mesh, resolve_devices, shard_batch

_MARKER = "SHARDING-OK"

_CHILD = r"""
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import ceemx
from ceemx.experiments import common

assert len(jax.devices()) == 4, jax.devices()
true = common.true_lorenz(1, m=2, coupling=False, process_noise=0.01, obs_noise=0.1)
p = common.lorenz_problem(0, true, B=8, T=32, sigma_w=0.01, sigma_v=0.1, coupling=False)
x0 = ceemx.warm_start(p.init_system, p.data)


def close(a, b, what):
    a, b = np.asarray(a), np.asarray(b)
    err = np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)
    assert err <= 1e-10, f"{what}: relative difference {err:.3g}"
    return err


worst = 0.0
for solver in (ceemx.JointLM(), ceemx.Alternating()):
    runs = {}
    for devices in (None, "all"):
        runs[devices] = ceemx.fit(
            p.init_system, p.data, x0, solver=solver, trainable=common.LORENZ_PARAMS,
            max_epochs=5, outliers="keep", progress=False, devices=devices,
        )
    ref, par = runs[None], runs["all"]
    name = type(solver).__name__
    assert len(ref.states.sharding.device_set) == 1, ref.states.sharding
    assert len(par.states.sharding.device_set) == 4, par.states.sharding
    assert len(ref.history) == len(par.history) == 5, (len(ref.history), len(par.history))
    for leaf_r, leaf_p in zip(common.LORENZ_PARAMS(ref.system), common.LORENZ_PARAMS(par.system)):
        worst = max(worst, close(leaf_p, leaf_r, f"{name} parameters"))
    worst = max(worst, close(par.states, ref.states, f"{name} states"))
    for hr, hp in zip(ref.history, par.history):
        worst = max(worst, close(hp["J"], hr["J"], f"{name} J at epoch {hr['epoch']}"))

# B = 6 on 4 devices: the largest divisor, 3 devices; strict: a ValueError naming B and the count
from ceemx.data.sharding import batch_mesh, shard_batch
d6, x6 = shard_batch(p.data[np.arange(6)], x0[:6], batch_mesh())
assert len(x6.sharding.device_set) == 3 and len(d6.y.sharding.device_set) == 3
np.testing.assert_array_equal(np.asarray(x6), np.asarray(x0[:6]))
try:
    shard_batch(p.data[np.arange(6)], x0[:6], batch_mesh(), strict=True)
except ValueError as e:
    assert "B = 6" in str(e) and "4 devices" in str(e), str(e)
else:
    raise AssertionError("strict=True accepted B = 6 on 4 devices")

# an outlier excluded at the start (B = 8 -> 7 fitted): the subset stays on the mesh
y = np.array(p.data.y)
y[3] += 50.0
import warnings
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    res = ceemx.fit(
        p.init_system, ceemx.Trajectories(y), x0, solver=ceemx.JointLM(),
        trainable=common.LORENZ_PARAMS, max_epochs=1, progress=False, devices="all",
    )
assert res.excluded == (3,) and np.isfinite(res.history[-1]["J"]), (res.excluded, res.history)
assert len(res.states.sharding.device_set) == 4 and res.states.shape[0] == 8
print(f"SHARDING-OK 4 devices, worst relative difference {worst:.2e}")
"""


@pytest.mark.slow  # a fresh process with 4 forced devices compiles 4 fits (≈ 50 s)
def test_fit_on_four_devices_matches_one():
    """``devices="all"`` on 4 forced host devices: same θ, states and J as without sharding."""
    flags = os.environ.get("XLA_FLAGS", "")
    env = {**os.environ, "XLA_FLAGS": f"{flags} --xla_force_host_platform_device_count=4".strip()}
    out = subprocess.run(
        [sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-4000:]
    line = [s for s in out.stdout.splitlines() if s.startswith(_MARKER)]
    assert line, out.stdout
    print(line[-1])


def test_shard_batch_one_device():
    """In this process (one device): values unchanged, every batch array on the mesh's device."""
    mesh = batch_mesh()
    data = ceemx.Trajectories(np.arange(3 * 3 * 2, dtype=float).reshape(3, 3, 2))
    states = jnp.ones((3, 3, 4))
    out, x = shard_batch(data, states, mesh, strict=True)
    for a, b in ((out.y, data.y), (out.u, data.u), (out.mask, data.mask), (x, states)):
        assert a.sharding.device_set == set(mesh.devices.flat)
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="batch size 2"):
        shard_batch(data, states[:2], mesh)


def test_resolve_devices():
    assert resolve_devices(None) is None
    mesh = resolve_devices("all")
    assert mesh is not None and mesh.axis_names == ("batch",)
    assert mesh.devices.size == len(jax.devices())
    assert resolve_devices(mesh) is mesh
    with pytest.raises(TypeError, match="devices"):
        resolve_devices("gpu")


@pytest.mark.slow  # a fit with devices='all' (≈ 6 s); the 4-device equality stays
def test_fit_devices_all_on_one_device_changes_nothing():
    """With one visible device ``devices="all"`` gives the very same fit as ``devices=None``."""
    from ceemx.experiments import common

    true = common.true_lorenz(1, m=2, coupling=False, process_noise=0.01, obs_noise=0.1)
    p = common.lorenz_problem(0, true, B=2, T=8, sigma_w=0.01, sigma_v=0.1, coupling=False)
    kw = dict(solver=ceemx.JointLM(), trainable=common.LORENZ_PARAMS, max_epochs=2)
    kw |= dict(outliers="keep", progress=False)
    ref = ceemx.fit(p.init_system, p.data, p.states, devices=None, **kw)
    par = ceemx.fit(p.init_system, p.data, p.states, devices="all", **kw)
    np.testing.assert_allclose(par.states, ref.states, rtol=1e-12)
    assert [h["J"] for h in par.history] == pytest.approx([h["J"] for h in ref.history], 1e-12)
