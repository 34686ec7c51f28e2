"""The real datasets' files downloaded into a user cache (ceemx.datasets.download), and records
of the ``nonlinear-benchmarks`` package as Trajectories (ceemx.data.from_nonlinear_benchmarks).

No network: the download path runs against ``file://`` URLs of archives made here from the
official files in ``../shared/data``, and an offline host is simulated by a downloader that
raises the error ``requests`` raises without a network.
"""

import dataclasses
import hashlib
import zipfile
from pathlib import Path

import numpy as np
import pytest

from ceemx import datasets
from ceemx.data import RecordInfo, Trajectories, from_nonlinear_benchmarks
from ceemx.datasets import download

CED = "coupled_electric_drives"


def _find(name: str) -> Path | None:
    try:
        path = datasets.data_root() / datasets.REGISTRY[name].file
    except FileNotFoundError:
        return None
    return path if path.is_file() else None


#: the official files of this checkout (../shared/data or CEEMX_DATA), found before any test
#: hides them
OFFICIAL = {name: _find(name) for name in datasets.REGISTRY}


def _official(name: str) -> Path:
    path = OFFICIAL[name]
    assert path is not None
    return path


def _need(name):
    return pytest.mark.skipif(OFFICIAL[name] is None, reason=f"{name} data not available")


def _archive(tmp_path: Path, name: str, content: bytes | None = None) -> str:
    """A zip laid out like the host's (a folder inside), holding the official file or
    ``content``; returns its ``file://`` URL."""
    src = download.SOURCES[name]
    path = tmp_path / "host" / src.archive
    path.parent.mkdir(parents=True, exist_ok=True)
    data = content if content is not None else _official(name).read_bytes()
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("ReadMe.txt", "the benchmark")
        z.writestr(f"Files/{src.member}", data)
    return path.as_uri()


