"""The real datasets' files: where they are looked for, downloaded once into a user cache, checked.

On first use a loader (:func:`ceemx.datasets.cascaded_tanks`, ``silverbox``,
``coupled_electric_drives``) fetches the official archive with `pooch`_ (HTTP, retries, atomic
writes), takes the data file out of it and checks the file's sha256 against the published one
(:attr:`Source.sha256`, which the registry's entries hold); later calls read the cached file.

=========================== ================================================ ===========
name                        archive (host)                                   data file
=========================== ================================================ ===========
``cascaded_tanks``          ``CascadedTanksFiles.zip`` (4TU.ResearchData)    ``dataBenchmark.csv``
``silverbox``               ``SilverboxFiles.zip`` (nonlinearbenchmark.org,  ``SNLS80mV.csv``
                            a Google Drive file)
``coupled_electric_drives`` ``CoupledElectricDrivesDataSetAndReferenceModels ``DATAUNIF.csv``
                            .zip`` (Uppsala University)
=========================== ================================================ ===========

Where the files are looked for, first found wins: the ``root`` argument, the folder named by
``CEEMX_DATA``, the cache (``cache`` argument, else ``CEEMX_DATA_CACHE``, else the platform's cache
folder, ``~/.cache/ceemx/datasets`` on Linux: ``pooch.os_cache``), a ``../shared/data`` folder of a
development checkout — and only then the download into the cache. The cache keeps the layout of
a data folder (``cascaded_tanks/dataBenchmark.csv``, …), so it can be handed to ``root=``.

What is checked: the data file's sha256, after a download and at every use of the cache (once
per file version per process). A downloaded file that fails is removed with its archive and
raises; a cached file that fails (torn, altered) is moved aside to ``<file>.corrupt`` and fetched
again — from the cached archive, else downloaded. The archives' digests are not pinned: the
hosts re-pack them (the Silverbox archive moved twice), and the data inside is what the
published digests are of. A ``file://`` URL copies a local archive (a mirror on a shared drive;
the tests).

Without a network the loader raises :class:`DatasetUnavailable` (a ``FileNotFoundError``) with
one sentence: what could not be downloaded from where, and where to put the file by hand.

.. _pooch: https://www.fatiando.org/pooch
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urlparse

__all__ = [
    "SOURCES",
    "DatasetUnavailable",
    "Source",
    "cache_dir",
    "data_file",
    "data_root",
    "fetch",
]


class DatasetUnavailable(FileNotFoundError):
    """A dataset's file is neither on disk nor downloadable (offline, host moved)."""


@dataclass(frozen=True)
class Source:
    """Where a dataset's official file comes from.

    Attributes:
        url: the archive's address.
        archive: the archive's file name (as the host names it).
        member: the data file's name inside the archive (matched by base name, any folder).
        file: where the data file goes under a data folder (``name/file.csv``).
        sha256: the data file's published sha256.
    """

    url: str
    archive: str
    member: str
    file: str
    sha256: str


SOURCES: dict[str, Source] = {
    "cascaded_tanks": Source(
        "https://data.4tu.nl/file/d4810b78-6cdd-48fe-8950-9bd601e5f47f/"
        "3b697e42-01a4-4979-a370-813a456c36f5",
        "CascadedTanksFiles.zip",
        "dataBenchmark.csv",
        "cascaded_tanks/dataBenchmark.csv",
        "ef2388ed822f3aef4aa80d6b0f2b466dd80b361786b3eafc7a2957c31ea323a7",
    ),
    "silverbox": Source(
        "https://drive.google.com/uc?export=download&id=17iS-6oBUUgrmiAcrZoG9S5sOaljZnDSy",
        "SilverboxFiles.zip",
        "SNLS80mV.csv",
        "silverbox/SNLS80mV.csv",
        "ae62d5a91230c10f76e6dd02c8a4fac3c9d4d8a95fbf50e87cb0c4885003e0f1",
    ),
    "coupled_electric_drives": Source(
        "http://www.it.uu.se/research/publications/reports/2017-024/"
        "CoupledElectricDrivesDataSetAndReferenceModels.zip",
        "CoupledElectricDrivesDataSetAndReferenceModels.zip",
        "DATAUNIF.csv",
        "coupled_electric_drives/DATAUNIF.csv",
        "9114f637f22ca826f03f066270cf68bd8cad686739a7fa4b471c14ccdbf66889",
    ),
}


def cache_dir(cache: str | os.PathLike | None = None) -> Path:
    """The download cache: ``cache``, else ``$CEEMX_DATA_CACHE``, else the platform's cache folder.

    The platform's folder is ``pooch.os_cache("ceemx") / "datasets"`` (``~/.cache/ceemx/datasets``
    on Linux, ``~/Library/Caches/ceemx/datasets`` on macOS). Not created here.
    """
    if cache is not None:
        return Path(cache)
    env = os.environ.get("CEEMX_DATA_CACHE")
    if env:
        return Path(env)
    import pooch

    return Path(pooch.os_cache("ceemx")) / "datasets"


