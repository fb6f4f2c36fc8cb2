"""Plots of roots and of analysis results (matplotlib).

The functions draw results; they compute no registrations. Every function returns the figure
(and its Axes) and never shows it; save with ``fig.savefig("name.png")``. Importing this
package does not choose a matplotlib backend and needs no display: figures are plain
`matplotlib.figure.Figure` objects, or pyplot figures when you imported `matplotlib.pyplot`
yourself (so notebooks display them).

Depth points down by default (``invert_y=True``: image convention, root base at the top);
lateral slot ``k`` has the same colour (`slot_color(k)`) in every plot, and a deeper branch a
shade of its parent's (`branch_color`).
"""

from .._errors import MissingDependencyError

try:
    import matplotlib as _matplotlib  # noqa: F401
except ImportError as _e:  # pragma: no cover - exercised by a test that hides matplotlib
    raise MissingDependencyError(
        "rootshape_jax.plot needs matplotlib (>= 3.8), a core dependency of rootshape_jax that "
        "is missing from this environment: pip install 'matplotlib>=3.8' (or reinstall "
        f"rootshape_jax). Import failed with: {_e}"
    ) from _e

del _matplotlib

from ._clusters import (
    plot_dendrogram as plot_dendrogram,
    plot_distance_matrix as plot_distance_matrix,
)
from ._diagnostics import (
    plot_energy_trace as plot_energy_trace,
    plot_explained_variance as plot_explained_variance,
)
from ._draw import branch_color as branch_color, slot_color as slot_color
from ._labels import (
    label_colors as label_colors,
    plot_mds as plot_mds,
    plot_pca_scores as plot_pca_scores,
)
from ._roots import (
    plot_geodesic as plot_geodesic,
    plot_mean as plot_mean,
    plot_modes as plot_modes,
    plot_regression_sweep as plot_regression_sweep,
    plot_root as plot_root,
    plot_samples_by_distance as plot_samples_by_distance,
)
