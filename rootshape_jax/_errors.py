"""The library's small exception hierarchy.

Every error a user can trigger with bad input derives from :class:`RootShapeError` and from
``ValueError``, so ``except ValueError`` keeps working for callers that do not know our types.
"""


class RootShapeError(Exception):
    """Base class of every error raised on purpose by rootshape_jax."""


class InvalidRootError(RootShapeError, ValueError):
    """A root (or a curve, or a tree) is not valid input: too few points, NaN/inf, wrong shape."""


class CoordinateRangeError(InvalidRootError):
    """Coordinates so large that squared lengths overflow the working float precision."""


class CapacityError(InvalidRootError):
    """A root has more laterals than the padded capacity ``K`` (or more points than ``T``), or a
    branch has more children than the capacity ``Kℓ`` of its level (`batch(max_children=...)`)."""


class RSMLError(RootShapeError, ValueError):
    """An RSML file is malformed, or one of its roots cannot be read."""


class ImageError(RootShapeError, ValueError):
    """A scanned image cannot be turned into roots (empty, wrong dimensions, no root found)."""


class InputError(RootShapeError, ValueError):
    """An input path cannot be used: missing, an empty folder, or an unsupported file type."""


class MetadataError(RootShapeError, ValueError):
    """A metadata table does not fit the roots: a root without a row, duplicate rows, a missing
    or reserved column, or a label asked for that the table does not have."""


class UnitError(RootShapeError, ValueError):
    """Coordinates cannot be converted to the requested unit (unknown unit, or pixels without
    a resolution), or roots in different units meet where sizes are compared or written."""


class MissingDependencyError(RootShapeError, ImportError):
    """An optional extra (``pip install 'rootshape_jax[EXTRA]'``) is needed for this feature."""


class InvalidCostError(RootShapeError, ValueError):
    """A cost matrix handed to the assignment solver has the wrong shape or dtype."""


class StoreMismatchError(RootShapeError, ValueError):
    """A `store=` directory holds blocks of another run (other inputs, options or block size)."""


class ConvergenceError(RootShapeError, RuntimeError):
    """An iterative solver stopped at its step limit with ``throw=True``; raise `max_steps`,
    loosen the tolerance, or pass ``throw=False`` and check the result's status."""


class RSMLWarning(UserWarning):
    """Part of an RSML file was skipped (non-strict reading): the message names file and root."""


class MissingRadiusWarning(UserWarning):
    """Some roots of a batch have radii (diameters) and others not: theirs are taken as 0; or
    the metric weighs thickness on trees without any radii, where that weight has no effect.

    It matters only when the metric weighs thickness; filter it by this class otherwise."""


class ExtrapolationWarning(UserWarning):
    """`TraitRegression.synthesize` was asked for trait values far outside its training roots'
    (more than 3 standard deviations from their mean): the linear model extrapolates there."""


class LabelError(RootShapeError, ValueError):
    """Labels unusable for learning or cross-validation: wrong length, missing (NaN) values, a
    single class, or a class too small for a same-class neighbour or for the folds."""


def as_count(value, name: str, *, minimum: int = 1) -> int:
    """`value` as a Python int >= `minimum` (numpy integers accepted, bools and floats not);
    `ValueError` naming `name` otherwise."""
    import numbers

    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}.")
    return int(value)


def require_labels_present(values) -> None:
    """`LabelError` naming the roots whose label is missing (None or NaN): such a label would
    otherwise be a class of its own. `values`: the labels as Python objects."""
    missing = [i for i, v in enumerate(values) if v is None or (isinstance(v, float) and v != v)]
    if missing:
        raise LabelError(
            f"labels of roots {missing[:10]} are missing (NaN or None); drop those roots or give them a label."
        )


def is_real_scalar(value, kinds: str = "iuf") -> bool:
    """True for one real number (Python, numpy or a concrete JAX scalar) whose dtype kind is
    in `kinds` ("iu": integers); False for bools, strings, arrays of more than one value."""
    import numpy as np

    if isinstance(value, (bool, np.bool_)) or np.ndim(value) != 0:
        return False
    return np.asarray(value).dtype.kind in kinds


def as_flag(value, name: str) -> bool:
    """`value` as a bool (numpy bools accepted); `TypeError` naming `name` otherwise: a string
    such as "False" is truthy and would silently mean True."""
    import numpy as np

    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {value!r}.")
    return bool(value)


def require_finite_values(x, what: str):
    """`x` unchanged when finite. A concrete array holding NaN or inf raises `InputError`
    naming `what`; a traced one gets an `eqx.error_if` (raised when the program runs)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    if isinstance(x, jax.core.Tracer):
        return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), f"{what} contains NaN or inf.")
    a = np.asarray(x)
    if a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
        raise InputError(f"{what} contains NaN or inf ({int(np.sum(~np.isfinite(a)))} of {a.size} values).")
    return x


def user_stacklevel() -> int:
    """The `stacklevel` that attributes a warning to the first caller outside rootshape_jax;
    pass it from the function that calls `warnings.warn`. A fixed level pointed inside the
    package when a public call reached the warning through another path (e.g. ``distance`` →
    ``to_srvf``), and the "once per line" filter then merged the warnings of different calls."""
    import os
    import sys

    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        frame, level = frame.f_back, level + 1
    return level
