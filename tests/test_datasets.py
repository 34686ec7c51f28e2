"""Datasets: the helicopter-like generator, the Zenodo helicopter loader, the real datasets."""

import hashlib
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from ceemx import Trajectories, datasets
from ceemx.datasets import heli_sim

# ---------------------------------------------------------------- helicopter-like generator


@pytest.fixture(scope="module")
def small():
    return datasets.helicopter_like(3, n_train=4, n_valid=2, n_test=2, steps=40)


def test_generator_shapes_dtype_and_normalisation(small):
    d = small
    assert isinstance(d, datasets.HelicopterData)
    for split, n in ((d.train, 4), (d.valid, 2), (d.test, 2)):
        assert isinstance(split, Trajectories)
        assert split.y.shape == (n, 40, 6) and split.u.shape == (n, 40, 10)
        assert split.y.dtype == np.float64 and split.u.dtype == np.float64
        assert np.all(np.isfinite(np.asarray(split.y))) and bool(np.asarray(split.mask).all())
    y, u = np.asarray(d.train.y), np.asarray(d.train.u)
    np.testing.assert_allclose(y.mean((0, 1)), 0.0, atol=1e-12)
    np.testing.assert_allclose(y.std((0, 1)), 1.0, rtol=1e-12)
    np.testing.assert_allclose(u.mean((0, 1)), 0.0, atol=1e-12)
    for a, k in ((d.y_mean, 6), (d.y_std, 6), (d.u_mean, 10), (d.u_std, 10)):
        assert a.shape == (k,) and a.dtype == np.float64
    assert d.y_std.min() > 0 and d.dt == 0.02
    assert d.source == "helicopter-like generator (seed 3)"
    names = d.train_names + d.valid_names + d.test_names
    assert len(set(names)) == 8 and all(n.startswith("flight") for n in names)
    # hover-ish mean specific force: about −g along body z
    assert -12.0 < d.y_mean[2] < -6.0


@pytest.mark.slow  # two full generator runs
def test_generator_deterministic_per_seed():
    make = lambda seed: datasets.helicopter_like(seed, n_train=2, n_valid=1, n_test=1, steps=20)  # noqa: E731
    a, b, c = make(3), make(3), make(4)
    np.testing.assert_array_equal(np.asarray(a.test.y), np.asarray(b.test.y))
    np.testing.assert_array_equal(np.asarray(a.train.u), np.asarray(b.train.u))
    assert a.test_names == b.test_names
    assert not np.allclose(np.asarray(a.train.y), np.asarray(c.train.y))


def test_generator_rejects_bad_sizes():
    with pytest.raises(ValueError, match="n_valid"):
        datasets.helicopter_like(0, n_valid=0)
    with pytest.raises(ValueError, match="steps"):
        datasets.helicopter_like(0, n_train=1, n_valid=1, n_test=1, steps=1)


def _unexplained(X, Y, n_train):
    iu = np.triu_indices(X.shape[1])
    F = np.concatenate(
        [np.ones((len(X), 1)), X, (X[:, :, None] * X[:, None, :])[:, iu[0], iu[1]]], 1
    )
    A, B = F[:n_train], Y[:n_train]
    W = np.linalg.solve(A.T @ A + 1e-3 * len(A) * np.eye(A.shape[1]), A.T @ B)
    R = Y[n_train:] - F[n_train:] @ W
    return (R**2).mean(0) / Y[n_train:].var(0)


@pytest.mark.slow
def test_hidden_states_carry_what_the_current_input_misses():
    sim = heli_sim.simulate_flights(np.random.default_rng(0), 8, 400)
    assert sim["u"].shape == (8, 400, 10) and sim["hidden"].shape == (8, 400, 5)
    for v in sim.values():
        assert np.all(np.isfinite(v))
    np.testing.assert_allclose(np.linalg.norm(sim["gravity"], axis=-1), heli_sim.G, rtol=1e-12)
    # samples in random order (a sanity check of the design, not a model comparison)
    order = np.random.default_rng(1).permutation(8 * 400)
    zs = lambda a: (a - a.mean((0, 1))) / a.std((0, 1))  # noqa: E731
    u, z, y = (zs(sim[k]).reshape(8 * 400, -1)[order] for k in ("u", "hidden", "y"))
    n_train = 6 * 400
    naive = _unexplained(u, y, n_train)
    oracle = _unexplained(np.concatenate([u, z], -1), y, n_train)
    assert naive.mean() > 0.08  # a fifth at the default size; the current input is not enough
    assert oracle.mean() < 0.5 * naive.mean()


