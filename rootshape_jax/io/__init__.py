"""Reading and writing root systems: RSML files, folders, scanned images, metadata tables."""

from .._root import is_plant_system as is_plant_system
from ._compare import (
    PlantComparison as PlantComparison,
    TracingComparison as TracingComparison,
    compare_to_tracing as compare_to_tracing,
    total_length as total_length,
)
from ._extract_cli import extract_images as extract_images
from ._folder import (
    IMAGE_SUFFIXES as IMAGE_SUFFIXES,
    RSML_SUFFIXES as RSML_SUFFIXES,
    ReadReport as ReadReport,
    read_folder as read_folder,
    read_paths as read_paths,
    read_root_file as read_root_file,
    root_files as root_files,
    short_reason as short_reason,
)
from ._image import roots_from_image as roots_from_image
from ._metadata import (
    MetadataTable as MetadataTable,
    attach_metadata as attach_metadata,
    labels_of as labels_of,
    read_metadata as read_metadata,
)
from ._rsml import (
    plant_system as plant_system,
    read_rsml as read_rsml,
    write_rsml as write_rsml,
)
from ._units import (
    NORMALISED_UNIT as NORMALISED_UNIT,
    convert_units as convert_units,
    unit_label as unit_label,
)
