"""Input and output around the core: images (16-bit safe), DiLiGenT folders, psmini capture folders, exports.

Nothing in the core imports this package; it turns files into the tensors the core expects (``Sample``) and
reconstructions back into files. Formats: ``docs/capture-format.md`` and ``docs/file-formats.md``.
"""

from __future__ import annotations

from psmini.io.capture import (
    Capture,
    lights_from_dict,
    lights_to_dict,
    read_capture,
    read_manifest,
    write_capture,
)
from psmini.io.diligent import is_diligent_folder, read_diligent
from psmini.io.export import (
    read_normal_png,
    robust_max,
    save_albedo_png,
    save_depth,
    save_mesh_ply,
    save_normal_png,
    save_normal_std,
    save_ply,
    write_outputs,
)
from psmini.io.images import (
    DILIGENT_GRAY_WEIGHTS,
    read_gray,
    read_image,
    read_image_raw,
    read_image_stack,
    read_image_tensor,
    rgb_to_gray,
    write_image,
)
from psmini.io.lightsfile import LightsFile, read_lights_file, with_lights_file, write_lights_file
from psmini.io.load import SampleScan, find_samples, load_sample, scan_samples
from psmini.io.matfile import read_mat
from psmini.io.rigfiles import load_rig_calibration_mat, write_flatfield_capture
from psmini.io.sample import Sample

__all__ = [
    # images
    "DILIGENT_GRAY_WEIGHTS",
    "read_image",
    "read_image_raw",
    "read_image_tensor",
    "read_gray",
    "read_image_stack",
    "rgb_to_gray",
    "write_image",
    "read_mat",
    # samples
    "Sample",
    "load_sample",
    "find_samples",
    "scan_samples",
    "SampleScan",
    "read_diligent",
    "is_diligent_folder",
    # capture folders
    "Capture",
    "read_capture",
    "read_manifest",
    "write_capture",
    "lights_to_dict",
    "lights_from_dict",
    # calibration files
    "LightsFile",
    "read_lights_file",
    "write_lights_file",
    "with_lights_file",
    "write_flatfield_capture",
    "load_rig_calibration_mat",
    # export
    "robust_max",
    "save_albedo_png",
    "read_normal_png",
    "save_normal_png",
    "save_mesh_ply",
    "save_depth",
    "save_ply",
    "save_normal_std",
    "write_outputs",
]
