"""Data-only files for kept results: dataclasses of numpy arrays, scalars, strings and containers.

A kept result lives in the output folder, which other people and machines can write
to; reading it back must never run code, so nothing here is a pickle. A file is one
``.npz`` (numpy's zip of ``.npy`` arrays, read with ``allow_pickle=False``) holding:

- ``tree``: the value as JSON, each array replaced by ``{"$a": n}``;
- ``a<n>``: the arrays (any dtype numpy stores without pickling: numbers, booleans,
  fixed-width strings, structured records of those; object arrays are refused).

Containers and other values are tagged objects in the JSON: ``$l`` list, ``$t`` tuple,
``$d`` dict (a list of key-value pairs: keys may be numbers or tuples), ``$s`` set,
``$f`` frozenset, ``$b`` bytes (base64), ``$p`` path, ``$c`` dataclass (its class
and fields by name), ``$e`` enum member. Numpy scalars are 0-d arrays, so they come
back with their type. A dataclass or enum is looked up by name only among holefill's
own modules (``pipeline.*``), and must be a dataclass (an enum); its fields must be
exactly the class's, and those annotated ``int``, ``float``, ``str`` or ``bool``
must hold one. So a new field of these kinds needs no code here.

Anything else (a file changed by hand, another program's file, another class)
raises :class:`ValueError`: the caller recomputes rather than trusts it.
"""

from __future__ import annotations

import base64
import dataclasses
import enum
import importlib
import json
import os
from pathlib import Path, PurePath
from typing import Any

import numpy as np

#: The only modules whose classes a file may name.
TRUSTED_PACKAGE = "pipeline"

#: Modules that moved, by their old names: a result an earlier version kept names its
#: classes there and still reads back (``--incremental`` over an older run's ``work/``).
MOVED_MODULES = {
    "pipeline.survey": "pipeline.survey.scan",
    "pipeline.density": "pipeline.survey.density",
    "pipeline.footprint": "pipeline.survey.footprint",
    "pipeline.footprint_density": "pipeline.survey.footprint_density",
    "pipeline.tile_grid": "pipeline.survey.tile_grid",
    "pipeline.ground_level": "pipeline.survey.ground_level",
}

_SIMPLE_TYPES: dict[str, tuple[type, ...]] = {
    "int": (int, np.integer),
    "float": (float, int, np.floating, np.integer),
    "str": (str,),
    "bool": (bool, np.bool_),
}


def dump(path: str | os.PathLike, value: Any, *, version: int) -> None:
    """Write ``value`` as a data-only file (under a temporary name, then renamed).

    The temporary name is hidden (``.<name>.tmp``): one left by a killed process must not pass
    for a result (``<name>.tmp.npz`` matched ``rasterize-*.npz``).
    """
    arrays: list[np.ndarray] = []
    tree = {"version": version, "value": _encode(value, arrays)}
    payload = {f"a{i}": a for i, a in enumerate(arrays)}
    payload["tree"] = np.frombuffer(json.dumps(tree).encode(), dtype=np.uint8)
    write_npz_atomically(path, payload)


