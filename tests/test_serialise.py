"""`save` / `load`: the library's data and results round-trip through one .npz file, nothing
else is stored or run (no pickle), and what cannot be saved or loaded is named."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_root, tree_allclose

import rootshape_jax as rs
from rootshape_jax.datasets import synthetic_roots


def same_exactly(a, b) -> bool:
    """Same structure, same leaf types (JAX or numpy), dtypes, weak types (a Python number's
    type, which mixed-precision code and jit caches see) and values (NaN equal to NaN)."""
    la, ta = jax.tree.flatten(a)
    lb, tb = jax.tree.flatten(b)
    return (
        ta == tb
        and all(type(x) is type(y) or (isinstance(x, jax.Array) and isinstance(y, jax.Array)) for x, y in zip(la, lb))
        and all(
            np.asarray(x).dtype == np.asarray(y).dtype
            and getattr(x, "weak_type", None) == getattr(y, "weak_type", None)
            and np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
            for x, y in zip(la, lb)
        )
    )


@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(7)
    trees = rs.batch([random_root(rng, n_laterals=3) for _ in range(4)], n_points=12, dtype=np.float64)
    km = rs.karcher_mean(trees, max_steps=5, progress=False, throw=False)
    return trees, km, rs.tangent_pca(km)


def test_data_and_results_round_trip(fitted, tmp_path):
    trees, km, pc = fitted
    srvf = rs.to_srvf(trees)
    reg = rs.register(*rs.unstack(trees)[:2])
    for name, obj in [
        ("trees", trees),
        ("srvf", srvf),
        ("mean", km),
        ("pca", pc),
        ("registration", reg),
        ("weights", rs.Weights(main=0.5, position=2.0)),
    ]:
        back = rs.load(rs.save(tmp_path / f"{name}.npz", obj))
        assert type(back) is type(obj) and same_exactly(back, obj), name
    back = rs.load(tmp_path / "mean.npz")
    assert bool(back.result == km.result)
    assert back.init_index == km.init_index and int(back.steps) == int(km.steps)
    # What a user does with a loaded PCA gives what the original gives.
    loaded = rs.load(tmp_path / "pca.npz")
    assert loaded.n_components == pc.n_components
    np.testing.assert_array_equal(
        np.asarray(rs.reconstruct(loaded, jnp.ones(pc.n_components)).main),
        np.asarray(rs.reconstruct(pc, jnp.ones(pc.n_components)).main),
    )


def test_roots_containers_and_plain_values_round_trip(tmp_path):
    roots = synthetic_roots(2, seed=3)
    deep = roots[0]
    obj = {
        "roots": roots,
        "pair": (np.float32(1.5), float("nan"), None, True, 3, "mm"),
        "matrix": np.arange(6, dtype=np.int16).reshape(2, 3),
        "labels": np.array(["control", "drought"]),
        "clusters": rs.cluster(np.array([[0.0, 1.0, 4.0], [1.0, 0.0, 4.0], [4.0, 4.0, 0.0]])),
    }
    back = rs.load(rs.save(tmp_path / "x.npz", obj))
    assert set(back) == set(obj)
    for r, s in zip(back["roots"], roots):
        assert type(r) is rs.Root and r.name == s.name and r.metadata == s.metadata
        np.testing.assert_array_equal(r.main, s.main)
        assert all(np.array_equal(a, b) for a, b in zip(r.laterals, s.laterals))
        np.testing.assert_array_equal(r.attach, s.attach)
        assert len(r.children) == len(s.children)
    assert back["roots"][0].n_laterals == deep.n_laterals
    p = back["pair"]
    assert type(p) is tuple and p[0] == np.float32(1.5) and p[0].dtype == np.float32 and np.isnan(p[1])
    assert p[2:] == (None, True, 3, "mm")
    assert back["matrix"].dtype == np.int16 and np.array_equal(back["matrix"], obj["matrix"])
    assert list(back["labels"]) == ["control", "drought"]
    assert isinstance(back["clusters"], rs.Clustering)
    np.testing.assert_array_equal(back["clusters"].labels, obj["clusters"].labels)
    assert tree_allclose(back["clusters"].linkage, obj["clusters"].linkage)


def test_what_cannot_be_saved_is_named(tmp_path):
    @dataclasses.dataclass
    class Mine:
        x: int = 1

    cases = [
        (Mine(), r"obj is a .*Mine, which save cannot store"),
        ({"f": lambda: 0}, r"obj\[.f.\] is a builtins.function"),
        ([jax.random.key(0)], r"obj\[0\] is a JAX random key; save jax.random.key_data"),
        ({1: 2}, "keys that are not strings"),
        (np.array([object()]), "array of Python objects"),
    ]
    for obj, match in cases:
        with pytest.raises(TypeError, match=match):
            rs.save(tmp_path / "bad.npz", obj)
    assert not (tmp_path / "bad.npz").exists()  # nothing half-written


def _header_file(path, structure, version=1, **arrays):
    header = {"format": "rootshape_jax.save", "version": version, "structure": structure}
    np.savez(path, __rootshape__=np.array(json.dumps(header)), **arrays)
    return path


def test_files_that_are_not_ours_or_name_other_code_are_refused(tmp_path):
    np.savez(tmp_path / "plain.npz", x=np.ones(3))
    (tmp_path / "text.npz").write_text("not a zip")
    for path in (tmp_path / "plain.npz", tmp_path / "text.npz"):
        with pytest.raises(rs.InputError, match="not a file written by rootshape_jax.save"):
            rs.load(path)
    # A file may only name rootshape_jax's data classes: anything else is refused before
    # it is imported or built (no module of another package is imported, nothing is run).
    for name in ("os:system", "subprocess:Popen", "rootshape_jax.__main__:main", "rootshape_jax._cli._main:main"):
        path = _header_file(tmp_path / "evil.npz", {"class": name, "fields": {}})
        with pytest.raises(rs.InputError, match="not one of rootshape_jax's|does not have"):
            rs.load(path)
    assert "rootshape_jax.__main__" not in sys.modules
    path = _header_file(tmp_path / "new.npz", None, version=99)
    with pytest.raises(rs.InputError, match="newer rootshape_jax"):
        rs.load(path)
    path = _header_file(tmp_path / "old.npz", {"class": "rootshape_jax._metric:Weights", "fields": {"main": 1.0}})
    with pytest.raises(rs.InputError, match="load it with the version that saved it"):
        rs.load(path)
    with pytest.raises(FileNotFoundError):
        rs.load(tmp_path / "missing.npz")


def test_float64_arrays_are_not_rounded_silently(tmp_path):
    # Loaded where JAX runs in 32 bits (its default), float64 JAX arrays would be rounded; a
    # Python number's weak scalar (the weights) takes that session's width, as the number would.
    path = rs.save(tmp_path / "f64.npz", {"x": jnp.ones(3, jnp.float64), "w": rs.Weights(main=0.1)})
    weights = rs.save(tmp_path / "w64.npz", rs.Weights(main=0.1))
    code = (
        "import rootshape_jax as rs\n"
        "try:\n    rs.load(r'%s')\nexcept rs.InputError as e:\n    print('refused:', e)\n"
        "print('weights', rs.load(r'%s').main.dtype)\n" % (path, weights)
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert "refused:" in out.stdout and 'jax.config.update("jax_enable_x64", True)' in out.stdout, out.stderr
    assert "weights float32" in out.stdout, out.stdout + out.stderr


def test_a_file_edited_by_hand_is_checked_as_the_class_checks_itself(tmp_path):
    trees = rs.batch(synthetic_roots(2, seed=1), n_points=10)
    path = rs.save(tmp_path / "t.npz", trees)
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    header = json.loads(str(arrays["__rootshape__"]))
    mask_key = header["structure"]["fields"]["mask"]["array"]
    arrays[mask_key] = arrays[mask_key][:, :-1]  # one lateral slot fewer than the curves have
    np.savez(tmp_path / "edited.npz", **arrays)
    with pytest.raises(rs.InputError, match="edited.npz: its RootTree is not valid"):
        rs.load(tmp_path / "edited.npz")


def test_numpy_scalars_weak_types_and_dtypes_npz_cannot_keep(tmp_path):
    # A review found np.float64 saved as "np.float64(1.5)" (never loadable), bfloat16 coming
    # back as raw bytes, and weak types lost: then loaded default weights made a float32
    # distance fail under 64-bit JAX (a float64 carry), which the original weights do not.
    r = synthetic_roots(1, seed=2)[0]
    r = dataclasses.replace(r, metadata=dict(r.metadata, resolution=np.float64(179.0)))
    back = rs.load(rs.save(tmp_path / "r.npz", {"acc": np.float64(1.5), "root": r}))
    assert back["acc"] == 1.5 and type(back["acc"]) is np.float64
    assert back["root"].metadata["resolution"] == 179.0
    import ml_dtypes

    for bad in (np.ones(2, ml_dtypes.bfloat16), jnp.ones(2, jnp.bfloat16)):
        with pytest.raises(TypeError, match="dtype bfloat16, which .npz cannot keep"):
            rs.save(tmp_path / "b.npz", bad)
    w = rs.load(rs.save(tmp_path / "w.npz", rs.Weights()))
    assert all(x.weak_type for x in jax.tree.leaves(w))
    a, b = rs.unstack(rs.batch(synthetic_roots(2, seed=4), n_points=10, dtype=np.float32))
    assert float(rs.distance(a, b, weights=w)) == float(rs.distance(a, b, weights=rs.Weights()))


def test_malformed_files_and_misplaced_saves_are_named(tmp_path):
    bad = [
        ("list.npz", ["not", "a", "header"], {}),
        ("nokey.npz", {"format": "rootshape_jax.save", "version": 1, "structure": {"array": "a9", "kind": "jax"}}, {}),
        (
            "fields.npz",
            {
                "format": "rootshape_jax.save",
                "version": 1,
                "structure": {"class": "rootshape_jax._metric:Weights", "fields": [1]},
            },
            {},
        ),
        ("status.npz", {"format": "rootshape_jax.save", "version": 1, "structure": {"status": "hello"}}, {}),
        (
            "foreign.npz",
            {
                "format": "rootshape_jax.save",
                "version": 1,
                "structure": {"class": "rootshape_jax._serialise:_STATUS", "fields": {}},
            },
            {},
        ),
        ("boolversion.npz", {"format": "rootshape_jax.save", "version": True, "structure": None}, {}),
    ]
    for name, header, arrays in bad:
        np.savez(tmp_path / name, __rootshape__=np.array(json.dumps(header)), **arrays)
        with pytest.raises(rs.InputError, match=name):
            rs.load(tmp_path / name)
    root = {"class": "rootshape_jax._root:Root", "fields": {f.name: None for f in dataclasses.fields(rs.Root)}}
    root["fields"]["main"] = "not an array"
    _header_file(tmp_path / "root.npz", root)
    with pytest.raises(rs.InputError, match="root.npz: its Root is not valid"):
        rs.load(tmp_path / "root.npz")
    with pytest.raises(IsADirectoryError, match="is a folder; give a file name"):
        rs.save(tmp_path, [1])
    cycle = []
    cycle.append(cycle)
    with pytest.raises(TypeError, match="holds itself"):
        rs.save(tmp_path / "c.npz", cycle)
