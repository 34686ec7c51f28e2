"""The structure of an Equinox module as JSON, and the skeleton it rebuilds (for saved models).

A saved model (:func:`ceemx.save`) is two parts: its array leaves, written by
``eqx.tree_serialise_leaves``, and the rest of it — classes, static fields, numbers, strings,
functions — written here as JSON (:func:`describe`). Loading rebuilds a *skeleton* from the
JSON (:func:`rebuild`): the same classes with the same static fields and, in place of every array,
a ``jax.ShapeDtypeStruct`` (a ``np.ndarray`` of zeros for NumPy leaves), into which
``eqx.tree_deserialise_leaves`` reads the arrays.

What is written (every value is one of these, else :class:`StructureError` names its path):

- ``None``, booleans, integers, floats (inf and NaN included), strings: as JSON values;
- arrays (JAX or NumPy): shape and dtype (their values go with the leaves; an array in a static
  field, which is no leaf, is written with its values);
- tuples, lists and dicts with string keys;
- Equinox modules, dataclasses and named tuples: the class by import path and each field;
- functions, classes and other objects that a module holds under a name (``jnp.tanh``,
  ``jax.nn.relu``, Equinox's identity): by import path; ``functools.partial`` of those; enum
  members; dtypes.

Trust model: :func:`rebuild` imports the modules the JSON names (which runs their top-level code,
as ``import`` does), looks names up in them, and creates instances of the named classes without
calling their ``__init__`` (fields are set as they were saved; named tuples and partials are
built from saved values). It calls no other function named in the file. A model file is still
code-adjacent: load files you trust, as you would import a module you trust.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import importlib
import math
from typing import Any

import equinox as eqx
import jax
import numpy as np

__all__ = ["NameNotFound", "StructureError", "describe", "import_path", "rebuild", "resolve"]


class StructureError(ValueError):
    """A value that cannot be written as structure, or a structure that cannot be rebuilt."""


class NameNotFound(StructureError, ImportError):
    """A module or a name in it, named by a saved structure, that cannot be imported here."""


def import_path(obj: Any) -> str:
    """``module:qualified.name`` of a named object, checked to resolve back to ``obj`` itself.

    Looks for the object under its ``__qualname__`` in its ``__module__``, else under any name in
    that module (an object assigned to a module-level name, e.g. a lambda).

    Raises:
        StructureError: for an object that no module holds under a name (a lambda or a class
            defined inside a function).
    """
    module = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None) or getattr(obj, "__name__", None)
    if not isinstance(module, str):
        raise StructureError(f"{obj!r} has no module to import it from.")
    if isinstance(qualname, str) and "<" not in qualname:
        try:
            if resolve(f"{module}:{qualname}") is obj:
                return f"{module}:{qualname}"
        except StructureError:
            pass
    try:
        found = [k for k, v in vars(importlib.import_module(module)).items() if v is obj]
    except ImportError:
        found = []
    if found:
        return f"{module}:{sorted(found)[0]}"
    raise StructureError(
        f"{obj!r} cannot be found by name in its module {module!r} (a lambda, or something "
        "defined inside a function): define it at the top level of a module."
    )


def resolve(path: str) -> Any:
    """The object at ``module:qualified.name`` (imports the module).

    Raises:
        NameNotFound: naming the path, when the module cannot be imported or has no such name
            (the import error as the cause); an ``ImportError`` and a :class:`StructureError`.
    """
    module, _, qualname = path.partition(":")
    try:
        obj: Any = importlib.import_module(module)
    except Exception as err:  # an ImportError, or the module's own code failing
        raise NameNotFound(
            f"cannot import module {module!r} (for {path!r}): {type(err).__name__}: {err}"
        ) from err
    for part in qualname.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise NameNotFound(f"module {module!r} has no {qualname!r} (for {path!r}).") from None
    return obj


def _float(x: float) -> Any:
    return x if math.isfinite(x) else {"$float": repr(x)}


def describe(tree: Any, path: str = "") -> Any:
    """The structure of ``tree`` as JSON-serialisable values (module notes).

    Args:
        tree: an Equinox module (or any value the notes list).
        path: the name of ``tree`` in messages.

    Raises:
        StructureError: naming the path of the first value that cannot be written.
    """
    return _describe(tree, path or "model", static=False)


def _fields(obj: Any, path: str) -> dict[str, Any]:
    """The fields the instance holds (a field left at a class-level default is not one)."""
    held = vars(obj) if hasattr(obj, "__dict__") else None
    out = {}
    for f in dataclasses.fields(obj):
        if held is not None and f.name not in held:
            continue
        static = bool(f.metadata.get("static", False))
        out[f.name] = _describe(getattr(obj, f.name), f"{path}.{f.name}", static=static)
    return out


def _describe(x: Any, path: str, *, static: bool) -> Any:  # noqa: C901 - one case per kind
    if x is None or isinstance(x, (bool, str)):
        return x
    if isinstance(x, int) and not isinstance(x, enum.Enum):
        return x
    if isinstance(x, float):
        return _float(x)
    if isinstance(x, (jax.Array, np.ndarray, np.generic)):
        kind = "numpy" if isinstance(x, (np.ndarray, np.generic)) else "jax"
        if isinstance(x, np.generic):
            kind = "numpy-scalar"
        spec = {"$array": kind, "shape": list(np.shape(x)), "dtype": np.dtype(x.dtype).name}
        if static:  # not a leaf: its values are not serialised with the leaves
            spec["values"] = np.asarray(x).tolist()
        return spec
    if isinstance(x, enum.Enum):
        return {"$enum": import_path(type(x)), "name": x.name}
    if isinstance(x, np.dtype):
        return {"$dtype": x.name}
    if isinstance(x, eqx.Module) or (dataclasses.is_dataclass(x) and not isinstance(x, type)):
        kind = "$module" if isinstance(x, eqx.Module) else "$dataclass"
        return {kind: _class_path(type(x), path), "fields": _fields(x, path)}
    if isinstance(x, tuple) and hasattr(type(x), "_fields"):  # a named tuple
        values = {
            k: _describe(getattr(x, k), f"{path}.{k}", static=static)
            for k in type(x)._fields  # pyright: ignore[reportAttributeAccessIssue]
        }
        return {"$namedtuple": _class_path(type(x), path), "fields": values}
    if isinstance(x, (tuple, list)):
        key = "$tuple" if isinstance(x, tuple) else "$list"
        return {key: [_describe(v, f"{path}[{i}]", static=static) for i, v in enumerate(x)]}
    if isinstance(x, dict):
        if not all(isinstance(k, str) for k in x):
            raise StructureError(f"{path}: a dict with non-string keys cannot be saved.")
        return {"$dict": {k: _describe(v, f"{path}[{k!r}]", static=static) for k, v in x.items()}}
    if isinstance(x, functools.partial):
        return {
            "$partial": _describe(x.func, f"{path}.func", static=True),
            "args": [_describe(a, f"{path}.args", static=True) for a in x.args],
            "keywords": {k: _describe(v, path, static=True) for k, v in x.keywords.items()},
        }
    if callable(x) or isinstance(x, type):
        try:
            return {"$ref": import_path(x)}
        except StructureError as err:
            raise StructureError(f"{path}: {err}") from None
    raise StructureError(
        f"{path}: a {type(x).__name__} cannot be saved (saved are arrays, numbers, strings, "
        "tuples, lists, dicts, Equinox modules, dataclasses, named tuples and named functions)."
    )


def _class_path(cls: type, path: str) -> str:
    if "<locals>" in cls.__qualname__:
        raise StructureError(
            f"{path}: class {cls.__qualname__} is defined inside a function; define it at the top "
            "level of a module to save it."
        )
    try:
        return import_path(cls)
    except StructureError as err:
        raise StructureError(f"{path}: {err}") from None


def rebuild(spec: Any) -> Any:
    """The skeleton that :func:`describe`'s output describes (module notes).

    Arrays become ``jax.ShapeDtypeStruct`` (NumPy arrays: zeros of their shape and dtype) unless
    their values were written; everything else is rebuilt as it was.

    Raises:
        StructureError: a module or name that cannot be imported, or a class whose fields are
            not the saved ones (the class changed since the save).
    """
    if spec is None or isinstance(spec, (bool, int, float, str)):
        return spec
    if not isinstance(spec, dict) or not spec:
        raise StructureError(f"not a saved structure: {spec!r}.")
    key = next(iter(spec))
    if key == "$float":
        return float(spec["$float"])
    if key == "$array":
        return _array(spec)
    if key in ("$tuple", "$list"):
        items = [rebuild(v) for v in spec[key]]
        return tuple(items) if key == "$tuple" else items
    if key == "$dict":
        return {k: rebuild(v) for k, v in spec["$dict"].items()}
    if key == "$ref":
        return resolve(spec["$ref"])
    if key == "$dtype":
        return np.dtype(spec["$dtype"])
    if key == "$enum":
        return resolve(spec["$enum"])[spec["name"]]
    if key == "$partial":
        args = [rebuild(a) for a in spec["args"]]
        return functools.partial(rebuild(spec["$partial"]), *args, **_items(spec["keywords"]))
    if key == "$namedtuple":
        return resolve(spec["$namedtuple"])(**_items(spec["fields"]))
    if key in ("$module", "$dataclass"):
        return _instance(spec[key], _items(spec["fields"]))
    raise StructureError(f"unknown saved structure {key!r}.")


def _items(specs: dict) -> dict[str, Any]:
    return {k: rebuild(v) for k, v in specs.items()}


def _array(spec: dict) -> Any:
    dtype = np.dtype(spec["dtype"])
    shape = tuple(spec["shape"])
    if "values" in spec:
        values = np.asarray(spec["values"], dtype).reshape(shape)
        if spec["$array"] == "jax":
            return jax.numpy.asarray(values)
        return values[()] if spec["$array"] == "numpy-scalar" else values
    if spec["$array"] == "jax":
        return jax.ShapeDtypeStruct(shape, dtype)
    if spec["$array"] == "numpy-scalar":
        return dtype.type(0)
    return np.zeros(shape, dtype)


def _instance(path: str, fields: dict[str, Any]) -> Any:
    """An instance of the class at ``path`` with ``fields``, built without its ``__init__``."""
    cls = resolve(path)
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise StructureError(f"{path!r} is not a dataclass or Equinox module.")
    names = {f.name for f in dataclasses.fields(cls)}
    extra = sorted(set(fields) - names)
    missing = sorted(n for n in names - set(fields) if not hasattr(cls, n))
    if extra or missing:
        raise StructureError(
            f"class {path!r} has changed since the save: saved fields {extra} are gone, fields "
            f"{missing} are new. Load with the version of the class that saved it."
        )
    obj = object.__new__(cls)
    for name, value in fields.items():
        object.__setattr__(obj, name, value)
    return obj
