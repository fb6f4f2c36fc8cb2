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

import equinox as eqx
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
    `Clustering`, ... with their arrays (JAX or numpy, in numpy's own dtypes: not bfloat16),
    numbers, strings and None.
    Compute once, reuse later: ``rs.save("pca.npz", pc)``, then in another session
    ``pc = rs.load("pca.npz")`` and ``rs.project(pc, new_trees)``.

    Raises `TypeError` naming the part of `obj` that cannot be saved (a class from outside
    rootshape_jax, a function). Returns the path written.
    """
    if Path(path).is_dir():
        raise IsADirectoryError(f"save: {path} is a folder; give a file name, e.g. {Path(path) / 'results.npz'}.")
    arrays: dict[str, np.ndarray] = {}
    try:
        structure = _encode(obj, arrays, "obj")
    except RecursionError:
        raise TypeError("save: obj is nested too deeply, or holds itself (a cycle).") from None
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
    float32, so `load` raises `InputError` instead. Scalars that came from Python numbers (JAX's
    weak type, e.g. `Weights`) come back as such, at the session's default width. A file that
    `save` did not write, that names a class outside rootshape_jax, or whose contents fail
    their class's own checks raises `InputError`.
    """
    path = Path(path)
    try:
        npz = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        if isinstance(e, (FileNotFoundError, IsADirectoryError, PermissionError)):
            raise
        raise InputError(f"{path}: not a file written by rootshape_jax.save ({e}).") from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise InputError(f"{path}: not a file written by rootshape_jax.save (a single array).")
    with npz:
        try:
            header = json.loads(str(npz[_HEADER]))
        except (KeyError, ValueError):
            raise InputError(f"{path}: not a file written by rootshape_jax.save (no header).") from None
        version = header.get("version") if isinstance(header, dict) else None
        if not isinstance(header, dict) or header.get("format") != FORMAT or type(version) is not int:
            raise InputError(f"{path}: not a file written by rootshape_jax.save.")
        if version > VERSION:
            raise InputError(
                f"{path} was written by a newer rootshape_jax (file format {version}, this one reads "
                f"up to {VERSION}); update rootshape_jax to load it."
            )
        # Arrays are read when the structure names them, so a file's other members cost nothing.
        try:
            return _decode(header.get("structure"), npz, path)
        except InputError:
            raise
        except (KeyError, IndexError, TypeError, ValueError, AttributeError, RecursionError, MemoryError) as e:
            raise InputError(f"{path}: not a valid rootshape_jax.save file ({type(e).__name__}: {e}).") from None


# --------------------------------------------------------------------------------------------
# Encoding: JSON for the structure, numbered arrays beside it.


def _encode(x: Any, arrays: dict, where: str) -> Any:
    if x is None or isinstance(x, (bool, str)):
        return x
    # numpy scalars first: np.float64 is also a Python float.
    if isinstance(x, (jax.Array, np.ndarray, np.generic)):
        if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            raise TypeError(f"save: {where} is a JAX random key; save jax.random.key_data(key) instead.")
        a = np.asarray(x)
        if a.dtype.hasobject:
            raise TypeError(f"save: {where} is an array of Python objects; give it a numeric or string dtype.")
        if a.dtype.kind not in "biufcUS" or a.dtype.type.__module__ != "numpy":
            # .npz keeps numpy's own dtypes only: bfloat16, float8, ... would come back as bytes.
            raise TypeError(
                f"save: {where} has dtype {a.dtype.name}, which .npz cannot keep; cast it to float32 first."
            )
        key = f"a{len(arrays)}"
        arrays[key] = a
        kind = "jax" if isinstance(x, jax.Array) else ("numpy" if isinstance(x, np.ndarray) else "scalar")
        entry = {"array": key, "kind": kind}
        if kind == "jax" and x.weak_type:
            entry["weak"] = True  # a Python number's type: keeps mixed-precision code and jit caches as they were
        return entry
    if isinstance(x, (int, float)):
        return {"float": repr(float(x))} if isinstance(x, float) else int(x)
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
        return float(str(x["float"]))
    if isinstance(x, dict) and "array" in x:
        if x["array"] == _HEADER:
            raise InputError(f"{path}: not a valid rootshape_jax.save file (an array entry names the header).")
        a = arrays[str(x["array"])]
        if x["kind"] == "numpy":
            return a
        if x["kind"] == "scalar":
            return a[()]
        if x.get("weak") and a.ndim == 0 and a.dtype.kind in "iufc":
            # A Python number's type (weak, the default width): mixed-precision code and jit
            # caches treat it as they treated the original.
            return jnp.asarray(a.item())
        if a.dtype in (np.float64, np.int64, np.uint64, np.complex128) and not jax.config.jax_enable_x64:
            raise InputError(
                f"{path} holds {a.dtype} JAX arrays, which JAX would round to 32 bits: enable 64-bit JAX "
                'first (jax.config.update("jax_enable_x64", True)), then load.'
            )
        if x["kind"] != "jax" or a.dtype.kind not in "biufc":
            raise InputError(f"{path}: not a valid rootshape_jax.save file (array entry {x['array']!r}).")
        return jnp.asarray(a)
    if isinstance(x, dict) and "status" in x:
        value = _decode(x["status"], arrays, path)
        if np.ndim(value) != 0 or np.asarray(value).dtype.kind not in "iu":
            raise InputError(f"{path}: not a valid rootshape_jax.save file (a solver status that is not an integer).")
        status = object.__new__(_STATUS)
        object.__setattr__(status, "_value", value)
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
        if not isinstance(x.get("fields"), dict) or set(x["fields"]) != names:
            raise InputError(
                f"{path}: its {cls.__qualname__} has fields {sorted(x['fields'])}, this rootshape_jax's has "
                f"{sorted(names)}; load it with the version that saved it."
            )
        for name, value in x["fields"].items():
            object.__setattr__(obj, name, _decode(value, arrays, path))
        # The classes' own invariants (shapes, padding), as at construction: a file edited by
        # hand fails here, naming itself, not later inside JAX. (`Root.__post_init__` checks
        # and converts; run again on its own output it changes nothing.)
        checks = [kls.__dict__.get("__check_init__") for kls in cls.__mro__]
        if not isinstance(obj, eqx.Module):
            checks.append(getattr(cls, "__post_init__", None))
        for check in checks:
            if check is not None:
                try:
                    check(obj)
                except (ValueError, TypeError, AttributeError, IndexError) as e:
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
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)) or cls.__module__.split(".")[0] != "rootshape_jax":
        raise InputError(f"{path} names {name!r}, which is not one of rootshape_jax's data classes.")
    return cls
