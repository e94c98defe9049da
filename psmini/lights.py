r"""Light models: distant (directional) lights, isotropic point lights and LEDs.

Every model is an ``nn.Module`` whose parameters can be learnt, with one interface: given surface points
:math:`(B, 3, H, W)` in millimetres (camera frame: x right, y up, z toward the camera) it returns per-pixel
unit light vectors :math:`(B, K, 3, H, W)` and irradiance factors :math:`(B, K, 1, H, W)`, so that a
Lambertian pixel reads ``albedo * irradiance * max(n · l, 0)``.

The LED model is the standard one of near-light photometric stereo (Quéau et al., "LED-based photometric
stereo: modeling, calibration and numerical solution", JMIV 2018; Santo et al. 2020):

.. math::
    l = \frac{s - x}{\lVert s - x \rVert}, \qquad
    E = \phi \, \frac{\max(d \cdot (x - s) / \lVert x - s \rVert, 0)^{\mu}}{\lVert x - s \rVert^{2}}

with LED position ``s`` (mm), principal direction ``d``, intensity ``φ`` and anisotropy ``μ`` (0: isotropic
point, 1: Lambertian LED).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from psmini._checks import check_finite, check_shape, check_tensor
from psmini.errors import CalibrationError, DataFormatError, InputError, ShapeError

__all__ = [
    "ring_lights",
    "check_spans_3d",
    "as_batched_lights",
    "LightModel",
    "DirectionalLights",
    "PointLights",
    "LEDLights",
    "lights_to_dict",
    "lights_from_dict",
]

# Ratio of the smallest to the largest singular value of the light matrix below which the lights are
# taken as coplanar: the normal component off their plane is then amplified more than 1000-fold.
_COPLANAR_RATIO = 1e-3


def ring_lights(
    count: int,
    zenith_deg: float,
    azimuth_offset_deg: float = 0.0,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    r"""Unit directions of ``count`` distant lights evenly spaced on a ring around the optical axis.

    Args:
        count: number of lights K.
        zenith_deg: angle between each light and the optical axis (+z), degrees.
        azimuth_offset_deg: azimuth of the first light, degrees counter-clockwise from +x.
        device: device of the result.
        dtype: floating dtype of the result (default: torch's default dtype).

    Returns:
        unit directions, shape :math:`(K, 3)`, camera frame (x right, y up, z toward the camera).

    Example:
        >>> ring_lights(8, zenith_deg=55.0).shape
        torch.Size([8, 3])
    """
    if count < 1:
        raise CalibrationError(f"a ring needs at least one light, got count={count}")
    dtype = dtype or torch.get_default_dtype()
    azimuth = torch.arange(count, device=device, dtype=dtype) * (2 * math.pi / count) + math.radians(azimuth_offset_deg)
    zenith = torch.tensor(math.radians(zenith_deg), device=device, dtype=dtype)
    return torch.stack(
        [zenith.sin() * azimuth.cos(), zenith.sin() * azimuth.sin(), zenith.cos().expand_as(azimuth)], dim=-1
    )


def check_spans_3d(lights: Tensor, name: str = "lights") -> Tensor:
    """Raise :class:`CalibrationError` unless every light set has at least 3 lights spanning 3D.

    Args:
        lights: light vectors, shape :math:`(K, 3)` or :math:`(B, K, 3)`.
        name: the argument's name, for the message.

    Returns:
        ``lights`` unchanged.

    Example:
        >>> check_spans_3d(ring_lights(8, 55.0)).shape
        torch.Size([8, 3])
    """
    check_tensor(lights, name)
    if lights.ndim not in (2, 3) or lights.shape[-1] != 3:
        raise ShapeError(f"{name} must have shape (K, 3) or (B, K, 3), got {tuple(lights.shape)}")
    check_finite(lights, name)
    count = lights.shape[-2]
    if count < 3:
        raise CalibrationError(f"photometric stereo needs at least 3 lights spanning 3D, got {count}")
    singular = torch.linalg.svdvals(lights.detach())
    ratio = singular[..., -1] / singular[..., 0].clamp_min(torch.finfo(lights.dtype).tiny)
    if bool((ratio < _COPLANAR_RATIO).any()):
        raise CalibrationError(
            f"{name} are coplanar (or collinear): the {count} light vectors do not span 3D "
            f"(smallest/largest singular value {float(ratio.min()):.2e} < {_COPLANAR_RATIO:g})"
        )
    return lights


def as_batched_lights(lights: Tensor, batch: int, reference: Tensor, name: str = "lights") -> Tensor:
    """Return ``lights`` as :math:`(B, K, 3)` on the device and dtype of ``reference``."""
    check_tensor(lights, name)
    if lights.ndim == 2:
        lights = lights.unsqueeze(0)
    if lights.ndim != 3 or lights.shape[-1] != 3 or lights.shape[0] not in (1, batch):
        raise ShapeError(f"{name} must have shape (K, 3) or ({batch}, K, 3), got {tuple(lights.shape)}")
    return lights.to(device=reference.device, dtype=reference.dtype).expand(batch, -1, -1)


def _check_points(points: Tensor) -> dict[str, int]:
    return check_shape(points, ["B", "3", "H", "W"], "points")


def _as_parameter(x: Tensor, learnable: bool) -> Tensor:
    """A fresh ``nn.Parameter`` when learnable; otherwise ``x`` itself, so gradients flow back to the caller's
    tensor."""
    return nn.Parameter(x.detach().clone()) if learnable else x


def _floats(x: Tensor) -> list:
    return x.detach().cpu().double().tolist()


class LightModel(nn.Module):
    r"""What every light model is: K lights that give per-pixel light vectors and irradiance at 3-D points.

    Subclasses name their JSON ``kind`` and their fields (``_FIELDS``: name, array rank, optional), say whether the
    light varies over the field (``is_near``: point and LED models, whose positions are known) and implement
    ``forward(points)`` → unit vectors :math:`(B, K, 3, H, W)` and irradiance :math:`(B, K, 1, H, W)`. The JSON
    form (``capture.json``'s ``lights``, lights files, LED fits) is :meth:`to_dict` / :meth:`from_dict`; code asks
    the model (``is_near``, ``count``) instead of probing attributes.
    """

    kind: ClassVar[str]
    is_near: ClassVar[bool]
    _FIELDS: ClassVar[tuple[tuple[str, int, bool], ...]]
    _KINDS: ClassVar[dict[str, type[LightModel]]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "kind" in cls.__dict__:  # a concrete model with its own JSON name
            LightModel._KINDS[cls.kind] = cls

    @property
    def count(self) -> int:
        """Number of lights K."""
        return int(getattr(self, self._FIELDS[0][0]).shape[0])

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of this model: ``{"model": kind, field: values, ...}`` (see :func:`lights_to_dict`)."""
        return {"model": self.kind, **{name: _floats(getattr(self, name)) for name, _, _ in self._FIELDS}}

    @staticmethod
    def from_dict(data: Mapping[str, Any], *, dtype: torch.dtype | None = None) -> LightModel:
        """The model of a JSON light object; see :func:`lights_from_dict`."""
        if not isinstance(data, Mapping):
            raise DataFormatError(f"a light model must be a JSON object, got {type(data).__name__}")
        model = data.get("model")
        cls = LightModel._KINDS.get(model) if isinstance(model, str) else None
        if cls is None:
            raise DataFormatError(f"light model must be one of {sorted(LightModel._KINDS)}, got {data.get('model')!r}")
        dtype = dtype or torch.get_default_dtype()
        values: dict[str, Tensor | None] = {}
        for key, ndim, optional in cls._FIELDS:
            if data.get(key) is None:
                if not optional:
                    raise DataFormatError(f"light model {cls.kind!r} lacks {key!r}")
                values[key] = None
                continue
            try:
                array = np.asarray(data[key], dtype=np.float64)
            except (TypeError, ValueError) as error:
                raise DataFormatError(f"light model {cls.kind!r}: {key!r} must hold numbers ({error})") from error
            if array.ndim != ndim or (ndim == 2 and array.shape[1] != 3):
                expected = "a list of [x, y, z] triples" if ndim == 2 else "a list of numbers"
                raise DataFormatError(f"light model {cls.kind!r}: {key!r} must be {expected}, got shape {array.shape}")
            values[key] = torch.as_tensor(array, dtype=dtype)
        return cls(**values)


def lights_to_dict(lights: LightModel) -> dict[str, Any]:
    """The JSON object of a light model (``capture.json``'s ``lights``, lights files, LED fits).

    Args:
        lights: a :class:`LightModel` (``DirectionalLights``, ``PointLights`` or ``LEDLights``).

    Returns:
        ``{"model": "directional", "directions": [[x, y, z], ...], "intensities": [...]}``,
        ``{"model": "point", "positions_mm": ..., "intensities": ...}`` or
        ``{"model": "led", "positions_mm": ..., "principal_directions": ..., "intensities": ..., "mu": ...}``.

    Raises:
        InputError: for anything that is not a :class:`LightModel`.

    Example:
        >>> lights_to_dict(DirectionalLights(torch.eye(3)))["model"]
        'directional'
    """
    if not isinstance(lights, LightModel):
        raise InputError(
            "lights must be DirectionalLights, PointLights or LEDLights from psmini.lights, "
            f"got {type(lights).__name__}"
        )
    return lights.to_dict()


def lights_from_dict(data: Mapping[str, Any], *, dtype: torch.dtype | None = None) -> LightModel:
    """The light model of a JSON light object (inverse of :func:`lights_to_dict`).

    Args:
        data: a light object as in ``docs/capture-format.md``; ``intensities`` (and ``mu`` for LEDs) may be
            omitted (ones).
        dtype: floating dtype of the parameters (default: torch's default dtype).

    Returns:
        ``DirectionalLights``, ``PointLights`` or ``LEDLights``.

    Raises:
        DataFormatError: an unknown model, a missing key, values that are not numbers of the right shape.
        CalibrationError: values the light model refuses (zero directions, intensities <= 0, mu < 0).

    Example:
        >>> lights_from_dict({"model": "directional", "directions": [[0, 0, 1], [1, 0, 1], [0, 1, 1]]}).count
        3
    """
    return LightModel.from_dict(data, dtype=dtype)


class DirectionalLights(LightModel):
    r"""Distant lights: one unit direction and one relative intensity per light.

    Args:
        directions: light directions, shape :math:`(K, 3)` (normalised on construction).
        intensities: relative intensities, shape :math:`(K,)`; ones when omitted.
        learnable: make directions and intensities ``nn.Parameter`` s.

    Example:
        >>> lights = DirectionalLights(ring_lights(8, 55.0))
        >>> dirs, irradiance = lights(torch.zeros(1, 3, 4, 4))
        >>> dirs.shape, irradiance.shape
        (torch.Size([1, 8, 3, 4, 4]), torch.Size([1, 8, 1, 4, 4]))
    """

    kind = "directional"
    is_near = False
    _FIELDS = (("directions", 2, False), ("intensities", 1, True))

    def __init__(self, directions: Tensor, intensities: Tensor | None = None, learnable: bool = False) -> None:
        super().__init__()
        check_shape(directions, ["K", "3"], "directions")
        check_finite(directions, "directions")
        norm = directions.norm(dim=-1, keepdim=True)
        if bool((norm <= 0).any()):
            raise CalibrationError("directions must be non-zero vectors")
        if intensities is None:
            intensities = torch.ones(directions.shape[0], device=directions.device, dtype=directions.dtype)
        check_shape(intensities, ["K"], "intensities")
        if intensities.shape[0] != directions.shape[0]:
            raise ShapeError(
                f"intensities ({intensities.shape[0]}) and directions ({directions.shape[0]}) must count the same "
                "lights"
            )
        if bool((intensities <= 0).any()) or not bool(torch.isfinite(intensities).all()):
            raise CalibrationError(f"intensities must be positive and finite, got {intensities.tolist()}")
        self.directions = _as_parameter(directions / norm, learnable)
        self.intensities = _as_parameter(intensities.to(directions.dtype), learnable)

    def scaled_directions(self) -> Tensor:
        """Directions times intensities, shape :math:`(K, 3)`: the light matrix of least squares."""
        unit = self.directions / self.directions.norm(dim=-1, keepdim=True)
        return unit * self.intensities.unsqueeze(-1)

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Per-pixel unit light vectors and irradiance (constant over the image for distant lights)."""
        sizes = _check_points(points)
        batch, height, width = sizes["B"], sizes["H"], sizes["W"]
        unit = (self.directions / self.directions.norm(dim=-1, keepdim=True)).to(points)
        dirs = unit[None, :, :, None, None].expand(batch, -1, -1, height, width)
        irradiance = self.intensities.to(points)[None, :, None, None, None].expand(batch, -1, 1, height, width)
        return dirs, irradiance


class PointLights(LightModel):
    r"""Isotropic point lights with inverse-square falloff (the LED model with :math:`\mu = 0`).

    Args:
        positions_mm: light positions, shape :math:`(K, 3)`, millimetres, camera frame.
        intensities: radiant intensities :math:`\phi`, shape :math:`(K,)`; ones when omitted. Irradiance at
            distance r is :math:`\phi / r^2` (r in mm).
        learnable: make the parameters ``nn.Parameter`` s.

    Example:
        >>> lights = PointLights(torch.tensor([[0.0, 0.0, 10.0], [5.0, 0.0, 10.0], [0.0, 5.0, 10.0]]))
        >>> dirs, irradiance = lights(torch.zeros(1, 3, 2, 2))
        >>> round(float(irradiance[0, 0, 0, 0, 0]), 6)  # 1 / 10² mm²
        0.01
    """

    kind = "point"
    is_near = True
    _FIELDS: ClassVar[tuple[tuple[str, int, bool], ...]] = (("positions_mm", 2, False), ("intensities", 1, True))

    def __init__(self, positions_mm: Tensor, intensities: Tensor | None = None, learnable: bool = False) -> None:
        super().__init__()
        check_shape(positions_mm, ["K", "3"], "positions_mm")
        check_finite(positions_mm, "positions_mm")
        count = positions_mm.shape[0]
        if intensities is None:
            intensities = torch.ones(count, device=positions_mm.device, dtype=positions_mm.dtype)
        check_shape(intensities, ["K"], "intensities")
        if intensities.shape[0] != count:
            raise ShapeError(f"intensities ({intensities.shape[0]}) and positions ({count}) must count the same lights")
        if bool((intensities <= 0).any()) or not bool(torch.isfinite(intensities).all()):
            raise CalibrationError(f"intensities must be positive and finite, got {intensities.tolist()}")
        self.positions_mm = _as_parameter(positions_mm, learnable)
        self.intensities = _as_parameter(intensities.to(positions_mm.dtype), learnable)

    def _offsets(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Vectors from the points to the lights, (B, K, 3, H, W), and their lengths (B, K, 1, H, W)."""
        _check_points(points)
        offsets = self.positions_mm.to(points)[None, :, :, None, None] - points[:, None]
        # the summed squares, not Tensor.norm: a norm along dim 2 is 45 times slower on the CPU (psmini._tensor)
        squared = offsets.square().sum(dim=2, keepdim=True)
        if bool((squared.detach() <= 0).any()):
            raise CalibrationError("a surface point coincides with a light position")
        return offsets, squared.sqrt()

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Per-pixel unit light vectors and inverse-square irradiance."""
        offsets, distance = self._offsets(points)
        irradiance = self.intensities.to(points)[None, :, None, None, None] / distance.square()
        return offsets / distance, irradiance


class LEDLights(PointLights):
    r"""LEDs: point lights with a principal direction and a :math:`\cos^\mu` angular fall-off.

    Args:
        positions_mm: LED positions, shape :math:`(K, 3)`, millimetres, camera frame.
        principal_directions: directions the LEDs point to, shape :math:`(K, 3)` (normalised).
        intensities: intensities :math:`\phi` on the principal axis at 1 mm, shape :math:`(K,)`.
        mu: anisotropy :math:`\mu \ge 0`, shape :math:`(K,)`; ones (Lambertian LEDs) when omitted.
        learnable: make the parameters ``nn.Parameter`` s.

    Example:
        >>> positions = torch.tensor([[5.0, 0.0, 10.0], [-5.0, 0.0, 10.0], [0.0, 5.0, 10.0]])
        >>> leds = LEDLights(positions, torch.tensor([[0.0, 0.0, -1.0]]).expand(3, 3))
        >>> dirs, irradiance = leds(torch.zeros(1, 3, 2, 2))
        >>> dirs.shape
        torch.Size([1, 3, 3, 2, 2])
    """

    kind = "led"
    _FIELDS = (("positions_mm", 2, False), ("principal_directions", 2, False), ("intensities", 1, True),
               ("mu", 1, True))

    def __init__(
        self,
        positions_mm: Tensor,
        principal_directions: Tensor,
        intensities: Tensor | None = None,
        mu: Tensor | None = None,
        learnable: bool = False,
    ) -> None:
        super().__init__(positions_mm, intensities, learnable)
        check_shape(principal_directions, ["K", "3"], "principal_directions")
        check_finite(principal_directions, "principal_directions")
        if principal_directions.shape[0] != self.count:
            raise ShapeError(
                f"principal_directions ({principal_directions.shape[0]}) and positions ({self.count}) "
                "must count the same lights"
            )
        norm = principal_directions.norm(dim=-1, keepdim=True)
        if bool((norm <= 0).any()):
            raise CalibrationError("principal_directions must be non-zero vectors")
        if mu is None:
            mu = torch.ones(self.count, device=positions_mm.device, dtype=positions_mm.dtype)
        check_shape(mu, ["K"], "mu")
        if mu.shape[0] != self.count or bool((mu < 0).any()) or not bool(torch.isfinite(mu).all()):
            raise CalibrationError(f"mu must hold {self.count} finite values >= 0, got {mu.tolist()}")
        self.principal_directions = _as_parameter(principal_directions / norm, learnable)
        self.mu = _as_parameter(mu.to(positions_mm.dtype), learnable)

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Per-pixel unit light vectors and irradiance with the LED's angular fall-off."""
        offsets, distance = self._offsets(points)
        to_light = offsets / distance
        axis = self.principal_directions.to(points)
        axis = axis / axis.norm(dim=-1, keepdim=True)
        cosine = -(to_light * axis[None, :, :, None, None]).sum(dim=2, keepdim=True)
        # clamp to a tiny positive value, not 0: cos**mu has an infinite gradient in mu at 0
        cosine = cosine.clamp_min(torch.finfo(points.dtype).tiny)
        falloff = cosine.pow(self.mu.to(points)[None, :, None, None, None])
        irradiance = self.intensities.to(points)[None, :, None, None, None] * falloff / distance.square()
        return to_light, irradiance
