"""Save an identified model and load it in another process: :func:`save`, :func:`load`.

A model file is a ZIP archive of two members:

- ``model.json`` — the format number, what the model is (:class:`ModelInfo`: class, ceemx and
  JAX versions, dtype, dimensions, noise, the data's :class:`~ceemx.data.info.DataInfo`, the
  fit's one-line summary), the model's structure (:mod:`ceemx.infra.structure`: classes by import
  path, static fields, the shape and dtype of every array) and the sha256 of the leaves;
- ``leaves.eqx`` — the arrays, by ``eqx.tree_serialise_leaves``.

:func:`load` rebuilds a skeleton of the model from the structure (the classes imported by their
import path, instances made without running ``__init__``) and reads the arrays into it with
``eqx.tree_deserialise_leaves``. The class must therefore be importable where the model is
loaded: a class defined in a module on the path (``mymodels.py``, a package) loads anywhere; one
defined in a script or notebook (``__main__``) loads only where ``__main__`` defines it again
(:func:`save` warns). Trust model: loading imports the modules the file names — running their
top-level code, as ``import`` does — and calls no other function named in the file; arrays are
read by NumPy without pickle. Load files you trust, as you would import a module you trust.

The file is written to a temporary name beside ``path`` and moved into place
(:func:`ceemx.infra.checkpoint.atomic_write`): a crash leaves the previous file or the new one.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import io
import json
import os
import pathlib
import platform
import zipfile
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import equinox as eqx
import jax
import numpy as np

from ceemx.data.info import DataInfo
from ceemx.data.trajectories import Trajectories
from ceemx.infra.checkpoint import atomic_write, load_leaf
from ceemx.infra.json_values import from_json, to_json
from ceemx.infra.structure import NameNotFound, StructureError, describe, rebuild
from ceemx.infra.warn import warn
from ceemx.models.system import AbstractSystem, float_dtype

__all__ = ["ModelInfo", "load", "save"]

_FORMAT = 1
_META = "model.json"
_LEAVES = "leaves.eqx"


@dataclasses.dataclass(frozen=True)
class ModelInfo:
    """What a model file says about its model (``ceemx.load(path, with_info=True)``).

    Attributes:
        model: the model's class, ``module:QualName``.
        ceemx_version: the version of ceemx that saved it.
        versions: the versions of JAX, Equinox, NumPy and Python that saved it.
        dtype: the dtype of the model's parameters (``float64`` or ``float32``).
        state_dim: n.
        obs_dim: m.
        input_dim: p.
        noise: ``{"process_noise": …, "obs_noise": …}`` in words with their scales.
        data: the :class:`~ceemx.data.info.DataInfo` of the data it was fitted to or given with
            it (sample time, channel names and units), or ``None``.
        fit: the fit's summary (``repr`` of the :class:`ceemx.FitResult`: solver, convergence,
            J, the first parameters), or ``None`` for a model saved without a fit.
        saved_at: when it was saved (UTC, ISO 8601).
    """

    model: str
    ceemx_version: str
    versions: dict[str, str]
    dtype: str
    state_dim: int
    obs_dim: int
    input_dim: int
    noise: dict[str, str]
    data: DataInfo | None
    fit: str | None
    saved_at: str

    def __str__(self) -> str:
        """A few lines: class, dimensions, dtype, noise, data, fit, versions."""
        lines = [
            f"ceemx model {self.model} (n = {self.state_dim}, m = {self.obs_dim}, "
            f"p = {self.input_dim}, {self.dtype}), saved {self.saved_at} by ceemx "
            f"{self.ceemx_version}",
            *(f"  {k}: {v}" for k, v in self.noise.items()),
        ]
        if self.data is not None:
            d = self.data
            text = f"  data: dt = {d.dt} {d.time_unit}; outputs "
            text += ", ".join(d.output_labels(self.obs_dim))
            if self.input_dim:
                text += "; inputs " + ", ".join(d.input_labels(self.input_dim))
            lines.append(text)
        if self.fit is not None:
            lines.append("  fit: " + self.fit.replace("\n", "\n  "))
        return "\n".join(lines)


def _version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return "0+unknown"


def _describe_noise(noise) -> str:
    if noise is None:
        return "none"
    values = noise.describe()
    parts = [type(noise).__name__]
    for k, v in values.items():
        a = np.atleast_1d(np.asarray(v, np.float64)).reshape(-1)
        parts.append(f"{k} " + ", ".join(f"{x:.4g}" for x in a[:6]) + (" …" if a.size > 6 else ""))
    return ", ".join(parts)


def _is_fit_result(model: Any) -> bool:
    return all(hasattr(model, a) for a in ("system", "solver", "history", "converged"))


def _data_info(model: Any, data: Trajectories | DataInfo | None) -> DataInfo | None:
    if isinstance(data, Trajectories):
        return data.info
    if data is None or isinstance(data, DataInfo):
        if data is None and _is_fit_result(model) and getattr(model, "problem", None) is not None:
            return getattr(model.problem.data, "info", None)
        return data
    raise TypeError(f"`data` must be Trajectories, a DataInfo or None; got {type(data).__name__}.")


def _warn_main(spec: Any) -> None:
    """Warn when the model's classes live in ``__main__`` (a script or notebook)."""
    text = json.dumps(spec)
    if '"__main__:' in text:
        warn(
            "the model's class is defined in a script or notebook (__main__): another process "
            "can load the file only where __main__ defines the same class. Define the class in a "
            "module on the path (e.g. mymodels.py) to load it anywhere."
        )