# ---------------------------------------------------------------- Zenodo helicopter loader


def _write_heli(torch, root: Path, sizes=(("train", 3), ("valid", 2), ("test", 1)), T=7):
    rng = np.random.default_rng(0)
    folder = root / "split_normalized"
    stored = {}
    for split, n in sizes:
        (folder / split).mkdir(parents=True)
        stored[split] = []
        for i in reversed(range(n)):  # written out of order: the loader sorts
            time = np.arange(T) * 0.02
            data = rng.standard_normal((T, 19))
            controls = rng.standard_normal((T, 4))
            torch.save(
                (torch.tensor(time), torch.tensor(data), torch.tensor(controls)),
                folder / split / f"traj_{i:03d}.pt",
            )
            stored[split].append((f"traj_{i:03d}", data, controls))
        stored[split].sort(key=lambda t: t[0])
    stats = [rng.standard_normal(19), rng.random(19) + 0.5, rng.standard_normal(4), rng.random(4)]
    torch.save(tuple(torch.tensor(s) for s in stats), folder / "statistics.pt")
    (folder / "train" / ".hidden.pt").write_bytes(b"not a tensor")  # dot files are skipped
    return stored, stats


def test_load_helicopter_round_trip(tmp_path):
    torch = pytest.importorskip("torch")
    stored, stats = _write_heli(torch, tmp_path)
    for root in (tmp_path, tmp_path / "split_normalized"):
        d = datasets.load_helicopter(root)
        for split in ("train", "valid", "test"):
            traj = getattr(d, split)
            names = getattr(d, f"{split}_names")
            assert names == tuple(n for n, _, _ in stored[split])
            y = np.stack([data[:, -6:] for _, data, _ in stored[split]])
            u = np.stack([np.concatenate([c, data[:, 7:-6]], 1) for _, data, c in stored[split]])
            np.testing.assert_array_equal(np.asarray(traj.y), y)
            np.testing.assert_array_equal(np.asarray(traj.u), u)
            assert traj.y.dtype == np.float64 and traj.u.shape[-1] == 10
        d_mean, d_std, c_mean, c_std = stats
        np.testing.assert_array_equal(d.y_mean, d_mean[-6:])
        np.testing.assert_array_equal(d.y_std, d_std[-6:])
        np.testing.assert_array_equal(d.u_mean, np.concatenate([c_mean, d_mean[7:-6]]))
        np.testing.assert_array_equal(d.u_std, np.concatenate([c_std, d_std[7:-6]]))
        assert d.dt == 0.02 and "3662987" in d.source


def test_load_helicopter_errors(tmp_path, monkeypatch):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        datasets.load_helicopter(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match="split_normalized"):
        datasets.load_helicopter(tmp_path)
    folder = tmp_path / "split_normalized"
    folder.mkdir()
    with pytest.raises(FileNotFoundError, match="statistics.pt"):
        datasets.load_helicopter(folder.parent)
    (folder / "statistics.pt").write_bytes(b"")
    monkeypatch.setitem(sys.modules, "torch", None)  # torch missing
    with pytest.raises(ImportError, match=r"pip install 'ceemx\[torch\]'"):
        datasets.load_helicopter(tmp_path)


def test_load_helicopter_missing_split(tmp_path):
    torch = pytest.importorskip("torch")
    _write_heli(torch, tmp_path, sizes=(("train", 1), ("valid", 1)))
    with pytest.raises(FileNotFoundError, match="test"):
        datasets.load_helicopter(tmp_path)


# ---------------------------------------------------------------- real datasets


def test_windows_arithmetic():
    u = np.arange(10.0)
    y = np.stack([np.arange(10.0), -np.arange(10.0)], 1)
    uw, yw = datasets.windows(u, y, 4)
    assert uw.shape == (2, 4, 1) and yw.shape == (2, 4, 2)
    np.testing.assert_array_equal(uw[1, :, 0], [4, 5, 6, 7])
    uw, yw = datasets.windows(u, y, 4, stride=3)
    assert uw.shape[0] == (10 - 4) // 3 + 1 == 3
    np.testing.assert_array_equal(uw[:, 0, 0], [0, 3, 6])
    np.testing.assert_array_equal(yw[2, :, 1], [-6, -7, -8, -9])
    assert datasets.windows(u, y, 10)[0].shape == (1, 10, 1)
    with pytest.raises(ValueError, match="no window"):
        datasets.windows(u, y, 11)
    with pytest.raises(ValueError, match="stride"):
        datasets.windows(u, y, 4, stride=0)
    with pytest.raises(ValueError, match="shape|\\(N, p\\)"):
        datasets.windows(u[:9], y, 4)


