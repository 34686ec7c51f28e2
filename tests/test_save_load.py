"""Saving, loading and exporting identified models (ceemx.save, ceemx.load, ceemx.export_*).

The round trip that matters is to another process: a model saved here is loaded by a fresh
Python (a subprocess) and free-runs to the same outputs, bit for bit — for a built-in system and
for a user's class defined in a module on the path.
"""

import json
import os
import pathlib
import subprocess
import sys
import zipfile

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.systems import CoupledLorenz, LinearSystem

SRC = pathlib.Path(__file__).parents[1] / "src"

# A user's model, in a module of its own (docs/custom_systems.md's mass-spring-damper).
USER_MODULE = """
import jax.numpy as jnp
from jaxtyping import Array

import ceemx


class MassSpringDamper(ceemx.AbstractContinuousSystem):
    k: Array = ceemx.param(positive=True)
    c: Array = ceemx.param(positive=True)
    m: Array = ceemx.param(fixed=True, default=1.0)

    @property
    def state_dim(self) -> int:
        return 2

    @property
    def obs_dim(self) -> int:
        return 1

    @property
    def control_dim(self) -> int:
        return 1

    def vector_field(self, x, u, t):
        return jnp.stack([x[1], (u[0] - self.k * x[0] - self.c * x[1]) / self.m])

    def observe(self, x, u, t):
        return x[:1]
"""

LOAD_AND_RUN = """
import sys
import jax
import numpy as np
jax.config.update("jax_enable_x64", True)
import ceemx
folder = sys.argv[1]
given = np.load(folder + "/inputs.npz")
out = {}
for name in ("lorenz", "msd"):
    model, info = ceemx.load(folder + f"/{name}.ceemx", with_info=True)
    u = given[name + "_u"] if given[name + "_u"].shape[-1] else None
    xs, ys = ceemx.free_run(model, given[name + "_x1"], u, num_steps=60)
    out[name] = ys
    out[name + "_class"] = np.array(type(model).__module__ + "." + type(model).__qualname__)
    out[name + "_dt"] = np.array(-1.0 if info.data is None else info.data.dt)
np.savez(folder + "/loaded.npz", **out)
"""


def lorenz():
    return CoupledLorenz(10.0, 28.0, 8 / 3, np.eye(3), dt=0.04, obs_noise=0.3)


@pytest.fixture(scope="module")
def user_module(tmp_path_factory):
    folder = tmp_path_factory.mktemp("user_models")
    (folder / "ceemx_test_user_models.py").write_text(USER_MODULE)
    sys.path.insert(0, str(folder))
    try:
        import ceemx_test_user_models  # pyright: ignore[reportMissingImports]

        yield folder, ceemx_test_user_models
    finally:
        sys.path.remove(str(folder))
        sys.modules.pop("ceemx_test_user_models", None)


