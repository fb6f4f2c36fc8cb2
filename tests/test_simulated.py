import sys

import numpy as np
import pytest

from rootshape_jax._errors import MissingDependencyError
from rootshape_jax._root import Root
from rootshape_jax.datasets import available_species, simulated_roots

try:
    import plantbox as pb
except ImportError:
    pb = None

needs_cplantbox = pytest.mark.skipif(
    pb is None,
    reason="CPlantBox is not installed (optional extra: pip install 'rootshape_jax[sim]')",
)


def _same(a: Root, b: Root) -> bool:
    return (
        np.array_equal(a.main, b.main)
        and len(a.laterals) == len(b.laterals)
        and all(np.array_equal(x, y) for x, y in zip(a.laterals, b.laterals))
        and np.array_equal(a.attach, b.attach)
    )


def _check_on_parent(root: Root, depth: int = 0) -> int:
    """Every lateral, at every order, starts exactly on its parent at its attach fraction."""
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(root.main, axis=0), axis=1))])
    count = 0
    for k, (lat, a) in enumerate(zip(root.laterals, root.attach)):
        at = np.array([np.interp(a * cum[-1], cum, root.main[:, j]) for j in range(root.dim)])
        np.testing.assert_allclose(lat[0], at, atol=1e-9)
        if root.children:
            np.testing.assert_array_equal(root.children[k].main, lat)
            count += _check_on_parent(root.children[k], depth + 1)
    return count + len(root.laterals)


def test_missing_dependency(monkeypatch):
    monkeypatch.setitem(sys.modules, "plantbox", None)  # makes `import plantbox` fail
    with pytest.raises(MissingDependencyError, match=r"pip install 'rootshape_jax\[sim\]'"):
        simulated_roots("wheat", 1)
    with pytest.raises(MissingDependencyError, match="sim"):
        available_species()


@needs_cplantbox
def test_available_species():
    names = available_species()
    assert names[:3] == ["wheat", "maize", "lupin"]
    assert "Zea_mays_1_Leitner_2010" in names and "Glycine_max" in names
    assert len(names) == len(set(names))
    with pytest.raises(ValueError, match="Unknown species"):
        simulated_roots("triffid", 1)
    with pytest.raises(ValueError, match="days"):
        simulated_roots("wheat", 1, days=0)


@needs_cplantbox
@pytest.mark.parametrize("species", ["wheat", "lupin", "maize"])
def test_simulated_roots_valid_and_deterministic(species):
    roots = simulated_roots(species, 2, days=14, seed=7)
    assert len(roots) == 2
    # wheat.xml's tap root has an apical zone of 14.2 ± 6.4 cm and lmax 80 ± 80 cm, so some
    # tap roots never branch: require laterals on every root only for the other species.
    assert sum(r.n_laterals for r in roots) > 0
    for i, r in enumerate(roots):
        assert isinstance(r, Root) and r.dim == 3
        assert r.main_length > 10.0  # mm
        assert r.n_laterals > 0 or species == "wheat"
        assert all(lat.shape[0] >= 2 for lat in r.laterals)
        _check_on_parent(r)
        assert np.all(np.isfinite(r.main))
        assert np.all((r.attach >= 0) & (r.attach <= 1))
        # Our convention: z is depth, growing downward, in mm (seed sown 3 cm deep).
        assert r.main[-1, 2] > r.main[0, 2]
        assert r.metadata["species"] == species and r.metadata["index"] == i
        assert r.metadata["unit"] == "mm" and r.metadata["source"] == "cplantbox"
    again = simulated_roots(species, 2, days=14, seed=7)
    assert all(_same(a, b) for a, b in zip(roots, again))
    other = simulated_roots(species, 2, days=14, seed=8)
    assert not any(_same(a, b) for a, b in zip(roots, other))
    assert not _same(roots[0], roots[1])
    # Plant i does not depend on n.
    assert _same(simulated_roots(species, 1, days=14, seed=7)[0], roots[0])


@needs_cplantbox
def test_matches_cplantbox_geometry():
    # The RSML round trip plus unit/axis conversion must reproduce CPlantBox's own nodes.
    root = simulated_roots("wheat", 1, days=21, seed=3)[0]
    rs = pb.RootSystem()
    rs.readParameters(str(pb.data_path()) + "/structural/rootsystem/wheat.xml")
    rs.setSeed(root.metadata["cplantbox_seed"])
    rs.initialize(False)
    rs.simulate(21.0, False)
    tap = rs.getBaseRoots()[0]
    nodes = np.array([[v.x, v.y, v.z] for v in tap.getNodes()])
    np.testing.assert_allclose(root.main, nodes * np.array([10.0, -10.0, -10.0]), rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(root.main[0], [0.0, 0.0, 30.0], atol=1e-6)
    flip = np.array([10.0, -10.0, -10.0])
    kids = [tap.getChild(k) for k in range(tap.getNumberOfChildren())]
    # One-node children (just emerged, zero length) are written as one point and dropped.
    kids = [c for c in kids if c.getNumberOfNodes() >= 3]
    assert len(kids) >= 5 and root.n_laterals == len(kids)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(root.main, axis=0), axis=1))])
    for lat, a, c in zip(root.laterals, root.attach, kids):
        cnodes = np.array([[v.x, v.y, v.z] for v in c.getNodes()]) * flip
        # Same polyline, starting exactly at its branching node on the main root.
        np.testing.assert_allclose(lat, cnodes, rtol=1e-6, atol=1e-4)
        np.testing.assert_array_equal(lat[0], root.main[c.parentNI])
        assert a == pytest.approx(cum[c.parentNI] / cum[-1], abs=1e-12)


@needs_cplantbox
def test_dim2_is_the_vertical_projection():
    r3 = simulated_roots("lupin", 1, days=10, seed=2)[0]
    r2 = simulated_roots("lupin", 1, days=10, seed=2, dim=2)[0]
    assert r2.dim == 2 and r2.n_laterals == r3.n_laterals > 0
    np.testing.assert_array_equal(r2.main, r3.main[:, [0, 2]])
    for a, b in zip(r2.laterals, r3.laterals):
        np.testing.assert_array_equal(a, b[:, [0, 2]])
    assert _check_on_parent(r2) >= r2.n_laterals
    with pytest.raises(ValueError, match="dim"):
        simulated_roots("lupin", 1, dim=4)


@needs_cplantbox
def test_metadata_describes_converted_coordinates():
    r = simulated_roots("lupin", 1, days=7, seed=0)[0]
    assert r.metadata["parameter_file"] == "Lupinus_albus_Leitner_2014.xml"
    assert r.metadata["cplantbox_seed"] >= 0 and r.metadata["days"] == 7.0
    stack = [r]
    while stack:
        node = stack.pop()
        assert node.metadata["unit"] == "mm"
        assert "resolution" not in node.metadata and "file" not in node.metadata
        stack.extend(node.children)
