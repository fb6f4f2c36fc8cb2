"""Reading and writing root systems: RSML files and scanned images."""

from ._compare import (
    PlantComparison as PlantComparison,
    TracingComparison as TracingComparison,
    compare_to_tracing as compare_to_tracing,
    total_length as total_length,
)
from ._extract_cli import extract_images as extract_images
from ._image import roots_from_image as roots_from_image
from ._rsml import read_rsml as read_rsml, write_rsml as write_rsml