@pytest.mark.parametrize("name", list(datasets.REGISTRY))
def test_registry_entry_is_consistent(name):
    """An entry's names agree with each other, its source and its gray-box model."""
    from ceemx.datasets import download

    e = datasets.REGISTRY[name]
    assert e.name == name and e.source == download.SOURCES[name]
    assert e.file.startswith(f"{name}/") and len(e.sha256) == 64
    assert set(e.default_tests) <= set(e.tests) and set(e.test_names) <= set(e.tests)
    renamed = {e.test_names.get(t, t) for t in e.tests}
    assert all(set(p.rmse) <= renamed and p.unit == e.score_unit for p in e.published)
    columns = {s.u for s in (*e.train.values(), *e.tests.values())}
    columns |= {s.y for s in (*e.train.values(), *e.tests.values())}
    assert max(columns) < len(e.columns)
    model = e.model.factory(**e.model.options)
    assert model.obs_dim == len(e.output_names) and model.control_dim == 1
    assert 0 <= e.model.hidden[1] < model.state_dim
    assert float(np.asarray(model.dt)) == pytest.approx(e.dt)


def test_cli_datasets_are_the_registry(capsys):
    """``--dataset`` choices (listed without importing JAX) are the registry's names."""
    from ceemx import cli

    parser = cli.build_parser()
    for name in datasets.REGISTRY:
        assert parser.parse_args(["experiment", "real_data", "--dataset", name]).dataset == name
    with pytest.raises(SystemExit):
        parser.parse_args(["experiment", "real_data", "--dataset", "nope"])
    listed = re.search(r"choose from ([^)]*)\)", capsys.readouterr().err)
    assert listed is not None
    assert listed.group(1).replace("'", "").split(", ") == list(datasets.REGISTRY)
    with pytest.raises(ValueError, match="unknown dataset"):
        datasets.real_dataset("nope")


def _have(name: str) -> bool:
    try:
        return (datasets.data_root() / datasets.REGISTRY[name].file).is_file()
    except FileNotFoundError:
        return False


def _need(name):
    return pytest.mark.skipif(not _have(name), reason=f"{name} data not available")


@_need("cascaded_tanks")
def test_cascaded_tanks_record_and_splits():
    rec = datasets.load_records("cascaded_tanks")
    u, y = rec.train["estimation"]
    assert u.shape == y.shape == (1024, 1) and u.dtype == np.float64
    assert set(rec.tests) == {"validation"} and rec.tests["validation"][1].shape == (1024, 1)
    assert rec.n_init == 50 and rec.dt == 4.0 and "Schoukens" in rec.citation
    w = datasets.window_splits("cascaded_tanks")
    # 768 training samples, windows of 128 every 32: 21; last 256 → 2; test 1024 → 8.
    assert w.train.y.shape == (21, 128, 1) and w.valid.y.shape == (2, 128, 1)
    assert w.test.y.shape == (8, 128, 1) and w.train.u.shape == (21, 128, 1)
    np.testing.assert_allclose(w.y_mean, y[:768].mean(0))
    np.testing.assert_allclose(w.y_std, y[:768].std(0))
    np.testing.assert_allclose(w.u_mean, u[:768].mean(0))
    # test windows are the official test record, normalised with training statistics
    np.testing.assert_allclose(
        np.asarray(w.test.y)[1, :, 0] * w.y_std[0] + w.y_mean[0],
        rec.tests["validation"][1][128:256, 0],
    )
    np.testing.assert_allclose(
        np.asarray(w.valid.y)[0, :, 0] * w.y_std[0] + w.y_mean[0], y[768:896, 0]
    )
    assert w.output_names == ("lower tank level",) and "cascaded_tanks" in w.source
    s = datasets.window_splits("cascaded_tanks", smoke=True)
    assert s.train.y.shape[0] <= 4 and s.valid.y.shape[0] <= 2 and s.test.y.shape[0] <= 2
    assert 26 <= s.train.y.shape[1] <= 64
    with pytest.raises(ValueError, match="26"):
        datasets.window_splits("cascaded_tanks", length=20)


