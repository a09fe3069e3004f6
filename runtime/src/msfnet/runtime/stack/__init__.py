"""The photometric stack: its type, loaders, image selection and the DiLiGenT-layout writers."""

from msfnet.runtime.stack.load import GT_NAMES, INTENSITY_NAMES, LIGHTS_NAMES, MASK_NAMES, LoadOptions, check_stack_size, load_folder, load_npz, load_stack, prepare_stack
from msfnet.runtime.stack.readers import read_normals, read_vectors
from msfnet.runtime.stack.save import FILENAMES_FILE, INTENSITIES_FILE, LIGHTS_FILE, MASK_FILE, NORMALS_FILE, filenames_text, save_stack, write_filenames, write_image, write_intensities, write_lights, write_mask, write_normals
from msfnet.runtime.stack.select import evenly_spaced, parse_select, selection
from msfnet.runtime.stack.transforms import auto_mask, parse_roi
from msfnet.runtime.stack.types import Stack, as_held, held_dtype, light_condition, unit_lights

__all__ = ["FILENAMES_FILE", "GT_NAMES", "INTENSITIES_FILE", "INTENSITY_NAMES", "LIGHTS_FILE",
           "LIGHTS_NAMES", "MASK_FILE", "MASK_NAMES", "NORMALS_FILE", "LoadOptions", "Stack",
           "as_held", "auto_mask", "check_stack_size", "evenly_spaced", "filenames_text",
           "held_dtype", "light_condition", "load_folder", "load_npz", "load_stack",
           "parse_roi", "parse_select", "prepare_stack", "read_normals", "read_vectors",
           "save_stack", "selection", "unit_lights", "write_filenames", "write_image",
           "write_intensities", "write_lights", "write_mask", "write_normals"]
