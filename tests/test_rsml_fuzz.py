"""Fuzzing `read_rsml` (issue 18 item 9): mutated RSML files give roots, `RSMLError` or
`RSMLWarning` — never another exception or warning.

Seeded (``derandomize=True``) and bounded: 3,000 examples (~10 s) in the default run, 20,000
under ``-m slow``; each example must finish within 5 s. Seeds are small RSML files written here (and the repository's test
fixtures); the real files in ../shared/data are used too when present.
"""

from __future__ import annotations

import datetime
import io
import warnings
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import (  # noqa: E402
    HealthCheck,
    given,
    settings,
    strategies as st,  # noqa: E402
)

from rootshape_jax._errors import RSMLError, RSMLWarning  # noqa: E402
from rootshape_jax._root import Root  # noqa: E402
from rootshape_jax.io import read_rsml, write_rsml  # noqa: E402

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared" / "data" / "rsml"

_HANDWRITTEN = b"""<?xml version="1.0" encoding="UTF-8"?>
<rsml xmlns:po="http://www.plantontology.org/xml-dtd/po.dtd">
  <metadata><version>1</version><unit>inch</unit><resolution>179.0</resolution>
    <time-sequence><label>t</label><index>2</index></time-sequence></metadata>
  <scene>
    <plant ID="1" label="p">
      <root ID="a" label="main" po:accession="PO:0009005">
        <properties><length>4.4</length></properties>
        <geometry><polyline>
          <point x="10" y="0"/><point x="10.5" y="50"/><point x="9" y="120"/><point x="11" y="200"/>
        </polyline></geometry>
        <functions>
          <function name="diameter" domain="polyline">
            <sample>8</sample><sample>7</sample><sample>6</sample><sample>4</sample>
          </function>
        </functions>
        <root ID="b"><properties><parent-node value="1"/></properties>
          <geometry><polyline><Point x="10.5" y="50"/><Point x="40" y="60"/><Point x="70" y="62"/></polyline></geometry>
          <functions><function name="radius" domain="length">
            <sample position="0" value="2"/><sample position="60" value="1"/></function></functions>
          <root ID="c"><geometry><polyline><point x="40" y="60"/><point x="41" y="80"/></polyline></geometry></root>
        </root>
        <root ID="d"><properties><diameter value="3"/></properties>
          <geometry><polyline><point><x>9</x><y>120</y></point><point><x>-20</x><y>130</y></point></polyline></geometry>
        </root>
      </root>
    </plant>
    <plant ID="2"><root ID="e"><geometry><polyline><point x="0" y="0" z="0"/><point x="1" y="9" z="2"/></polyline></geometry>
      <functions><function name="diameter" domain="uniform"><sample>2</sample><sample>1</sample><sample>1</sample></function></functions>
    </root></plant>
  </scene>
</rsml>
"""

# Fragments that exercise the reader's edge cases when spliced in anywhere.
_SNIPPETS = [
    b"<root>",
    b"</root>",
    b"<root/>",
    b"<root ID=''>",
    b"<geometry>",
    b"</geometry>",
    b"<polyline>",
    b"</polyline>",
    b'<point x="1" y="2"/>',
    b'<point x="1e300" y="0"/>',
    b'<point x="nan" y="inf"/>',
    b'<point x="1" y="2" z="3"/>',
    b'<point y="1"/>',
    b'<function name="diameter" domain="length">',
    b'<function name="radius" domain="uniform">',
    b'<function name="diameter" domain="weird">',
    b"</function>",
    b"<sample>-1</sample>",
    b'<sample position="x">1</sample>',
    b"<sample>1e309</sample>",
    b'<parent-node value="99"/>',
    b'<parent-node value="-3"/>',
    b"<parent-node>1.5</parent-node>",
    b'<diameter value="-2"/>',
    b"<resolution>0</resolution>",
    b"<resolution>1e-300</resolution>",
    b"<unit>mm</unit>",
    b"<unit></unit>",
    b"<plant>",
    b"</plant>",
    b"<scene>",
    b"</scene>",
    b"&amp;",
    b"&bogus;",
    b"<!DOCTYPE rsml>",
    b'<!ENTITY a "b">',
    b"<![CDATA[x]]>",
    b"<!-- c -->",
    b"<?pi x?>",
    b"\x00",
    b"\xff\xfe",
    b"\xc3\x28",
    b"\xe2\x82",
    b"9" * 5000,
    b"-",
    b".",
    b"e",
    b'"',
    b"'",
    b"<",
    b">",
    b"=",
    b" ",
]