@_need("cascaded_tanks")
def test_no_test_leakage_and_sha256(tmp_path):
    src = datasets.data_root() / datasets.REGISTRY["cascaded_tanks"].file
    lines = src.read_text().splitlines()
    changed = [lines[0]]
    for line in lines[1:]:  # scale the test output column yVal
        cols = line.split(",")
        if len(cols) < 4:
            changed.append(line)
            continue
        cols[3] = str(10.0 * float(cols[3]))
        changed.append(",".join(cols))
    (tmp_path / "cascaded_tanks").mkdir()
    (tmp_path / "cascaded_tanks" / "dataBenchmark.csv").write_text("\n".join(changed) + "\n")
    with pytest.raises(ValueError, match="sha256"):
        datasets.load_records("cascaded_tanks", root=tmp_path)
    a = datasets.window_splits("cascaded_tanks")
    b = datasets.window_splits("cascaded_tanks", root=tmp_path, verify=False)
    np.testing.assert_array_equal(a.y_mean, b.y_mean)
    np.testing.assert_array_equal(a.y_std, b.y_std)
    np.testing.assert_array_equal(np.asarray(a.train.y), np.asarray(b.train.y))
    np.testing.assert_array_equal(np.asarray(a.valid.y), np.asarray(b.valid.y))
    assert not np.allclose(np.asarray(a.test.y), np.asarray(b.test.y))
    expected = datasets.REGISTRY["cascaded_tanks"].sha256
    assert hashlib.sha256(src.read_bytes()).hexdigest() == expected


@_need("silverbox")
def test_silverbox_record_and_splits():
    rec = datasets.load_records("silverbox")
    assert rec.train["estimation"][0].shape == (105712 - 40650, 1)
    sizes = {k: v[0].shape[0] for k, v in rec.tests.items()}
    assert sizes == {
        "multisine": 127400 - 105712,
        "arrow_full": 40575 - 100,
        "arrow_no_extrapolation": 32100 - 100,
    }
    w = datasets.window_splits("silverbox", smoke=True)
    assert w.train.y.shape == (4, 32, 1) and w.test.y.shape == (2, 32, 1)
    assert w.output_names == ("V2",)


@_need("coupled_electric_drives")
def test_coupled_drives_two_sets():
    rec = datasets.load_records("coupled_electric_drives")
    assert set(rec.train) == set(rec.tests) == {"set1_low", "set2_high"}
    assert rec.train["set1_low"][0].shape == (400, 1) and rec.tests["set2_high"][1].shape == (
        100,
        1,
    )
    assert rec.n_init == 10 and rec.dt == 0.02
    w = datasets.window_splits("coupled_electric_drives")
    # per set: 300 samples, windows of 100 every 20 → 11; valid 1; test 1
    assert w.train.y.shape == (22, 100, 1) and w.valid.y.shape == (2, 100, 1)
    assert w.test.y.shape == (2, 100, 1)
    fit = np.concatenate([rec.train[k][1][:300] for k in ("set1_low", "set2_high")])
    np.testing.assert_allclose(w.y_mean, fit.mean(0))


def test_data_root_resolution(tmp_path, monkeypatch):
    monkeypatch.setenv("CEEMX_DATA", str(tmp_path))
    assert datasets.data_root() == tmp_path.resolve()
    monkeypatch.setenv("CEEMX_DATA", str(tmp_path / "missing"))
    with pytest.raises(FileNotFoundError, match="CEEMX_DATA"):
        datasets.data_root()
    with pytest.raises(FileNotFoundError, match="missing data file"):
        datasets.load_records("silverbox", root=tmp_path)
    with pytest.raises(ValueError, match="unknown dataset"):
        datasets.load_records("nope", root=tmp_path)


# ---------------------------------------------------------------- the official records as datasets


def _col(rec, split, name, k):
    return getattr(rec, split)[name][k][:, 0]