@pytest.fixture
def fresh(tmp_path, monkeypatch):
    """A fresh machine: no CEEMX_DATA, no ../shared/data, an empty cache under tmp_path."""
    monkeypatch.delenv("CEEMX_DATA", raising=False)
    monkeypatch.setenv("CEEMX_DATA_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(download, "_checkout_folders", lambda: [])
    return tmp_path / "cache"


def _serve(monkeypatch, name: str, url: str) -> None:
    monkeypatch.setitem(
        download.SOURCES, name, dataclasses.replace(download.SOURCES[name], url=url)
    )


@_need(CED)
def test_fresh_clone_downloads_checks_and_caches(fresh, tmp_path, monkeypatch):
    url = _archive(tmp_path, CED)
    _serve(monkeypatch, CED, url)
    ds = datasets.coupled_electric_drives()  # first use: downloaded
    target = fresh / "coupled_electric_drives" / "DATAUNIF.csv"
    assert ds.path == target and target.read_bytes() == _official(CED).read_bytes()
    assert download.sha256(target) == datasets.REGISTRY[CED].sha256
    here = datasets.coupled_electric_drives(root=_official(CED).parents[1])
    np.testing.assert_array_equal(ds.train.y, here.train.y)
    # Later uses read the cache: the host may be gone.
    Path(url.removeprefix("file://")).unlink()
    assert datasets.load_records(CED).path == target
    assert datasets.data_file(CED, download=False) == target
    # CEEMX_DATA still wins (and must hold the file).
    monkeypatch.setenv("CEEMX_DATA", str(tmp_path / "elsewhere"))
    with pytest.raises(FileNotFoundError, match="CEEMX_DATA"):
        datasets.data_file(CED)


@_need(CED)
def test_a_wrong_checksum_is_refused_and_removed(fresh, tmp_path):
    tampered = _official(CED).read_bytes().replace(b"1", b"2", 1)
    url = _archive(tmp_path, CED, tampered)
    with pytest.raises(ValueError, match="sha256 of the DATAUNIF.csv downloaded from"):
        download.fetch(CED, url=url)
    assert not (fresh / "coupled_electric_drives" / "DATAUNIF.csv").exists()


def test_not_an_archive_is_refused(fresh, tmp_path):
    page = tmp_path / "page.html"
    page.write_text("<html>a sign-in page</html>")
    with pytest.raises(ValueError, match="is not the cascaded_tanks archive"):
        download.fetch("cascaded_tanks", url=page.as_uri())


def test_offline_fails_with_one_sentence(fresh, monkeypatch):
    import pooch
    import requests

    def offline(self, url, output_file, pooch, check_only=False):
        raise requests.exceptions.ConnectionError("Failed to resolve host")

    monkeypatch.setattr(pooch.HTTPDownloader, "__call__", offline)
    with pytest.raises(datasets.DatasetUnavailable) as info:
        datasets.silverbox()
    message = str(info.value)
    target = fresh / "silverbox" / "SNLS80mV.csv"
    assert message.startswith("Could not download the silverbox dataset (SilverboxFiles.zip)")
    assert download.SOURCES["silverbox"].url in message and str(target) in message
    assert "CEEMX_DATA" in message and message.count(". ") == 0  # one sentence
    assert isinstance(info.value, FileNotFoundError)
    with pytest.raises(datasets.DatasetUnavailable, match="download=False"):
        datasets.silverbox(download=False)
    with pytest.raises(datasets.DatasetUnavailable, match="Could not download"):
        download.fetch("silverbox", url=(fresh / "missing.zip").as_uri())


# --- a cached file that fails its checksum is fetched again ------------------------------------

TOY_DATA = b"u,y\n1,2\n"


def _toy_zip(path: Path, data: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("Files/toy.csv", data)
    return path


@pytest.fixture
def toy(fresh, tmp_path, monkeypatch):
    """A dataset ``toy`` served as a file:// archive; its data file downloaded into the cache."""
    host = _toy_zip(tmp_path / "host" / "toy.zip", TOY_DATA)
    digest = hashlib.sha256(TOY_DATA).hexdigest()
    src = download.Source(host.as_uri(), "toy.zip", "toy.csv", "toy/toy.csv", digest)
    monkeypatch.setitem(download.SOURCES, "toy", src)
    target = download.fetch("toy")
    assert target == fresh / "toy" / "toy.csv" and target.read_bytes() == TOY_DATA
    return target, host


def test_a_corrupt_cached_file_is_set_aside_and_fetched_again(toy):
    """It was returned as it was; the loaders then refused it at every call ("sha256 of … is
    …; replace it with the official file"), the cache never repaired."""
    target, host = toy
    target.write_bytes(b"u,y\n1,9\n")  # a torn or altered file
    host.unlink()  # no download: the cached archive holds the right file
    assert datasets.data_file("toy") == target and target.read_bytes() == TOY_DATA
    assert target.with_name("toy.csv.corrupt").read_bytes() == b"u,y\n1,9\n"
    # The cached archive holds a wrong file too: downloaded afresh.
    target.write_bytes(b"garbage")
    _toy_zip(target.parents[1] / "archives" / "toy.zip", b"garbage")
    _toy_zip(host, TOY_DATA)
    assert datasets.data_file("toy") == target and target.read_bytes() == TOY_DATA


def test_a_corrupt_cached_file_offline_fails_with_one_sentence(toy, monkeypatch):
    import pooch
    import requests

    def offline(self, url, output_file, pooch, check_only=False):
        raise requests.exceptions.ConnectionError("Failed to resolve host. Try again.")

    target, _ = toy
    url = "https://example.org/toy.zip"  # the pooch boundary: an HTTP download that fails
    monkeypatch.setitem(
        download.SOURCES, "toy", dataclasses.replace(download.SOURCES["toy"], url=url)
    )
    monkeypatch.setattr(pooch.HTTPDownloader, "__call__", offline)
    target.write_bytes(b"garbage")
    with pytest.raises(datasets.DatasetUnavailable, match="download=False"):
        datasets.data_file("toy", download=False)  # refused, not returned
    assert target.read_bytes() == b"garbage"
    (target.parents[1] / "archives" / "toy.zip").unlink()
    with pytest.raises(datasets.DatasetUnavailable) as info:
        datasets.data_file("toy")
    message = str(info.value)
    aside = target.with_name("toy.csv.corrupt")
    assert message.startswith("The cached toy.csv of the toy dataset failed its sha256 check")
    assert f"moved to {aside}" in message and url in message and str(target) in message
    assert message.count(". ") == 0 and aside.read_bytes() == b"garbage"


def test_cache_folder(monkeypatch, tmp_path):
    import pooch

    monkeypatch.delenv("CEEMX_DATA_CACHE", raising=False)
    assert download.cache_dir() == Path(pooch.os_cache("ceemx")) / "datasets"
    monkeypatch.setenv("CEEMX_DATA_CACHE", str(tmp_path))
    assert download.cache_dir() == tmp_path
    assert download.cache_dir(tmp_path / "x") == tmp_path / "x"


# --------------------------------------------------------------------------------------------
# nonlinear-benchmarks records
# --------------------------------------------------------------------------------------------


class IOData:
    """A stand-in for ``nonlinear_benchmarks.Input_output_data`` (v1.0.1): u, y, the sample
    period, the initialisation window, a name, and slicing."""

    def __init__(self, u, y, sampling_time=None, name=None, n_init=None):
        self.u, self.y = np.asarray(u), np.asarray(y)
        self.sampling_time, self.name = sampling_time, name
        self.state_initialization_window_length = n_init

    def __getitem__(self, s):
        return IOData(self.u[s], self.y[s], self.sampling_time, self.name)


def _package_splits(name: str):
    """The package's v1.0.1 splits, made from the official file as its loaders make them."""
    columns = range(2 if name == "silverbox" else 4)
    d = np.loadtxt(_official(name), delimiter=",", skiprows=1, usecols=columns)
    if name == "cascaded_tanks":
        train, test = IOData(d[:, 0], d[:, 2], 4.0), IOData(d[:, 1], d[:, 3], 4.0)
        test.state_initialization_window_length = 50
        return train, {"test": test}
    if name == "silverbox":
        full = IOData(d[:, 0], d[:, 1], 1 / 610.35)
        arrow = full[100:40575]
        multisine = full[40650:127400]
        s = int(len(multisine.y) * 0.75)
        tests = {"multisine": multisine[s:], "arrow_full": arrow,
                 "arrow_no_extrapolation": arrow[:32000]}  # fmt: skip
        for t in tests.values():
            t.state_initialization_window_length = 50
        return multisine[:s], tests
    low, high = IOData(d[:, 0], d[:, 2], 0.02), IOData(d[:, 1], d[:, 3], 0.02)
    tests = {"set1_low": low[400:], "set2_high": high[400:]}
    for t in tests.values():
        t.state_initialization_window_length = 10
    return (low[:400], high[:400]), tests


@pytest.mark.parametrize("name", list(datasets.REGISTRY))
def test_nonlinear_benchmarks_records_agree_with_ours(name):
    if OFFICIAL[name] is None:
        pytest.skip(f"{name} data not available")
    ours = datasets.real_dataset(name)
    train, tests = _package_splits(name)
    t = from_nonlinear_benchmarks(train)
    assert isinstance(t, Trajectories)
    np.testing.assert_array_equal(t.y, ours.train.y)
    np.testing.assert_array_equal(t.u, ours.train.u)
    for key, record in tests.items():
        got, info = from_nonlinear_benchmarks(record, with_info=True)
        np.testing.assert_array_equal(got.y, ours.tests[key].y)
        np.testing.assert_array_equal(got.u, ours.tests[key].u)
        assert info.n_init == ours.n_init and info.dt == pytest.approx(ours.dt, rel=1e-12)


def test_nonlinear_benchmarks_records_of_different_lengths_are_padded_and_masked():
    a = IOData(np.arange(5.0), np.arange(5.0) * 2, 0.1, "a", 2)
    b = IOData(np.ones((3, 1)), np.ones(3), 0.1, None, 2)
    t, info = from_nonlinear_benchmarks((a, b), with_info=True)
    assert t.y.shape == (2, 5, 1) and t.u.shape == (2, 5, 1)
    np.testing.assert_array_equal(np.asarray(t.mask)[:, :, 0], [[1] * 5, [1, 1, 1, 0, 0]])
    assert info == RecordInfo(0.1, 2, ("a", None), (5, 3))
    one = from_nonlinear_benchmarks(a)
    assert isinstance(one, Trajectories) and one.y.shape == (1, 5, 1)
    with pytest.raises(ValueError, match="disagree on `sampling_time`"):
        from_nonlinear_benchmarks([a, IOData(np.ones(3), np.ones(3), 0.2)], with_info=True)
    with pytest.raises(TypeError, match="has no `u` and `y`"):
        from_nonlinear_benchmarks([np.ones(3)])
    with pytest.raises(ValueError, match="`u` has 3 samples, `y` 2"):
        from_nonlinear_benchmarks(IOData(np.ones(3), np.ones(2)))
