"""Fabric structure: what the cloth is, not only its shape.

ISO 25178-2 areal parameters on the scale-limited surface (:mod:`psmini.fabric.surface`), the yarn systems'
directions and densities, the weave repeat, crimp and openness from the height spectrum
(:mod:`psmini.fabric.structure`), and the descriptors and code-free classifier built on them
(:mod:`psmini.fabric.describe`). Batched :math:`(B, 1, H, W)` heights in mm, CPU or CUDA, float32 or float64.
"""

from __future__ import annotations

from psmini.fabric.describe import (
    COUPLING_OPTIONS,
    DESCRIBE_SURFACE_OPTIONS,
    DESCRIPTOR_NAMES,
    MODEL_FORMAT,
    MODEL_VERSION,
    FabricClassifier,
    albedo_periodicity,
    albedo_relief_coupling,
    describe,
    describe_reconstruction,
    describe_surface_options,
    descriptor_vector,
    reconstruct_for_description,
    structure_row,
    structure_surface,
)
from psmini.fabric.structure import (
    FabricStructure,
    SpectralPeak,
    StructureOptions,
    fabric_structure,
    structure_spectrum,
)
from psmini.fabric.surface import (
    ISO_PARAMETERS,
    ISO_UNITS,
    SurfaceOptions,
    autocorrelation,
    gaussian_filter,
    height_parameters,
    hybrid_parameters,
    iso25178,
    iso_s_cutoff_mm,
    remove_form,
    scale_limited_surface,
    spatial_parameters,
    valid_pixels,
)

__all__ = [
    "ISO_PARAMETERS", "ISO_UNITS", "SurfaceOptions", "autocorrelation", "gaussian_filter", "height_parameters",
    "hybrid_parameters", "iso25178", "iso_s_cutoff_mm", "remove_form", "scale_limited_surface",
    "spatial_parameters", "valid_pixels",
    "FabricStructure", "SpectralPeak", "StructureOptions", "fabric_structure", "structure_spectrum",
    "COUPLING_OPTIONS", "albedo_periodicity", "albedo_relief_coupling", "DESCRIBE_SURFACE_OPTIONS",
    "DESCRIPTOR_NAMES", "MODEL_FORMAT", "MODEL_VERSION", "FabricClassifier", "describe", "describe_reconstruction",
    "describe_surface_options", "descriptor_vector", "reconstruct_for_description", "structure_row",
    "structure_surface",
]
