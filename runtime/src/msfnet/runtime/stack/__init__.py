"""The photometric stack: its type, loaders, image selection and the DiLiGenT-layout writer."""

from .load import (
    GT_NAMES,
    INTENSITY_NAMES,
    LIGHTS_NAMES,
    MASK_NAMES,
    LoadOptions,
    check_stack_size,
    load_folder,
    load_npz,
    load_stack,
    prepare_stack,
)
from .readers import read_normals, read_vectors
from .save import save_stack
from .select import evenly_spaced, parse_select, selection
from .transforms import auto_mask, parse_roi
from .types import Stack, as_held, held_dtype, light_condition, unit_lights

__all__ = ["GT_NAMES", "INTENSITY_NAMES", "LIGHTS_NAMES", "MASK_NAMES", "LoadOptions", "Stack",
           "as_held", "auto_mask", "check_stack_size", "evenly_spaced", "held_dtype",
           "light_condition", "load_folder", "load_npz", "load_stack", "parse_roi",
           "parse_select", "prepare_stack", "read_normals", "read_vectors", "save_stack",
           "selection", "unit_lights"]