@_need("cascaded_tanks")
def test_cascaded_tanks_dataset():
    ds = datasets.cascaded_tanks()
    rec = datasets.load_records("cascaded_tanks")
    assert isinstance(ds, datasets.RealDataset) and ds.name == "cascaded_tanks"
    assert ds.train.y.shape == ds.train.u.shape == (1, 1024, 1) and ds.train_names == (
        "estimation",
    )
    assert set(ds.tests) == {"test"} and ds.tests["test"].y.shape == (1, 1024, 1)
    assert ds.train.y.dtype == np.float64 and bool(np.asarray(ds.train.mask).all())
    np.testing.assert_array_equal(
        np.asarray(ds.train.y)[0, :, 0], _col(rec, "train", "estimation", 1)
    )
    np.testing.assert_array_equal(
        np.asarray(ds.train.u)[0, :, 0], _col(rec, "train", "estimation", 0)
    )
    np.testing.assert_array_equal(
        np.asarray(ds.tests["test"].y)[0, :, 0], _col(rec, "tests", "validation", 1)
    )
    assert ds.n_init == 50 and ds.dt == 4.0 and ds.score_unit == "V" and ds.score_scale == 1.0
    assert "Schoukens" in ds.citation and "V" in ds.units and ds.verified
    assert ds.sha256 == datasets.REGISTRY["cascaded_tanks"].sha256
    rmse = [p.rmse["test"] for p in ds.published]
    assert rmse == sorted(rmse) and rmse[0] == 0.18 and rmse[-1] == 0.75 and len(rmse) == 6
    assert all(p.unit == "V" and "1024" in p.note for p in ds.published)
    # The records carry their metadata: scores and plots name the channels with their units.
    info = ds.tests["test"].info
    assert info is not None and info == ds.train.info and info.dt == 4.0
    assert info.output_labels(1) == ("lower tank level [V]",)
    assert info.input_names == ("pump voltage",) and info.input_units == ("V",)


@_need("silverbox")
def test_silverbox_dataset():
    ds = datasets.silverbox()
    assert ds.train.y.shape == (1, 105712 - 40650, 1)
    sizes = {k: v.y.shape for k, v in ds.tests.items()}
    assert sizes == {
        "multisine": (1, 127400 - 105712, 1),
        "arrow_full": (1, 40575 - 100, 1),
        "arrow_no_extrapolation": (1, 32100 - 100, 1),
    }
    rec = datasets.load_records("silverbox")
    np.testing.assert_array_equal(
        np.asarray(ds.tests["arrow_full"].u)[0, :, 0], _col(rec, "tests", "arrow_full", 0)
    )
    # the no-extrapolation test is the start of the full arrow record
    np.testing.assert_array_equal(
        np.asarray(ds.tests["arrow_no_extrapolation"].y),
        np.asarray(ds.tests["arrow_full"].y)[:, :32000],
    )
    assert ds.n_init == 50 and abs(ds.dt - 1 / 610.35) < 1e-15
    assert ds.score_unit == "mV" and ds.score_scale == 1000.0
    assert ds.published[0].rmse == {
        "multisine": 2.0,
        "arrow_full": 5.8,
        "arrow_no_extrapolation": 2.0,
    }
    assert "Wigren" in ds.citation and ds.output_names == ("V2",)


@_need("coupled_electric_drives")
def test_coupled_drives_dataset():
    ds = datasets.coupled_electric_drives()
    rec = datasets.load_records("coupled_electric_drives")
    assert ds.train.y.shape == (2, 400, 1) and ds.train_names == ("set1_low", "set2_high")
    assert set(ds.tests) == {"set1_low", "set2_high"}
    assert all(t.y.shape == (1, 100, 1) for t in ds.tests.values())
    for b, name in enumerate(ds.train_names):
        np.testing.assert_array_equal(np.asarray(ds.train.y)[b, :, 0], _col(rec, "train", name, 1))
        np.testing.assert_array_equal(
            np.asarray(ds.tests[name].u)[0, :, 0], _col(rec, "tests", name, 0)
        )
    assert ds.n_init == 10 and ds.dt == 0.02
    assert ds.published[0].rmse == {"set1_low": 0.14, "set2_high": 0.10}
    assert "different split" in ds.published[0].note


