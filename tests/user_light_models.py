"""Light models written as a user would, outside psmini, with its public API only (the tests of issue 45's
"extensible" part use them; tests copy this file's text into a temporary folder to read it back in a fresh process).

- :class:`TabulatedBeamLEDs`: a measured beam: a (K, N) table of relative irradiance against the angle off each LED's
  axis, linearly interpolated, over the squared distance.
- :class:`GaussianBeamLEDs`: a subclass of psmini's ``LEDLights`` that overrides ``forward`` with a Gaussian beam.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from psmini.lights import LEDLights, LightField, LightModel, PointLights


def _unit(x: Tensor) -> Tensor:
    return x / x.square().sum(dim=-1, keepdim=True).sqrt()


class TabulatedBeamLEDs(LightModel):
    r"""LEDs whose beam is a table: irradiance :math:`T_k(\theta) / r^2`, with :math:`\theta` the angle between the
    LED's axis and the ray to the point, :math:`T_k` linear between samples :math:`\theta_i = i \cdot` ``step_deg``,
    and 0 beyond the last one.

    Args:
        positions_mm: LED positions, (K, 3), mm.
        principal_directions: the LEDs' axes, (K, 3) (any length).
        step_deg: the table's angular step per LED, (K,), degrees.
        beam: the table, (K, N): irradiance at 1 mm on the rays at 0, step, 2 step, ... degrees off the axis.
        learnable: positions, axes and table as ``nn.Parameter`` s.
    """

    # no kind: it is this class's import path, which a fresh process can import
    fields = {
        "positions_mm": LightField((3,)),
        "principal_directions": LightField((3,)),
        "step_deg": LightField(()),
        "beam": LightField((None,)),
    }

    def __init__(self, positions_mm: Tensor, principal_directions: Tensor, step_deg: Tensor, beam: Tensor,
                 learnable: bool = False) -> None:
        super().__init__()

        def keep(x: Tensor) -> Tensor:
            return nn.Parameter(x.detach().clone()) if learnable else x

        self.positions_mm = keep(positions_mm)
        self.principal_directions = keep(principal_directions)
        self.beam = keep(beam)
        self.step_deg = step_deg  # held: the table's abscissae

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor]:
        offsets = self.positions_mm.to(points)[None, :, :, None, None] - points[:, None]  # (B, K, 3, H, W)
        squared = offsets.square().sum(dim=2, keepdim=True)                               # (B, K, 1, H, W)
        to_light = offsets / squared.sqrt()
        axis = _unit(self.principal_directions.to(points))[None, :, :, None, None]
        cosine = -(to_light * axis).sum(dim=2, keepdim=True)
        # the angle from its cosine and sine: acos loses precision near the axis, and its slope is infinite on it
        sine = (1 - cosine.square()).clamp_min(torch.finfo(points.dtype).tiny).sqrt()
        angle = torch.atan2(sine, cosine)
        beam = self.beam.to(points)
        count, samples = beam.shape
        position = angle / torch.deg2rad(self.step_deg.to(points))[None, :, None, None, None]
        lower = position.detach().floor().clamp(0, samples - 2)
        weight = position - lower                                       # in [0, 1] inside the table
        index = lower.long() + torch.arange(count, device=points.device)[None, :, None, None, None] * samples
        flat = beam.reshape(-1)
        value = flat[index] * (1 - weight) + flat[index + 1] * weight
        value = torch.where(position <= samples - 1, value, torch.zeros_like(value))
        return to_light, value / squared

    def project_(self) -> None:
        """Unit axes and a table >= 0 after each step of a fit."""
        with torch.no_grad():
            if isinstance(self.principal_directions, nn.Parameter):
                self.principal_directions.copy_(_unit(self.principal_directions))
            if isinstance(self.beam, nn.Parameter):
                self.beam.clamp_(min=0.0)

    @classmethod
    def from_leds(cls, leds: LEDLights, samples: int = 13, step_deg: float = 2.5, learnable: bool = False,
                  ) -> TabulatedBeamLEDs:
        """The table of an LED model's :math:`\\phi \\cos^\\mu` beam."""
        angles = torch.deg2rad(torch.arange(samples, dtype=leds.positions_mm.dtype) * step_deg)
        beam = leds.intensities[:, None] * angles.cos()[None].pow(leds.mu[:, None])
        return cls(leds.positions_mm, leds.principal_directions,
                   torch.full((leds.count,), step_deg, dtype=beam.dtype), beam, learnable)


class GaussianBeamLEDs(LEDLights):
    r"""LEDs with a Gaussian beam: irradiance :math:`\phi \exp(-(1 - \cos\theta) / w^2) / r^2`, about
    :math:`\exp(-\theta^2 / 2 w^2)` near the axis (w in radians).

    Subclasses ``LEDLights`` for its positions, axes, intensities and checks, and overrides ``forward``; its JSON has
    ``width`` where the LED model has ``mu``.
    """

    kind = "gaussian_beam_leds"  # the name an entry point registers (see tests/test_lights.py)
    fields = {
        "positions_mm": LightField((3,)),
        "principal_directions": LightField((3,)),
        "intensities": LightField((), optional=True),
        "width": LightField(()),
    }

    def __init__(self, positions_mm: Tensor, principal_directions: Tensor, intensities: Tensor | None = None,
                 width: Tensor | None = None, learnable: bool = False) -> None:
        super().__init__(positions_mm, principal_directions, intensities, None, learnable)
        if width is None:
            width = torch.full((self.count,), math.radians(30.0), dtype=positions_mm.dtype)
        self.width = nn.Parameter(width.detach().clone()) if learnable else width

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor]:
        to_light, isotropic = PointLights.forward(self, points)  # unit vectors, phi / r²
        axis = _unit(self.principal_directions.to(points))[None, :, :, None, None]
        cosine = -(to_light * axis).sum(dim=2, keepdim=True)
        width = self.width.to(points)[None, :, None, None, None]
        return to_light, isotropic * torch.exp(-(1 - cosine) / width.square())

    def project_(self) -> None:
        super().project_()
        with torch.no_grad():
            if isinstance(self.width, nn.Parameter):
                self.width.clamp_(min=1e-3)
