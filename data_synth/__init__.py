"""Synthetic textiles and simulated captures of the psmini rig, with ground truth.

``make_fabric(name, ...)`` draws a fabric (height field in mm, albedo, specular weight, cloth mask) at the rig's
scale; :mod:`data_synth.rig` renders it as the rig would see it (near LEDs, vignetting, noise, quantisation,
defocus) with psmini's differentiable renderer, and writes capture folders with their ground truth.
"""

from __future__ import annotations

from data_synth.fabrics import CARD_ALBEDO, FABRICS, Fabric, make_fabric

__all__ = ["CARD_ALBEDO", "FABRICS", "Fabric", "make_fabric"]