@_need("cascaded_tanks")
def test_dataset_sha256_and_missing_file(tmp_path, monkeypatch):
    src = datasets.data_root() / datasets.REGISTRY["cascaded_tanks"].file
    folder = tmp_path / "cascaded_tanks"
    folder.mkdir()
    lines = [line for line in src.read_text().splitlines() if line.strip()]
    (folder / "dataBenchmark.csv").write_text("\n".join(lines[:-1]) + "\n")  # one row short
    with pytest.raises(ValueError, match="sha256"):
        datasets.cascaded_tanks(tmp_path)
    ds = datasets.cascaded_tanks(tmp_path, verify=False)
    assert not ds.verified and ds.train.y.shape == (1, 1023, 1)
    # a missing file: the error names the expected file and both ways to give the folder
    for call in (
        lambda: datasets.silverbox(tmp_path),
        lambda: datasets.coupled_electric_drives(root=tmp_path),
    ):
        with pytest.raises(FileNotFoundError) as err:
            call()
        msg = str(err.value)
        assert "missing data file" in msg and "root=" in msg and "CEEMX_DATA" in msg
    with pytest.raises(FileNotFoundError, match=r"silverbox/SNLS80mV\.csv"):
        datasets.silverbox(tmp_path)
    monkeypatch.setenv("CEEMX_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match=r"SNLS80mV\.csv.*CEEMX_DATA"):
        datasets.silverbox()
    monkeypatch.setenv("CEEMX_DATA", str(tmp_path))
    assert datasets.cascaded_tanks(verify=False).path == (folder / "dataBenchmark.csv").resolve()


@_need("coupled_electric_drives")
def test_dataset_windows():
    ds = datasets.coupled_electric_drives()
    w = ds.train.windows(100, 50)  # per set (400 − 100) // 50 + 1 = 7 windows
    assert w.y.shape == (14, 100, 1) and w.u.shape == (14, 100, 1) and w.mask.shape == (14, 100, 1)
    y = np.asarray(ds.train.y)
    np.testing.assert_array_equal(np.asarray(w.y)[8], y[1, 50:150])  # set 2, second window
    np.testing.assert_array_equal(np.asarray(w.u)[6], np.asarray(ds.train.u)[0, 300:400])
    assert ds.train.windows(400).y.shape == (2, 400, 1)


# ---------------------------------------------------------------- Trajectories conveniences


def test_trajectories_windows_carry_masks():
    rng = np.random.default_rng(0)
    y, u = rng.standard_normal((2, 10, 2)), rng.standard_normal((2, 10, 3))
    mask = np.ones((2, 10, 2), bool)
    mask[1, 6:] = False  # padding of a shorter record
    mask[0, 2, 1] = False
    d = Trajectories(y, u, mask)
    w = d.windows(4, 3)  # starts 0, 3, 6 per record
    assert w.y.shape == (6, 4, 2) and w.u.shape == (6, 4, 3) and w.mask.shape == (6, 4, 2)
    for i, (b, t) in enumerate((b, t) for b in range(2) for t in (0, 3, 6)):
        np.testing.assert_array_equal(np.asarray(w.mask)[i], mask[b, t : t + 4])
        np.testing.assert_array_equal(np.asarray(w.u)[i], u[b, t : t + 4])
        np.testing.assert_array_equal(
            np.asarray(w.y)[i], np.where(mask[b, t : t + 4], y[b, t : t + 4], 0.0)
        )
    assert not np.asarray(w.mask)[5].any() and not np.asarray(w.mask)[0, 2, 1]
    assert d.windows(5).y.shape == (4, 5, 2)  # no overlap by default
    assert Trajectories(y).windows(10).u.shape == (2, 10, 0)
    for bad in ((1,), (11,), (4, 0), (4.0,)):
        with pytest.raises(ValueError, match="length|step"):
            d.windows(*bad)


def test_trajectories_from_arrays():
    t = Trajectories.from_arrays(np.arange(5.0), np.ones(5))
    assert t.y.shape == (1, 5, 1) and t.u.shape == (1, 5, 1) and t.mask.shape == (1, 5, 1)
    np.testing.assert_array_equal(np.asarray(t.y)[0, :, 0], np.arange(5.0))
    t = Trajectories.from_arrays(np.zeros((5, 2)), np.ones((5, 3)), np.arange(5) < 3)
    assert t.y.shape == (1, 5, 2) and t.u.shape == (1, 5, 3)
    np.testing.assert_array_equal(np.asarray(t.mask)[0, :, 1], np.arange(5) < 3)
    assert Trajectories.from_arrays(np.arange(5.0)).u.shape == (1, 5, 0)
    y = np.zeros((2, 5, 1))
    assert Trajectories.from_arrays(y, np.ones((2, 5, 1))).y.shape == (2, 5, 1)
    with pytest.raises(ValueError, match="`y`"):
        Trajectories.from_arrays(np.zeros((1, 2, 3, 4)))
    with pytest.raises(ValueError, match="`u`"):
        Trajectories.from_arrays(np.zeros(5), np.zeros((1, 5, 1)))
    with pytest.raises(ValueError, match="T >= 2"):
        Trajectories.from_arrays(np.zeros(1))