def _model_info(model: Any, system: AbstractSystem, model_class: str, data) -> ModelInfo:
    """The :class:`ModelInfo` of ``system`` (saved from ``model``, a system or a fit result)."""
    return ModelInfo(
        model=model_class,
        ceemx_version=_version("ceemx"),
        versions={
            "jax": jax.__version__,
            "equinox": _version("equinox"),
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
        dtype=np.dtype(float_dtype(system)).name,
        state_dim=int(system.state_dim),
        obs_dim=int(system.obs_dim),
        input_dim=int(system.input_dim),
        noise={
            "process_noise": _describe_noise(system.process_noise),
            "obs_noise": _describe_noise(system.obs_noise),
        },
        data=_data_info(model, data),
        fit=repr(model) if _is_fit_result(model) else None,
        saved_at=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    )


def save(
    path: str | os.PathLike,
    model: Any,
    *,
    data: Trajectories | DataInfo | None = None,
) -> pathlib.Path:
    """Save an identified model (or a whole fit's model and summary) to one file.

    Args:
        path: the file to write (its folder must exist; ``.ceemx`` is a good suffix). An
            existing file is replaced atomically.
        model: a :class:`ceemx.AbstractSystem`, or a :class:`ceemx.FitResult` (its ``system``
            is saved, with its one-line summary and its data's metadata).
        data: the data whose :class:`~ceemx.data.info.DataInfo` (sample time, names, units) to
            record with the model (default: a fit result's data).

    Returns:
        The path written.

    Raises:
        TypeError: ``model`` is neither a system nor a fit result; ``data`` of the wrong type.
        ValueError: a part of the model that cannot be saved (naming its field: a lambda, a
            class defined inside a function, an object that is neither array, number, string,
            container, module nor named function).
        OSError: the file cannot be written (the previous file, if any, is kept).

    Example:
        >>> ceemx.save("tanks.ceemx", result)  # doctest: +SKIP
        >>> model = ceemx.load("tanks.ceemx")  # doctest: +SKIP
    """
    system = model.system if _is_fit_result(model) else model
    if not isinstance(system, AbstractSystem):
        raise TypeError(
            f"`model` must be a ceemx.AbstractSystem or a ceemx.FitResult; got "
            f"{type(model).__name__}."
        )
    try:
        spec = describe(system)
        skeleton = rebuild(spec)
    except StructureError as err:
        raise ValueError(f"cannot save this model: {err}") from err
    if jax.tree_util.tree_structure(skeleton) != jax.tree_util.tree_structure(system):
        raise ValueError(  # a value the structure does not capture: refuse rather than mis-save
            "cannot save this model: its structure does not rebuild to the same pytree "
            f"({jax.tree_util.tree_structure(system)})."
        )
    _warn_main(spec)
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, system)
    leaves = buffer.getvalue()
    info = _model_info(model, system, spec["$module"], data)
    info_json = dataclasses.asdict(info)
    info_json["data"] = None if info.data is None else info.data.to_dict()
    meta = {
        "format": _FORMAT,
        "info": info_json,
        "structure": spec,
        "leaves_sha256": hashlib.sha256(leaves).hexdigest(),
    }

    def write(f):
        with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_DEFLATED) as z:
            z.writestr(_META, to_json(meta, indent=1))
            z.writestr(_LEAVES, leaves)

    target = pathlib.Path(path)
    atomic_write(os.fspath(target), write)
    return target