def _written_seed() -> bytes:
    """A file from `write_rsml`: 3D, several plants, radii, deeper orders."""
    rng = np.random.default_rng(7)
    roots = []
    for i in range(2):
        main = np.cumsum(rng.normal(size=(6, 3)) + [0, 0, 3], axis=0)
        lats = tuple(main[j] + np.cumsum(rng.normal(size=(4, 3)), axis=0) for j in (1, 3))
        lats = tuple(np.vstack([main[j], lat]) for j, lat in zip((1, 3), lats))
        roots.append(
            Root(
                main=main,
                laterals=lats,
                name=f"r{i}",
                metadata={"plant_id": str(i % 2)},
                main_radius=rng.uniform(0.1, 1, 6),
                lateral_radii=tuple(rng.uniform(0.1, 1, 5) for _ in lats),
            )
        )
    buf = io.BytesIO()
    write_rsml(roots, buf, unit="mm", resolution=10.0)
    return buf.getvalue()


def _shrunk(path: Path) -> bytes:
    """A real file cut down to stay fast to read: its first plant, the first 3 child roots of
    every root (recursively), every function and property kept, and its own namespaces."""
    import xml.etree.ElementTree as ET

    tree = ET.parse(path)
    scene = next(e for e in tree.getroot() if e.tag.lower().endswith("scene"))
    for plant in list(scene)[1:]:
        scene.remove(plant)
    stack = list(scene)
    while stack:
        el = stack.pop()
        roots = [c for c in el if c.tag.lower().endswith("root")]
        for c in roots[3:]:
            el.remove(c)
        stack.extend(roots[:3] if el.tag.lower().endswith("root") else list(el))
    return ET.tostring(tree.getroot())


def _seeds(real: bool) -> list[bytes]:
    seeds = [_HANDWRITTEN, _written_seed()]
    seeds += [p.read_bytes() for p in sorted((HERE / "data" / "rsml").glob("*.rsml"))]
    if real and SHARED.is_dir():
        seeds += [_shrunk(p) for p in sorted(SHARED.glob("*/*.rsml"))]
    return seeds


_NUMBERS = [b"0", b"-0", b"1e308", b"-1e308", b"1e-320", b"nan", b"-inf", b"", b"12abc", b"0x10", b"1_000"]

# Mutations that often keep the XML well-formed (so the reader's logic is reached) ...
_gentle = st.one_of(
    st.tuples(st.just("number"), st.floats(0, 1), st.sampled_from(_NUMBERS)),
    st.tuples(st.just("after_tag"), st.floats(0, 1), st.sampled_from(_SNIPPETS)),
    st.tuples(st.just("drop_tag"), st.floats(0, 1), st.just(b"")),
    st.tuples(st.just("duplicate_tag"), st.floats(0, 1), st.integers(1, 3)),
)
# ... and raw byte damage.
_raw = st.one_of(
    st.tuples(st.just("delete"), st.floats(0, 1), st.integers(1, 200)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.sampled_from(_SNIPPETS)),
    st.tuples(st.just("bytes"), st.floats(0, 1), st.binary(min_size=1, max_size=8)),
    st.tuples(st.just("duplicate"), st.floats(0, 1), st.integers(1, 400)),
    st.tuples(st.just("truncate"), st.floats(0, 1), st.just(b"")),
)
_mutations = st.builds(lambda a, b: a + b, st.lists(_gentle, min_size=1, max_size=4), st.lists(_raw, max_size=1))


def _mutate(data: bytes, mutations) -> bytes:
    buf = bytearray(data)
    for kind, where, arg in mutations:
        i = int(where * len(buf))
        if kind == "delete":
            del buf[i : i + arg]
        elif kind in ("insert", "bytes"):
            buf[i:i] = arg
        elif kind == "after_tag":  # keeps the file well-formed more often
            j = buf.find(b">", i)
            if j >= 0:
                buf[j + 1 : j + 1] = arg
        elif kind == "duplicate_tag":  # repeat one whole tag <...> (e.g. a point or a <root>)
            j = buf.find(b"<", i)
            k = buf.find(b">", j)
            if 0 <= j < k:
                buf[j:j] = buf[j : k + 1] * arg
        elif kind == "drop_tag":  # delete one whole tag <...>
            j = buf.find(b"<", i)
            k = buf.find(b">", j)
            if 0 <= j < k:
                del buf[j : k + 1]
        elif kind == "duplicate":
            buf[i:i] = buf[i : i + arg]
        elif kind == "number":
            # Replace the next number after i (an attribute value or element text).
            j = i
            while j < len(buf) and not (48 <= buf[j] <= 57):
                j += 1
            k = j
            while k < len(buf) and (48 <= buf[k] <= 57 or buf[k] in b".-+eE"):
                k += 1
            buf[j:k] = arg
        elif kind == "truncate":
            del buf[i:]
    return bytes(buf)


