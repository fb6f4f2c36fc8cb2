"""Saving and loading the library's data and results (`save`, `load`): one ``.npz`` file.

The arrays are stored as numpy arrays; the structure around them (which class, which field,
static values such as `TangentPCA.n_components`) as JSON in the same file. Nothing is pickled:
a file names only classes of rootshape_jax (and optimistix's solver status), and loading
builds those from the stored fields without running any other code, so a file from someone
else cannot execute anything. The classes are rebuilt as JAX's own pytree unflattening
builds them (fields set, ``__init__`` not run): what was saved is what comes back.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import json
import os
import sys
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._atomic import atomic_write
from ._errors import InputError

FORMAT = "rootshape_jax.save"
VERSION = 1
_HEADER = "__rootshape__"
_STATUS = type(optx.RESULTS.successful)  # optimistix's solver status (an Enumeration item)


def save(path: str | os.PathLike, obj: Any) -> Path:
    """Save `obj` to `path` (an ``.npz`` file, written whole or not at all) for `load`.

    `obj` is one of the library's data or results, or a list, tuple or dict of them: a
    `RootTree`, `SRVFTree`, `Root` (with its children and metadata), `KarcherMean`,
    `TangentPCA`, `TraitRegression`, `Registration`, `Weights`, `LearnedWeights`,
    `Clustering`, ... with their arrays (JAX or numpy, any dtype), numbers, strings and None.
    Compute once, reuse later: ``rs.save("pca.npz", pc)``, then in another session
    ``pc = rs.load("pca.npz")`` and ``rs.project(pc, new_trees)``.

    Raises `TypeError` naming the part of `obj` that cannot be saved (a class from outside
    rootshape_jax, a function). Returns the path written.
    """
    arrays: dict[str, np.ndarray] = {}
    structure = _encode(obj, arrays, "obj")
    header = {"format": FORMAT, "version": VERSION, "structure": structure}
    arrays[_HEADER] = np.array(json.dumps(header))

    def write(p: Path) -> None:
        with open(p, "wb") as f:
            np.savez(f, **arrays)

    return atomic_write(path, write)


def load(path: str | os.PathLike) -> Any:
    """What `save` wrote to `path`, as it was saved: JAX arrays come back as JAX arrays (on
    the default device), numpy arrays as numpy arrays, with their dtypes.

    A file with float64 JAX arrays needs float64 enabled before loading
    (``jax.config.update("jax_enable_x64", True)``); without it JAX would round them to
    float32, so `load` raises `InputError` instead. A file that `save` did not write, or that
    names a class outside rootshape_jax, raises `InputError`.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (ValueError, OSError, EOFError) as e:
        if isinstance(e, (FileNotFoundError, IsADirectoryError, PermissionError)):
            raise
        raise InputError(f"{path}: not a file written by rootshape_jax.save ({e}).") from None
    try:
        header = json.loads(str(arrays.pop(_HEADER)))
    except (KeyError, json.JSONDecodeError):
        raise InputError(f"{path}: not a file written by rootshape_jax.save (no header).") from None
    if header.get("format") != FORMAT or not isinstance(header.get("version"), int):
        raise InputError(f"{path}: not a file written by rootshape_jax.save.")
    if header["version"] > VERSION:
        raise InputError(
            f"{path} was written by a newer rootshape_jax (file format {header['version']}, this one reads "
            f"up to {VERSION}); update rootshape_jax to load it."
        )
    return _decode(header["structure"], arrays, path)


# --------------------------------------------------------------------------------------------
# Encoding: JSON for the structure, numbered arrays beside it.


def _encode(x: Any, arrays: dict, where: str) -> Any:
    if x is None or isinstance(x, (bool, str)):
        return x
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return {"float": repr(x)} if isinstance(x, float) else x
    if isinstance(x, (jax.Array, np.ndarray, np.generic)):
        if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            raise TypeError(f"save: {where} is a JAX random key; save jax.random.key_data(key) instead.")
        if np.asarray(x).dtype.hasobject:
            raise TypeError(f"save: {where} is an array of Python objects; give it a numeric or string dtype.")
        key = f"a{len(arrays)}"
        arrays[key] = np.asarray(x)
        kind = "jax" if isinstance(x, jax.Array) else ("numpy" if isinstance(x, np.ndarray) else "scalar")
        return {"array": key, "kind": kind}
    if isinstance(x, _STATUS):
        if x._enumeration is not optx.RESULTS:
            raise TypeError(f"save: {where} is a status of another enumeration than optimistix.RESULTS.")
        return {"status": _encode(x._value, arrays, f"{where}._value")}
    if isinstance(x, (list, tuple)):
        items = [_encode(v, arrays, f"{where}[{i}]") for i, v in enumerate(x)]
        return {"tuple": items} if isinstance(x, tuple) else {"list": items}
    if isinstance(x, dict):
        if not all(isinstance(k, str) for k in x):
            raise TypeError(f"save: {where} is a dict with keys that are not strings.")
        return {"dict": {k: _encode(v, arrays, f"{where}[{k!r}]") for k, v in x.items()}}
    cls = type(x)
    if dataclasses.is_dataclass(x) and cls.__module__.split(".")[0] == "rootshape_jax":
        fields = {f.name: _encode(getattr(x, f.name), arrays, f"{where}.{f.name}") for f in dataclasses.fields(x)}
        return {"class": f"{cls.__module__}:{cls.__qualname__}", "fields": fields}
    raise TypeError(
        f"save: {where} is a {cls.__module__}.{cls.__qualname__}, which save cannot store; it saves the "
        "data and results of rootshape_jax, arrays, numbers, strings, and lists, tuples and dicts of them."
    )


