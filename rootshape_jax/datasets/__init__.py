"""Example root populations: synthetic (built in) and simulated (CPlantBox, optional extra)."""

from ._simulated import available_species as available_species, simulated_roots as simulated_roots
from ._synthetic import (
    CONDITIONS as CONDITIONS,
    DEFAULT_COMPOSITION as DEFAULT_COMPOSITION,
    RootParameters as RootParameters,
    default_dataset as default_dataset,
    synthetic_roots as synthetic_roots,
)
