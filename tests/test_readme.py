"""The README's Python example runs as written and does what its comments say."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _example() -> str:
    text = README.read_text()
    start = text.index("```python", text.index("## In Python")) + len("```python")
    return text[start : text.index("```", start)]


@pytest.mark.slow
def test_readme_example_mean_has_the_roots_length_direction_and_unit(tmp_path, monkeypatch):
    from rootshape_jax.io import read_rsml

    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(_example(), "README.md", "exec"), scope)  # noqa: S102 - our own README
    roots, back = scope["roots"], scope["back"]
    rs = scope["rs"]
    # "give it the roots' mean main-root length, put it at the mean seed"
    assert float(rs.curve_length(back.main)) == pytest.approx(np.mean([r.main_length for r in roots]), rel=1e-5)
    np.testing.assert_allclose(np.asarray(back.main[0]), np.mean([r.main[0] for r in roots], axis=0), atol=1e-3)
    # "point the mean's main root like the roots'": their mean direction, to 0.1 degree.
    chords = np.array([r.main[-1] - r.main[0] for r in roots])
    target = np.mean(chords / np.linalg.norm(chords, axis=1)[:, None], axis=0)
    m = np.asarray(back.main[-1] - back.main[0], np.float64)
    cos = m @ target / np.linalg.norm(m) / np.linalg.norm(target)
    assert np.degrees(np.arccos(min(cos, 1.0))) < 0.1
    (mean_root,) = read_rsml(tmp_path / "mean.rsml")
    assert mean_root.metadata["unit"] == roots[0].metadata["unit"]
    assert mean_root.main_length == pytest.approx(float(rs.curve_length(back.main)), rel=1e-4)