def _decode(x: Any, arrays: dict, path: Path) -> Any:
    if x is None or isinstance(x, (bool, str, int)):
        return x
    if isinstance(x, dict) and "float" in x:
        return float(x["float"])
    if isinstance(x, dict) and "array" in x:
        a = arrays[x["array"]]
        if x["kind"] == "numpy":
            return a
        if x["kind"] == "scalar":
            return a[()]
        if a.dtype in (np.float64, np.int64, np.uint64, np.complex128) and not jax.config.jax_enable_x64:
            raise InputError(
                f"{path} holds {a.dtype} JAX arrays, which JAX would round to 32 bits: enable 64-bit JAX "
                'first (jax.config.update("jax_enable_x64", True)), then load.'
            )
        return jnp.asarray(a)
    if isinstance(x, dict) and "status" in x:
        status = object.__new__(_STATUS)
        object.__setattr__(status, "_value", _decode(x["status"], arrays, path))
        object.__setattr__(status, "_enumeration", optx.RESULTS)
        return status
    if isinstance(x, dict) and "tuple" in x:
        return tuple(_decode(v, arrays, path) for v in x["tuple"])
    if isinstance(x, dict) and "list" in x:
        return [_decode(v, arrays, path) for v in x["list"]]
    if isinstance(x, dict) and "dict" in x:
        return {k: _decode(v, arrays, path) for k, v in x["dict"].items()}
    if isinstance(x, dict) and "class" in x:
        cls = _library_class(x["class"], path)
        obj = object.__new__(cls)
        names = {f.name for f in dataclasses.fields(cls)}
        if set(x["fields"]) != names:
            raise InputError(
                f"{path}: its {cls.__qualname__} has fields {sorted(x['fields'])}, this rootshape_jax's has "
                f"{sorted(names)}; load it with the version that saved it."
            )
        for name, value in x["fields"].items():
            object.__setattr__(obj, name, _decode(value, arrays, path))
        # The classes' own invariants (shapes, padding), as at construction: a file edited by
        # hand fails here, naming itself, not later inside JAX.
        for kls in cls.__mro__:
            check = kls.__dict__.get("__check_init__")
            if check is not None:
                try:
                    check(obj)
                except (ValueError, TypeError) as e:
                    raise InputError(f"{path}: its {cls.__qualname__} is not valid: {e}") from None
        return obj
    raise InputError(f"{path}: not a file written by rootshape_jax.save (unknown entry {str(x)[:60]!r}).")


def _library_class(name: str, path: Path) -> type:
    """The dataclass `name` ("module:qualname") of rootshape_jax; nothing else is imported."""
    module, _, qualname = str(name).partition(":")
    if module.split(".")[0] != "rootshape_jax" or not qualname or "." in qualname:
        raise InputError(f"{path} names the class {name!r}, which is not one of rootshape_jax's.")
    if module not in sys.modules:
        # Only the public subpackages are imported for a name (never a module that runs
        # anything, such as rootshape_jax.__main__); their imports define every data class.
        public = ".".join(module.split(".")[:2])
        if public in ("rootshape_jax.io", "rootshape_jax.plot", "rootshape_jax.baselines", "rootshape_jax.datasets"):
            with contextlib.suppress(ImportError):  # an optional extra not installed
                importlib.import_module(public)
    try:
        cls = getattr(sys.modules[module], qualname)
    except (KeyError, AttributeError):
        raise InputError(
            f"{path} names {name!r}, which this rootshape_jax does not have; load it with the version that saved it."
        ) from None
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise InputError(f"{path} names {name!r}, which is not one of rootshape_jax's data classes.")
    return cls
