"""Fabric structure: ISO 25178-2 areal parameters and the textile's yarn systems, from height and albedo maps."""

from __future__ import annotations

from psmini.fabric.surface import (ISO_PARAMETERS, ISO_UNITS, SurfaceOptions, autocorrelation, gaussian_filter,
                                   height_parameters, hybrid_parameters, iso25178, remove_form,
                                   scale_limited_surface, spatial_parameters, valid_pixels)

__all__ = ["ISO_PARAMETERS", "ISO_UNITS", "SurfaceOptions", "autocorrelation", "gaussian_filter",
           "height_parameters", "hybrid_parameters", "iso25178", "remove_form", "scale_limited_surface",
           "spatial_parameters", "valid_pixels"]
from psmini.fabric.structure import FabricStructure, SpectralPeak, StructureOptions, fabric_structure, structure_spectrum

__all__ += ["FabricStructure", "SpectralPeak", "StructureOptions", "fabric_structure", "structure_spectrum"]
