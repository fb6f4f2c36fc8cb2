"""Comparison methods named by the paper, re-implemented from their published descriptions.

- QED tree-shape space (Feragen et al. 2010, 2013): father–child edges as landmark vectors,
  Euclidean distance / straight-line geodesic / mean for a fixed correspondence.
- Father–child elastic SRVF edges (Wang et al. 2018): the same topology, each edge an SRVF
  registered by the exact DP warp.
- Zhang–Shasha tree edit distance on the ordered father–child topology (edge lengths as labels).
- TMD (Kanari et al. 2018): persistence barcode of the radial-distance filtration (`tmd`
  package, ``bench`` extra) and the persistence-image distance.
- `geodesic_shrinkage`: total-length shrinkage along any path of roots.

Every method takes `rootshape_jax.Root` objects and matches laterals by their order along the
main root (no correspondence search, no rotation): align roots first if needed. See each
module's docstring for the exact definitions and references.
"""

from ._fc_srvf import (
    fc_srvf_distance as fc_srvf_distance,
    fc_srvf_distance_matrix as fc_srvf_distance_matrix,
    fc_srvf_geodesic as fc_srvf_geodesic,
    fc_srvf_mean as fc_srvf_mean,
)
from ._qed import (
    qed_distance as qed_distance,
    qed_distance_matrix as qed_distance_matrix,
    qed_geodesic as qed_geodesic,
    qed_mean as qed_mean,
    qed_vectors as qed_vectors,
)
from ._shrinkage import Shrinkage as Shrinkage, geodesic_shrinkage as geodesic_shrinkage
from ._ted import (
    edit_tree as edit_tree,
    tree_edit_distance as tree_edit_distance,
    tree_edit_distance_matrix as tree_edit_distance_matrix,
)
from ._tmd import (
    TMDImages as TMDImages,
    tmd_barcode as tmd_barcode,
    tmd_distance_matrix as tmd_distance_matrix,
    tmd_images as tmd_images,
    to_tmd_tree as to_tmd_tree,
)
