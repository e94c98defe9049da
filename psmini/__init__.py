"""psmini: differentiable, GPU-optional photometric stereo for close-range imaging of textiles.

The public API. Every stage of the data flow is a functional on batched torch tensors with a thin
``nn.Module`` beside it where state belongs; see DESIGN.md for shapes, axes and units.
"""

from __future__ import annotations

__version__ = "0.1.0"

from psmini.errors import CalibrationError, DataFormatError, InputError, PsminiError, RigError, ShapeError
from psmini.integrate import METHODS as INTEGRATION_METHODS
from psmini.integrate import FrankotChellappa, frankot_chellappa, integrate
from psmini.lights import DirectionalLights, LEDLights, PointLights, as_batched_lights, check_spans_3d, ring_lights

__all__ = [
    "__version__",
    # errors
    "PsminiError",
    "InputError",
    "ShapeError",
    "CalibrationError",
    "DataFormatError",
    "RigError",
    # lights
    "ring_lights",
    "check_spans_3d",
    "as_batched_lights",
    "DirectionalLights",
    "PointLights",
    "LEDLights",
    # integration
    "integrate",
    "INTEGRATION_METHODS",
    "frankot_chellappa",
    "FrankotChellappa",
]