def sha256(path: Path) -> str:
    """The file's sha256, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


#: digests of cached files already read in this process, by (path, size, mtime)
_DIGESTS: dict[tuple[str, int, int], str] = {}


def _digest(path: Path) -> str:
    """:func:`sha256` of ``path``, read once per file version per process."""
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        _DIGESTS[key] = sha256(path)
    return _DIGESTS[key]


def _set_aside(target: Path) -> Path:
    """Move a cached data file that failed its check to ``<name>.corrupt``; return that path."""
    aside = target.with_name(target.name + ".corrupt")
    os.replace(target, aside)
    return aside


def _copy_local(fname: str, action, pooch, *, check_only: bool | None = None):
    """A pooch downloader for ``file://`` URLs (``fname``): copies the local file to ``action``.

    pooch calls a downloader with the URL, the output file (a path or an open binary file) and
    the ``Pooch`` instance (unused).
    """
    source = Path(unquote(urlparse(fname).path))
    if check_only:
        return source.is_file()
    with source.open("rb") as src:
        if isinstance(action, str | os.PathLike):
            with open(action, "wb") as dst:
                shutil.copyfileobj(src, dst)
        else:
            shutil.copyfileobj(src, action)


def _extract(archive: Path, member: str, target: Path) -> None:
    """Write ``member`` (by base name, any case) of a zip archive to ``target``, atomically."""
    with zipfile.ZipFile(archive) as z:
        found = [n for n in z.namelist() if Path(n).name.lower() == member.lower()]
        if not found:
            raise ValueError(f"{archive} holds no {member}.")
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as dst, z.open(sorted(found, key=len)[0]) as src:
            shutil.copyfileobj(src, dst)
    os.replace(tmp, target)


def fetch(
    name: str,
    *,
    cache: str | os.PathLike | None = None,
    url: str | None = None,
    progress: bool = False,
) -> Path:
    """The dataset's data file in the cache, downloaded and checked on first use.

    A cached data file whose sha256 is not the published one (a torn or altered file) is moved
    aside to ``<file>.corrupt`` and fetched again: extracted afresh from the cached archive, and
    where that gives the wrong file too, from a new download.

    Args:
        name: a key of :data:`SOURCES`.
        cache: the cache folder (see :func:`cache_dir`).
        url: another address of the same archive (a mirror; ``file://`` copies a local file).
        progress: show pooch's progress bar.

    Returns:
        The path of the data file, ``cache_dir(cache) / SOURCES[name].file``, its sha256 checked.

    Raises:
        ValueError: an unknown name; the archive is not a zip holding the data file; the data
            file's sha256 is not the published one (the file and the archive are removed).
        DatasetUnavailable: the archive could not be downloaded (offline, the host moved); one
            sentence, which also says when a corrupt cached file was set aside.
    """
    if name not in SOURCES:
        raise ValueError(f"unknown dataset {name!r}; choose from {', '.join(SOURCES)}.")
    src = SOURCES[name]
    folder = cache_dir(cache)
    target = folder / src.file
    corrupt = None
    if target.is_file():
        if _digest(target) == src.sha256:
            return target
        corrupt = _set_aside(target)
    url = src.url if url is None else url
    cached_archive = folder / "archives" / src.archive
    for _ in range(2):  # a cached archive, then (if it holds another file) a new download
        downloaded = not cached_archive.is_file()
        archive = _retrieve(name, src, url, folder, target, progress, corrupt)
        try:
            _extract(archive, src.member, target)
        except (zipfile.BadZipFile, ValueError) as e:
            archive.unlink(missing_ok=True)
            raise ValueError(
                f"the file downloaded from {url} is not the {name} archive ({e}); the host may "
                f"have moved it: pass `url=` or put {src.member} at {target} by hand."
            ) from None
        digest = sha256(target)
        if digest == src.sha256:
            return target
        target.unlink()
        archive.unlink(missing_ok=True)  # the next attempt downloads it afresh
        if downloaded:
            raise ValueError(
                f"sha256 of the {src.member} downloaded from {url} is {digest}; expected "
                f"{src.sha256} (the published {name} file). It was removed; the host may serve "
                "another version."
            )
    raise AssertionError("unreachable: the second attempt downloads")  # pragma: no cover


def _retrieve(name: str, src: Source, url: str, folder: Path, target: Path, progress, corrupt):
    """The archive, from the cache or downloaded by pooch; offline: one sentence."""
    import pooch

    logger = pooch.get_logger()  # its "use this known_hash" advice is not for our users
    level = logger.level
    logger.setLevel("WARNING")
    try:
        return Path(
            pooch.retrieve(
                url,
                known_hash=None,  # the data file's digest is checked by fetch (module notes)
                fname=src.archive,
                path=folder / "archives",
                downloader=_copy_local if url.startswith("file://") else None,
                progressbar=progress,
            )
        )
    except Exception as e:  # offline, refused, moved: one sentence says what to do
        why = f"{type(e).__name__}: {e}".replace(". ", "; ").rstrip(".")
        what = (
            f"The cached {src.member} of the {name} dataset failed its sha256 check (moved to "
            f"{corrupt}) and could not be downloaded again"
            if corrupt is not None
            else f"Could not download the {name} dataset"
        )
        raise DatasetUnavailable(
            f"{what} ({src.archive}) from {url} ({why}); download it by hand and put its "
            f"{src.member} at {target} (or under a folder named by the CEEMX_DATA environment "
            f"variable, as {src.file})."
        ) from None
    finally:
        logger.setLevel(level)


def _checkout_folders() -> list[Path]:
    """``../shared/data`` of a development checkout: from the working directory and the repo."""
    repo = Path(__file__).resolve().parents[3]
    return [Path.cwd() / ".." / "shared" / "data", repo / ".." / "shared" / "data"]


def data_root(root: str | os.PathLike | None = None) -> Path:
    """The folder holding the datasets' files.

    Args:
        root: a folder to use; ``None`` tries ``$CEEMX_DATA``, then ``../shared/data`` relative to
            the working directory and to the repository.

    Returns:
        The first candidate folder that exists, resolved.

    Raises:
        FileNotFoundError: naming every folder tried.
    """
    env = os.environ.get("CEEMX_DATA")
    tried = [Path(root)] if root is not None else [Path(env)] if env else _checkout_folders()
    for p in tried:
        if p.is_dir():
            return p.resolve()
    raise FileNotFoundError(
        "data folder not found; tried "
        + ", ".join(str(p) for p in tried)
        + ". Pass `root=` or set CEEMX_DATA to a folder holding cascaded_tanks/, silverbox/ and "
        "coupled_electric_drives/ with the official files."
    )


def data_file(
    name: str,
    root: str | os.PathLike | None = None,
    *,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> Path:
    """Where a dataset's official file is, downloading it into the cache on first use.

    Looked for in ``root``, else ``$CEEMX_DATA`` (either one given: the file must be there),
    else the cache (:func:`cache_dir`), else ``../shared/data`` of a development checkout; else
    downloaded into the cache and checked (:func:`fetch`).

    Args:
        name: ``"cascaded_tanks"``, ``"silverbox"`` or ``"coupled_electric_drives"``.
        root: the data folder (see :func:`data_root`).
        cache: the download cache (``None``: ``$CEEMX_DATA_CACHE`` or the platform's cache).
        download: allow the download (``False``: only files already on disk).

    Returns:
        The file's path (a cached file's sha256 checked here — a corrupt one fetched again —,
        the others' by the loaders).

    Raises:
        ValueError: for an unknown name.
        FileNotFoundError: the file is not under ``root`` / ``$CEEMX_DATA``; or
            :class:`DatasetUnavailable` (a ``FileNotFoundError``) when it is nowhere on disk and
            cannot be downloaded — one sentence saying where to put it.
    """
    if name not in SOURCES:
        raise ValueError(f"unknown dataset {name!r}; choose from {', '.join(SOURCES)}.")
    file = SOURCES[name].file
    if root is not None or os.environ.get("CEEMX_DATA"):
        try:
            path = data_root(root) / file
        except FileNotFoundError as e:
            raise FileNotFoundError(f"{name}: cannot look for {file}: {e}") from None
        if not path.is_file():
            raise FileNotFoundError(
                f"missing data file {path}: the {name} dataset needs the official {file} under "
                f"the data folder. Pass `root=` (the folder holding {file.split('/')[0]}/) or "
                "set the CEEMX_DATA environment variable to it; with neither, the loaders "
                "download it into a user cache."
            )
        return path
    cached = cache_dir(cache) / file
    if cached.is_file():
        if download:
            return fetch(name, cache=cache)  # checked; a corrupt file fetched again
        if _digest(cached) != SOURCES[name].sha256:
            raise DatasetUnavailable(
                f"the cached {name} data file {cached} failed its sha256 check and "
                "download=False: allow the download to fetch it again, or put the official "
                f"file there or under a folder named by CEEMX_DATA (as {file})."
            )
        return cached
    for folder in _checkout_folders():
        if (folder / file).is_file():
            return (folder / file).resolve()
    if not download:
        raise DatasetUnavailable(
            f"the {name} data file is not on disk (looked for {cached}) and download=False: "
            "allow the download, or put the official file there or under a folder named by "
            f"CEEMX_DATA (as {file})."
        )
    return fetch(name, cache=cache)