def write_npz_atomically(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez`` of ``arrays`` to ``path``, written under a hidden temporary name and renamed."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:  # a file object: numpy appends no ".npz"
        np.savez(fh, allow_pickle=False, **arrays)
    os.replace(tmp, path)


def load(path: str | os.PathLike, *, version: int) -> Any:
    """What :func:`dump` wrote; ``ValueError`` for any other content or another format version."""
    try:
        with np.load(path, allow_pickle=False) as data:
            names = set(data.files)
            if "tree" not in names:
                raise ValueError("no tree")
            tree = json.loads(data["tree"].tobytes().decode())
            arrays = {name: data[name] for name in names - {"tree"}}
    except (OSError, KeyError, UnicodeDecodeError, EOFError) as e:
        raise ValueError(f"{path}: not a kept result ({e})") from None
    if not isinstance(tree, dict) or tree.get("version") != version:
        raise ValueError(f"{path}: intermediate format {tree.get('version') if isinstance(tree, dict) else '?'}, "
                         f"this holefill reads {version}")  # fmt: skip
    try:
        return _decode(tree.get("value"), arrays)
    except (TypeError, KeyError, AttributeError, ImportError, RecursionError, ValueError) as e:
        raise ValueError(f"{path}: unexpected content ({e})") from None


def _encode(value: Any, arrays: list[np.ndarray]) -> Any:
    if value is None or isinstance(value, (bool, str)) or type(value) in (int, float):
        return value
    if isinstance(value, (np.ndarray, np.generic)):
        array = np.asarray(value)
        if array.dtype.hasobject:
            raise TypeError(f"an array of Python objects ({array.dtype}) cannot be kept in a data-only file")
        arrays.append(array)
        return {"$a": len(arrays) - 1}
    if isinstance(value, enum.Enum):
        return {"$e": _class_name(type(value)), "v": _encode(value.value, arrays)}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = {f.name: _encode(getattr(value, f.name), arrays) for f in dataclasses.fields(value)}
        return {"$c": _class_name(type(value)), "v": fields}
    if isinstance(value, (int, float)):  # a subclass (numpy's float64 is one): as the plain number
        return int(value) if isinstance(value, int) else float(value)
    if isinstance(value, tuple):
        return {"$t": [_encode(v, arrays) for v in value]}
    if isinstance(value, list):
        return {"$l": [_encode(v, arrays) for v in value]}
    if isinstance(value, dict):
        return {"$d": [[_encode(k, arrays), _encode(v, arrays)] for k, v in value.items()]}
    if isinstance(value, (set, frozenset)):
        return {"$f" if isinstance(value, frozenset) else "$s": [_encode(v, arrays) for v in value]}
    if isinstance(value, bytes):
        return {"$b": base64.b64encode(value).decode()}
    if isinstance(value, PurePath):
        return {"$p": str(value)}
    raise TypeError(f"a {type(value).__module__}.{type(value).__qualname__} cannot be kept in a data-only file")


def _decode(node: Any, arrays: dict[str, np.ndarray]) -> Any:
    if node is None or isinstance(node, (bool, int, float, str)):
        return node
    if not isinstance(node, dict) or len(node) not in (1, 2):
        raise ValueError(f"unexpected node {str(node)[:60]!r}")
    tag = next(iter(node))
    items = node[tag]
    if tag == "$a":
        array = arrays[f"a{int(items)}"]
        return array[()] if array.ndim == 0 else array
    if tag == "$t":
        return tuple(_decode(v, arrays) for v in _listed(items))
    if tag == "$l":
        return [_decode(v, arrays) for v in _listed(items)]
    if tag == "$d":
        return {_decode(k, arrays): _decode(v, arrays) for k, v in _listed(items)}
    if tag in ("$s", "$f"):
        values = (_decode(v, arrays) for v in _listed(items))
        return frozenset(values) if tag == "$f" else set(values)
    if tag == "$b":
        return base64.b64decode(str(items), validate=True)
    if tag == "$p":
        return Path(str(items))
    if tag == "$e":
        cls = _trusted_class(str(items), enum_ok=True)
        return cls(_decode(node["v"], arrays))
    if tag == "$c":
        return _dataclass(_trusted_class(str(items)), node["v"], arrays)
    raise ValueError(f"unknown tag {tag!r}")


def _listed(items: Any) -> list:
    if not isinstance(items, list):
        raise ValueError("a container that is not a list")
    return items


def _dataclass(cls: type, fields: Any, arrays: dict[str, np.ndarray]) -> Any:
    """An instance of ``cls`` with exactly its fields, set as stored (no ``__init__``: no code of the file's)."""
    expected = {f.name: f for f in dataclasses.fields(cls)}
    if not isinstance(fields, dict) or set(fields) != set(expected):
        raise ValueError(f"{cls.__qualname__}: fields {sorted(fields) if isinstance(fields, dict) else '?'}")
    instance: Any = object.__new__(cls)
    for name, field in expected.items():
        value = _decode(fields[name], arrays)
        kinds = _SIMPLE_TYPES.get(field.type if isinstance(field.type, str) else getattr(field.type, "__name__", ""))
        if kinds is not None and not isinstance(value, kinds):
            raise ValueError(f"{cls.__qualname__}.{name}: a {type(value).__name__}, expected {field.type}")
        object.__setattr__(instance, name, value)
    return instance


def _class_name(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _trusted_class(name: str, *, enum_ok: bool = False) -> type:
    """The dataclass (or enum) ``module:qualname`` of holefill's own modules; anything else is refused."""
    module_name, _, qualname = name.partition(":")
    if not (module_name == TRUSTED_PACKAGE or module_name.startswith(TRUSTED_PACKAGE + ".")) or not qualname:
        raise ValueError(f"class {name!r} is not one of holefill's")
    if not all(part.isidentifier() for part in (*module_name.split("."), *qualname.split("."))):
        raise ValueError(f"class {name!r} is not a name")
    try:
        target: Any = importlib.import_module(MOVED_MODULES.get(module_name, module_name))
        for part in qualname.split("."):
            target = getattr(target, part)
    except (ImportError, AttributeError) as e:  # a class this version does not have
        raise ValueError(f"class {name!r} is not one of holefill's") from e
    if isinstance(target, type) and dataclasses.is_dataclass(target):
        return target
    if enum_ok and isinstance(target, type) and issubclass(target, enum.Enum):
        return target
    raise ValueError(f"{name!r} is not a dataclass")
