"""rootshape_jax: statistical shape analysis of plant root systems, in JAX.

A root is a main root plus first-order laterals; each branch is an SRVF and the tree is padded
with null laterals to fixed capacities, so the elastic metric, registration, distance matrices
and Karcher means are jit/vmap-compiled. See README.md and docs/architecture.md.
"""

from . import _early_interrupt

if _early_interrupt.is_the_program():  # the `rootshape` program: Ctrl-C while JAX loads ends it
    _early_interrupt.end_on_ctrl_c()

from ._assignment import (
    assignment_cost as assignment_cost,
    linear_assignment as linear_assignment,
)
from ._cluster import (
    Clustering as Clustering,
    cluster as cluster,
    confusion_matrix as confusion_matrix,
    contingency_table as contingency_table,
    loo_accuracy as loo_accuracy,
)
from ._curves import (
    curve_length as curve_length,
    l2_norm_squared as l2_norm_squared,
    resample_curve as resample_curve,
    srvf as srvf,
    srvf_to_curve as srvf_to_curve,
)
from ._elastic import (
    CurveRegistration as CurveRegistration,
    elastic_curve_distance as elastic_curve_distance,
    elastic_curve_distances as elastic_curve_distances,
)
from ._engine import (
    MEAN_REGISTRATION as MEAN_REGISTRATION,
    Registration as Registration,
    RegistrationOptions as RegistrationOptions,
)
from ._errors import (
    CapacityError as CapacityError,
    ConvergenceError as ConvergenceError,
    CoordinateRangeError as CoordinateRangeError,
    ExtrapolationWarning as ExtrapolationWarning,
    ImageError as ImageError,
    InputError as InputError,
    InvalidCostError as InvalidCostError,
    InvalidRootError as InvalidRootError,
    LabelError as LabelError,
    MetadataError as MetadataError,
    MissingDependencyError as MissingDependencyError,
    MissingRadiusWarning as MissingRadiusWarning,
    RootShapeError as RootShapeError,
    RSMLError as RSMLError,
    RSMLWarning as RSMLWarning,
    StoreMismatchError as StoreMismatchError,
    UnitError as UnitError,
)
from ._geodesic import geodesic as geodesic
from ._groups import PairTest as PairTest, holm as holm, pairwise_permanova as pairwise_permanova
from ._learn import (
    CVAccuracy as CVAccuracy,
    FoldTest as FoldTest,
    LearnedWeights as LearnedWeights,
    fold_accuracy as fold_accuracy,
    fold_t_test as fold_t_test,
    held_out_log_loss as held_out_log_loss,
    learn_weights as learn_weights,
    nested_cv_accuracy as nested_cv_accuracy,
)
from ._mds import MDS as MDS, mds as mds
from ._mean import (
    KarcherMean as KarcherMean,
    karcher_mean as karcher_mean,
    karcher_objective as karcher_objective,
)
from ._metric import (
    TERMS as TERMS,
    MetricTerms as MetricTerms,
    Weights as Weights,
    preshape_distance_squared as preshape_distance_squared,
)
from ._pairwise import (
    cross_distances as cross_distances,
    pairwise_distances as pairwise_distances,
)
from ._pca import (
    TangentPCA as TangentPCA,
    modes as modes,
    project as project,
    reconstruct as reconstruct,
    sample as sample,
    tangent_pca as tangent_pca,
)
from ._permanova import Permanova as Permanova, permanova as permanova
from ._plausibility import Plausibility as Plausibility, plausibility as plausibility
from ._registration import distance as distance, register as register
from ._regression import TraitRegression as TraitRegression
from ._root import Root as Root, limit_laterals as limit_laterals
from ._rotation import optimal_rotation as optimal_rotation
from ._serialise import load as load, save as save
from ._traits import trait_column as trait_column, traits as traits, traits_to_csv as traits_to_csv
from ._tree import (
    BranchLevel as BranchLevel,
    RootTree as RootTree,
    SRVFLevel as SRVFLevel,
    SRVFTree as SRVFTree,
    batch as batch,
    normalising_length as normalising_length,
    scale_tree as scale_tree,
    stack as stack,
    to_curves as to_curves,
    to_roots as to_roots,
    to_srvf as to_srvf,
    turn_about_base as turn_about_base,
    unstack as unstack,
    upright_rotation as upright_rotation,
)
from ._warp import (
    apply_warp_curve as apply_warp_curve,
    apply_warp_srvf as apply_warp_srvf,
    dp_warp as dp_warp,
    dp_warp_batch as dp_warp_batch,
)

__version__ = "0.1.0"
from . import (
    _dask,  # noqa: F401  (registers the Dask executor for client=; imports no Dask)
    baselines as baselines,
)
from ._devices import use_all_cores as use_all_cores
from ._executor import LocalExecutor as LocalExecutor
from .baselines import Shrinkage as Shrinkage, geodesic_shrinkage as geodesic_shrinkage
