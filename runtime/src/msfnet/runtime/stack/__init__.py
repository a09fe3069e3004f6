"""The photometric stack: its type, loaders, image selection and the DiLiGenT-layout writers."""

from msfnet.runtime.stack.load import (
    LIGHTS_NAMES,
    LoadOptions,
    check_stack_size,
    folder_name,
    linked_reads,
    load_stack,
    prepare_stack,
)
from msfnet.runtime.stack.readers import read_normals, read_vectors
from msfnet.runtime.stack.save import (
    FILENAMES_FILE,
    INTENSITIES_FILE,
    LIGHTS_FILE,
    MASK_FILE,
    NORMALS_FILE,
    filenames_text,
    save_stack,
    write_filenames,
    write_image,
    write_intensities,
    write_lights,
    write_mask,
    write_normals,
)
from msfnet.runtime.stack.select import evenly_spaced, parse_select, selection
from msfnet.runtime.stack.transforms import parse_roi
from msfnet.runtime.stack.types import MIN_LIGHTS, Stack, as_held, held_dtype, unit_lights

__all__ = [
    "FILENAMES_FILE",
    "INTENSITIES_FILE",
    "LIGHTS_FILE",
    "LIGHTS_NAMES",
    "MASK_FILE",
    "MIN_LIGHTS",
    "NORMALS_FILE",
    "LoadOptions",
    "Stack",
    "as_held",
    "check_stack_size",
    "evenly_spaced",
    "filenames_text",
    "folder_name",
    "held_dtype",
    "linked_reads",
    "load_stack",
    "parse_roi",
    "parse_select",
    "prepare_stack",
    "read_normals",
    "read_vectors",
    "save_stack",
    "selection",
    "unit_lights",
    "write_filenames",
    "write_image",
    "write_intensities",
    "write_lights",
    "write_mask",
    "write_normals",
]