def test_save_then_load_in_a_fresh_process_free_runs_identically(tmp_path, user_module):
    folder, mod = user_module
    msd = mod.MassSpringDamper(k=4.0, c=0.5, dt=0.1, hold="foh", substeps=2, obs_noise=0.01)
    T = 60
    rng = np.random.default_rng(0)
    inputs = {
        "lorenz_x1": np.array([-6.0, -6.0, 24.0]),
        "lorenz_u": np.zeros((T, 0)),
        "msd_x1": np.array([0.3, 0.0]),
        "msd_u": np.asarray(ceemx.foh_inputs(rng.standard_normal((T, 1)))),
    }
    np.savez(tmp_path / "inputs.npz", **inputs)
    data = ceemx.Trajectories.from_arrays(np.zeros(T), inputs["msd_u"], dt=0.1, output_names="q")
    ceemx.save(tmp_path / "lorenz.ceemx", lorenz())
    ceemx.save(tmp_path / "msd.ceemx", msd, data=data)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), str(folder)]))
    run = subprocess.run(
        [sys.executable, "-c", LOAD_AND_RUN, str(tmp_path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    loaded = np.load(tmp_path / "loaded.npz")
    _, want_lorenz = ceemx.free_run(lorenz(), inputs["lorenz_x1"], num_steps=T)
    _, want_msd = ceemx.free_run(msd, inputs["msd_x1"], inputs["msd_u"])
    np.testing.assert_array_equal(loaded["lorenz"], want_lorenz)  # bit for bit
    np.testing.assert_array_equal(loaded["msd"], want_msd)
    assert str(loaded["lorenz_class"]) == "ceemx.systems.lorenz.CoupledLorenz"
    assert str(loaded["msd_class"]) == "ceemx_test_user_models.MassSpringDamper"
    assert float(loaded["msd_dt"]) == 0.1 and float(loaded["lorenz_dt"]) == -1.0


def test_a_loaded_model_equals_the_saved_one_leaf_for_leaf(tmp_path):
    """A hybrid (an MLP with a module-level lambda as its final activation, bounds with inf)."""
    from ceemx.systems.learned_term import learned_term

    physics = LinearSystem(0.9 * jnp.eye(2), jnp.eye(2), process_noise=0.1)
    term = learned_term(
        jax.random.PRNGKey(0), x_mean=jnp.zeros(2), x_scale=jnp.ones(2), out_scale=jnp.ones(2)
    )
    hybrid = ceemx.Hybrid(physics, term, lower=jnp.array([0.0, -jnp.inf]))
    assert hybrid.lower == (0.0, -np.inf)
    for model in (physics, hybrid):
        path = ceemx.save(tmp_path / "m.ceemx", model)
        back = ceemx.load(path)
        assert type(back) is type(model) and bool(eqx.tree_equal(back, model))
        assert jax.tree_util.tree_structure(back) == jax.tree_util.tree_structure(model)
    with zipfile.ZipFile(path) as z:
        assert sorted(z.namelist()) == ["leaves.eqx", "model.json"]
        meta = json.loads(z.read("model.json"))
    assert meta["info"]["model"] == "ceemx.systems.hybrid:Hybrid"
    assert meta["info"]["dtype"] == "float64" and meta["info"]["ceemx_version"]


def test_a_fit_result_saves_its_summary_and_data_metadata(tmp_path):
    truth = LinearSystem(jnp.array([[0.8]]), jnp.array([[1.0]]), process_noise=0.1, obs_noise=0.1)
    _, sim = ceemx.simulate(truth, jax.random.PRNGKey(0), jnp.zeros((1, 1)), 20)
    data = sim.with_info(dt=0.5, output_names=("level",), output_units=("V",))
    guess = LinearSystem(jnp.array([[0.5]]), jnp.array([[1.0]]), process_noise=0.1, obs_noise=0.1)
    result = ceemx.fit(guess, data, max_epochs=1, solver=ceemx.Alternating())
    result.save(tmp_path / "fit.ceemx")
    model, info = ceemx.load(tmp_path / "fit.ceemx", with_info=True)
    assert bool(eqx.tree_equal(model, result.system))
    assert info.fit == repr(result) and info.fit.startswith("FitResult(")
    assert info.data == data.info and info.model == "ceemx.systems.linear:LinearSystem"
    assert (info.state_dim, info.obs_dim, info.input_dim, info.dtype) == (1, 1, 0, "float64")
    assert info.noise["obs_noise"].startswith("DiagonalGaussian, std ")
    text = str(info)
    assert "outputs level [V]" in text and "fit: FitResult(" in text


def test_load_says_why_it_cannot(tmp_path):
    folder = tmp_path / "gone"
    folder.mkdir()
    (folder / "ceemx_test_vanishing.py").write_text(USER_MODULE)
    sys.path.insert(0, str(folder))
    try:
        import ceemx_test_vanishing  # pyright: ignore[reportMissingImports]

        model = ceemx_test_vanishing.MassSpringDamper(k=1.0, c=1.0, dt=0.1)
        path = ceemx.save(tmp_path / "v.ceemx", model)
    finally:
        sys.path.remove(str(folder))
        sys.modules.pop("ceemx_test_vanishing", None)
    with pytest.raises(
        ImportError, match="ceemx_test_vanishing:MassSpringDamper is defined in mod"
    ):
        ceemx.load(path)
    (tmp_path / "junk.ceemx").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="is not a ceemx model file"):
        ceemx.load(tmp_path / "junk.ceemx")
    with pytest.raises(FileNotFoundError, match="no model file"):
        ceemx.load(tmp_path / "absent.ceemx")
    good = ceemx.save(tmp_path / "l.ceemx", lorenz())
    with zipfile.ZipFile(good) as z:
        meta, leaves = json.loads(z.read("model.json")), bytearray(z.read("leaves.eqx"))
    leaves[-1] ^= 1
    with zipfile.ZipFile(tmp_path / "bad.ceemx", "w") as z:
        z.writestr("model.json", json.dumps(meta))
        z.writestr("leaves.eqx", bytes(leaves))
    with pytest.raises(ValueError, match="is corrupt"):
        ceemx.load(tmp_path / "bad.ceemx")


def test_save_refuses_what_it_could_not_load():
    class Local(ceemx.AbstractSystem):  # defined in a function: no import path
        a: jax.Array

        @property
        def state_dim(self):
            return 1

        @property
        def obs_dim(self):
            return 1

        def dynamics(self, x, u, t):
            return self.a * x

        def observe(self, x, u, t):
            return x

    with pytest.raises(ValueError, match="Local is defined inside a function"):
        ceemx.save("unused.ceemx", Local(jnp.ones(1)))
    with pytest.raises(TypeError, match="must be a ceemx.AbstractSystem or a ceemx.FitResult"):
        ceemx.save("unused.ceemx", {"a": 1})
    assert not os.path.exists("unused.ceemx")


def test_export_step_and_exported_simulation_reproduce_the_free_run(tmp_path):
    model = lorenz()
    x1 = jnp.array([[-6.0, -6.0, 24.0], [1.0, 2.0, 20.0]])
    _, want = ceemx.free_run(model, x1, num_steps=40)

    step = ceemx.export_step(model)

    @jax.jit
    def run(step, x):
        return jax.lax.scan(lambda x, t: step(x, jnp.zeros(0), t), x, jnp.arange(40))[1]

    np.testing.assert_array_equal(jax.vmap(run, (None, 0))(step, x1), want)

    path = tmp_path / "lorenz.jaxexport"
    ceemx.export_simulate(model, path)
    exported = jax.export.deserialize(path.read_bytes())  # JAX alone, no ceemx model class
    states, outputs = exported.call(x1, jnp.zeros((2, 40, 0)))
    np.testing.assert_array_equal(outputs, want)
    _, short = exported.call(x1[:1], jnp.zeros((1, 7, 0)))  # any B and T
    np.testing.assert_array_equal(short, want[:1, :7])
    fixed = ceemx.export_simulate(model, batch_size=2, num_steps=40)
    assert fixed.in_avals[1].shape == (2, 40, 0)
    with pytest.raises(ValueError, match="`num_steps` must be a positive integer"):
        ceemx.export_simulate(model, num_steps=0)


class ScriptModel(ceemx.AbstractSystem):
    """A model as a script defines it (moved into ``__main__`` by the test below)."""

    a: jax.Array

    @property
    def state_dim(self):
        return 1

    @property
    def obs_dim(self):
        return 1

    def dynamics(self, x, u, t):
        return self.a * x

    def observe(self, x, u, t):
        return x


def test_a_class_of_a_script_saves_with_a_warning_and_loads_where_main_has_it(
    tmp_path, monkeypatch
):
    monkeypatch.setattr(ScriptModel, "__module__", "__main__")
    monkeypatch.setattr(sys.modules["__main__"], "ScriptModel", ScriptModel, raising=False)
    with pytest.warns(UserWarning, match=r"defined in a script or notebook \(__main__\)"):
        path = ceemx.save(tmp_path / "s.ceemx", ScriptModel(jnp.array([0.5])))
    assert float(ceemx.load(path).a[0]) == 0.5
    monkeypatch.delattr(sys.modules["__main__"], "ScriptModel")
    with pytest.raises(ImportError, match=r"defined in a script or notebook \(__main__\)"):
        ceemx.load(path)