def _read(path: pathlib.Path) -> tuple[dict, bytes]:
    if not path.is_file():
        raise FileNotFoundError(f"no model file {os.fspath(path)!r}.")
    try:
        with zipfile.ZipFile(path) as z:
            meta = from_json(z.read(_META))
            leaves = z.read(_LEAVES)
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError) as err:
        raise ValueError(
            f"{os.fspath(path)!r} is not a ceemx model file (written by ceemx.save): {err}"
        ) from None
    if not isinstance(meta, dict) or "structure" not in meta:
        raise ValueError(f"{os.fspath(path)!r} is not a ceemx model file (written by ceemx.save).")
    if meta.get("format") != _FORMAT:
        raise ValueError(
            f"{os.fspath(path)!r} has model file format {meta.get('format')!r}; this ceemx reads "
            f"format {_FORMAT} (saved by ceemx {meta.get('info', {}).get('ceemx_version')})."
        )
    if hashlib.sha256(leaves).hexdigest() != meta.get("leaves_sha256"):
        raise ValueError(f"{os.fspath(path)!r} is corrupt: its arrays do not match their sha256.")
    return meta, leaves


def _check_dtypes(skeleton: Any, path: pathlib.Path) -> None:
    """Refuse a float64 model where JAX would read it as float32 (x64 disabled)."""
    if jax.config.read("jax_enable_x64"):
        return
    for leaf in jax.tree_util.tree_leaves(skeleton):
        if isinstance(leaf, jax.ShapeDtypeStruct) and np.dtype(leaf.dtype).itemsize == 8:
            raise ValueError(
                f"{os.fspath(path)!r} holds a {np.dtype(leaf.dtype).name} model, which JAX would "
                "read as 32-bit here (x64 is disabled): enable it first, "
                "jax.config.update('jax_enable_x64', True)."
            )


def _check_leaves(loaded: Any, skeleton: Any) -> None:
    for got, want in zip(
        jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(skeleton), strict=True
    ):
        if isinstance(want, jax.ShapeDtypeStruct | np.ndarray) and (
            np.shape(got) != want.shape or np.dtype(got.dtype) != np.dtype(want.dtype)
        ):
            raise ValueError(
                f"a saved array is {np.dtype(got.dtype).name}{list(np.shape(got))} where the "
                f"structure says {np.dtype(want.dtype).name}{list(want.shape)}: corrupt file."
            )


def load(path: str | os.PathLike, *, with_info: bool = False) -> Any:
    """Load a model saved by :func:`save` (in this process or another).

    Args:
        path: the model file.
        with_info: also return its :class:`ModelInfo`.

    Returns:
        The model (the saved :class:`ceemx.AbstractSystem`, equal leaf for leaf to the one
        saved: same classes, static fields, values, shapes and dtypes; a weakly typed scalar,
        e.g. a noise scale given as a Python float, comes back strongly typed), or
        ``(model, info)`` with ``with_info``.

    Raises:
        FileNotFoundError: no such file.
        ImportError: the model's class (or a module it needs) cannot be imported here: the
            message names the class path and how to make it importable.
        ValueError: not a model file, another format, a corrupt file, a class whose fields
            changed since the save, or a float64 model with JAX's x64 disabled.

    Loading imports the modules the file names (module notes: trust model).

    Example:
        >>> model, info = ceemx.load("tanks.ceemx", with_info=True)  # doctest: +SKIP
        >>> print(info)  # doctest: +SKIP
    """
    path = pathlib.Path(path)
    meta, leaves = _read(path)
    model_class = meta.get("info", {}).get("model", "?")
    try:
        skeleton = rebuild(meta["structure"])
    except NameNotFound as err:
        module = model_class.partition(":")[0]
        where = "a script or notebook (__main__)" if module == "__main__" else f"module {module!r}"
        raise ImportError(
            f"cannot load {os.fspath(path)!r}: {err}. The model class {model_class} is "
            f"defined in {where}; make that module importable here (install it, put its "
            "folder on PYTHONPATH or sys.path, or import it first) and load again."
        ) from err
    except StructureError as err:
        raise ValueError(f"cannot load {os.fspath(path)!r}: {err}") from err
    _check_dtypes(skeleton, path)
    system = eqx.tree_deserialise_leaves(io.BytesIO(leaves), skeleton, filter_spec=load_leaf)
    _check_leaves(system, skeleton)
    if not with_info:
        return system
    values = dict(meta["info"])
    values["data"] = None if values.get("data") is None else DataInfo.from_dict(values["data"])
    return system, ModelInfo(**values)
