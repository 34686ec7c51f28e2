"""The paper's normalised Stanford helicopter dataset (Zenodo record 3662987), read from disk.

Layout of the published ``datasets.zip`` (Menda et al., "Normalized Stanford helicopter dataset",
2020, https://doi.org/10.5281/zenodo.3662987)::

    split_normalized/
        statistics.pt           (data_mean, data_std, controls_mean, controls_std)
        train/*.pt  valid/*.pt  test/*.pt

Each trajectory file holds a tuple ``(time, data, controls)`` of torch tensors: ``time`` (T,),
``data`` (T, D) and ``controls`` (T, 4). The authors' loader (``ceem/data_utils.py`` in
sisl/CEEM) takes the last six columns of ``data`` as the targets y (accelerations), and builds the
inputs u from the four controls followed by ``data[:, 7:-6]`` (measured velocities and rates); the
first seven columns of ``data`` are not used. The statistics follow the same slicing. The files
are already normalised; the statistics map back to physical units.

torch is needed only to read the files: ``pip install 'ceemx[torch]'``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ceemx.data.trajectories import Trajectories

__all__ = ["SPLITS", "HelicopterData", "load_helicopter", "normalise_splits"]

SPLITS = ("train", "valid", "test")


@dataclass(frozen=True)
class HelicopterData:
    """Normalised train/valid/test trajectories of a helicopter(-like) dataset.

    Attributes:
        train: normalised training trajectories, y (B, T, 6) and u (B, T, 10).
        valid: normalised validation trajectories.
        test: normalised test trajectories.
        train_names: one name per training trajectory (file stem, or flight and chunk).
        valid_names: one name per validation trajectory.
        test_names: one name per test trajectory.
        y_mean: (6,) mean of y in physical units; physical y = y_mean + y_std * y.
        y_std: (6,) standard deviation of y.
        u_mean: (10,) mean of u.
        u_std: (10,) standard deviation of u.
        dt: sample period [s].
        source: where the data came from, in words.
    """

    train: Trajectories
    valid: Trajectories
    test: Trajectories
    train_names: tuple[str, ...]
    valid_names: tuple[str, ...]
    test_names: tuple[str, ...]
    y_mean: np.ndarray
    y_std: np.ndarray
    u_mean: np.ndarray
    u_std: np.ndarray
    dt: float
    source: str


def _std(x: np.ndarray) -> np.ndarray:
    s = x.std(axis=(0, 1))
    return np.where(s > 0, s, 1.0)


def normalise_splits(
    parts: Sequence[tuple[np.ndarray, np.ndarray, tuple[str, ...]]], *, dt: float, source: str
) -> HelicopterData:
    """Normalise raw (u, y, names) splits with the first (training) split's statistics.

    Args:
        parts: three ``(u (B, T, p), y (B, T, m), names)`` in the order train, valid, test.
        dt: sample period [s].
        source: description stored in the result.

    Returns:
        The :class:`HelicopterData`; a channel with zero training variance gets std 1.
    """
    u_tr, y_tr = np.asarray(parts[0][0], np.float64), np.asarray(parts[0][1], np.float64)
    u_mean, u_std = u_tr.mean(axis=(0, 1)), _std(u_tr)
    y_mean, y_std = y_tr.mean(axis=(0, 1)), _std(y_tr)
    trajs = [
        Trajectories(
            (np.asarray(y, np.float64) - y_mean) / y_std,
            (np.asarray(u, np.float64) - u_mean) / u_std,
        )
        for u, y, _ in parts
    ]
    return HelicopterData(
        train=trajs[0],
        valid=trajs[1],
        test=trajs[2],
        train_names=tuple(parts[0][2]),
        valid_names=tuple(parts[1][2]),
        test_names=tuple(parts[2][2]),
        y_mean=y_mean,
        y_std=y_std,
        u_mean=u_mean,
        u_std=u_std,
        dt=dt,
        source=source,
    )


def _import_torch():
    try:
        import torch  # pyright: ignore[reportMissingImports]
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "reading the helicopter dataset's .pt files needs torch: pip install 'ceemx[torch]'"
        ) from e
    return torch


def _to_numpy(t) -> np.ndarray:
    return np.asarray(t.detach().cpu().numpy() if hasattr(t, "detach") else t, np.float64)


def _load(torch, path: Path):
    return torch.load(path, map_location="cpu", weights_only=True)


def _stack(arrays: list[np.ndarray], what: str, folder: Path):
    """Stack (T_i, k) arrays; pad shorter ones with zeros and a False mask."""
    T = max(a.shape[0] for a in arrays)
    widths = {a.shape[1] for a in arrays}
    if len(widths) != 1:
        raise ValueError(f"{folder}: the {what} of the files have different widths {widths}.")
    out = np.zeros((len(arrays), T, widths.pop()))
    mask = np.zeros((len(arrays), T), bool)
    for i, a in enumerate(arrays):
        out[i, : a.shape[0]] = a
        mask[i, : a.shape[0]] = True
    return out, mask


def _read_split(torch, folder: Path):
    if not folder.is_dir():
        raise FileNotFoundError(f"missing split folder {folder}.")
    files = sorted(f for f in folder.glob("*.pt") if not f.name.startswith("."))
    if not files:
        raise FileNotFoundError(f"no .pt trajectory files in {folder}.")
    us, ys = [], []
    for f in files:
        item = _load(torch, f)
        if not isinstance(item, (tuple, list)) or len(item) != 3:
            raise ValueError(f"{f}: expected a tuple (time, data, controls); got {type(item)}.")
        _, data, controls = (_to_numpy(x) for x in item)
        if data.ndim != 2 or controls.ndim != 2 or data.shape[0] != controls.shape[0]:
            raise ValueError(
                f"{f}: expected data (T, D) and controls (T, 4) with the same T; got "
                f"{data.shape} and {controls.shape}."
            )
        if data.shape[1] < 14:
            raise ValueError(f"{f}: data has {data.shape[1]} columns; expected at least 14.")
        us.append(np.concatenate([controls, data[:, 7:-6]], axis=1))
        ys.append(data[:, -6:])
    u, mask = _stack(us, "inputs", folder)
    y, _ = _stack(ys, "outputs", folder)
    traj = Trajectories(y, u, mask if not mask.all() else None)
    return traj, tuple(f.stem for f in files)


def load_helicopter(root: str | Path) -> HelicopterData:
    """Read the paper's normalised helicopter dataset (Zenodo 3662987) from ``root``.

    Args:
        root: the folder holding ``split_normalized/``, or ``split_normalized`` itself.

    Returns:
        A :class:`HelicopterData`: the trajectories as stored (already normalised), files in
        sorted order, inputs u = (4 controls, ``data[:, 7:-6]``) and outputs y = ``data[:, -6:]``,
        the statistics in the same slicing, ``dt = 0.02``. Trajectories of unequal length are
        zero-padded and masked.

    Raises:
        ImportError: when torch is missing (``pip install 'ceemx[torch]'``).
        FileNotFoundError: for a missing folder, split folder, ``statistics.pt`` or an empty split.
        ValueError: for files that do not hold what the layout above says.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"helicopter dataset folder {root} does not exist.")
    folder = root if (root / "statistics.pt").exists() else root / "split_normalized"
    if not folder.is_dir():
        raise FileNotFoundError(
            f"{root} holds neither `split_normalized/` nor `statistics.pt`; download "
            "datasets.zip from https://doi.org/10.5281/zenodo.3662987 and unzip it there."
        )
    stats_file = folder / "statistics.pt"
    if not stats_file.exists():
        raise FileNotFoundError(f"missing {stats_file}.")
    torch = _import_torch()
    stats = _load(torch, stats_file)
    if not isinstance(stats, (tuple, list)) or len(stats) != 4:
        raise ValueError(
            f"{stats_file}: expected (data_mean, data_std, controls_mean, controls_std)."
        )
    d_mean, d_std, c_mean, c_std = (_to_numpy(x).reshape(-1) for x in stats)
    splits = [_read_split(torch, folder / s) for s in SPLITS]
    return HelicopterData(
        train=splits[0][0],
        valid=splits[1][0],
        test=splits[2][0],
        train_names=splits[0][1],
        valid_names=splits[1][1],
        test_names=splits[2][1],
        y_mean=d_mean[-6:],
        y_std=d_std[-6:],
        u_mean=np.concatenate([c_mean, d_mean[7:-6]]),
        u_std=np.concatenate([c_std, d_std[7:-6]]),
        dt=0.02,
        source=f"Stanford helicopter dataset (Zenodo 3662987) from {folder}",
    )