def _check_read(data: bytes, strict: bool, physical: bool) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            roots = read_rsml(io.BytesIO(data), strict=strict, physical_units=physical)
        except RSMLError:
            roots = []
    others = [w for w in caught if not issubclass(w.category, RSMLWarning)]
    assert not others, f"unexpected warnings: {[str(w.message) for w in others]}"
    for r in roots:  # whatever comes out is a valid Root
        assert isinstance(r, Root) and np.all(np.isfinite(r.main)) and np.isfinite(r.main_length)
        assert all(np.isfinite(lat).all() for lat in r.laterals)
        if r.main_radius is not None:
            assert np.all(r.main_radius >= 0) and np.all(np.isfinite(r.main_radius))


def _fuzz(real: bool, n: int):
    seeds = _seeds(real)

    @settings(
        # A mutated file that takes seconds to read is a bug too (e.g. an expansion blow-up):
        # each example has a 5 s deadline (they take ~3 ms).
        max_examples=n,
        derandomize=True,
        deadline=datetime.timedelta(seconds=5),
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(
        seed=st.integers(0, len(seeds) - 1),
        mutations=_mutations,
        strict=st.booleans(),
        physical=st.booleans(),
    )
    def run(seed, mutations, strict, physical):
        _check_read(_mutate(seeds[seed], mutations), strict, physical)

    run()


def test_seeds_read_cleanly():
    """The unmutated seeds are readable (so mutations start from meaningful files)."""
    for data in (_HANDWRITTEN, _written_seed()):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            roots = read_rsml(io.BytesIO(data))
        assert roots and any(r.main_radius is not None for r in roots)


def test_fuzz_read_rsml():
    _fuzz(real=True, n=3000)  # ~10 s


@pytest.mark.slow
def test_fuzz_read_rsml_long():
    _fuzz(real=True, n=20000)


def test_cli_on_a_folder_of_mutated_files_keeps_going_and_summarises(tmp_path):
    """`rootshape traits FOLDER` on seeded mutations of real-format files: exit 0, no traceback,
    every bad file named once, a summary line, and the readable roots' traits written."""
    import random
    import subprocess
    import sys

    from rootshape_jax.datasets import synthetic_roots
    from rootshape_jax.io import write_rsml

    folder = tmp_path / "mutated"
    folder.mkdir()
    good = tmp_path / "good.rsml"
    write_rsml(synthetic_roots(2, seed=3), good)
    data = good.read_bytes()
    rng = random.Random(0)
    kinds = ["delete", "insert", "bytes", "truncate", "drop_tag", "duplicate_tag", "number"]
    for k in range(12):
        muts = []
        for _ in range(rng.randint(1, 3)):
            kind = rng.choice(kinds)
            arg = {
                "delete": rng.randint(1, 200),
                "insert": b"<root>",
                "bytes": bytes([rng.randrange(256)]),
                "truncate": b"",
                "drop_tag": b"",
                "duplicate_tag": rng.randint(1, 3),
                "number": rng.choice([b"nan", b"1e300", b"-", b"7"]),
            }[kind]
            muts.append((kind, rng.random(), arg))
        (folder / f"m{k:02d}.rsml").write_bytes(_mutate(data, muts))
    (folder / "z_good.rsml").write_bytes(data)
    out = tmp_path / "o"
    proc = subprocess.run(
        [sys.executable, "-m", "rootshape_jax", "traits", str(folder), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    summary = proc.stdout.strip().splitlines()[-1]
    import re as _re

    m = _re.match(r"read (\d+) root system\(s\) from (\d+) file\(s\)(?:; skipped (\d+): (.*))?", summary)
    assert m, summary
    n_read, n_skipped = int(m.group(2)), int(m.group(3) or 0)
    assert n_read + n_skipped == 13 and n_read >= 1, summary
    # Each problem file is named on one stderr line at most.
    for k in range(12):
        assert len([ln for ln in proc.stderr.splitlines() if f"m{k:02d}.rsml" in ln]) <= 1
    assert (out / "traits.csv").exists()
