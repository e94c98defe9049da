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

import importlib
import importlib.metadata
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from psmini._checks import as_index, check_finite, check_shape, check_tensor
from psmini.errors import CalibrationError, DataFormatError, InputError, ShapeError

__all__ = [
    "ring_lights",
    "check_spans_3d",
    "as_batched_lights",
    "LightModel",
    "LightField",
    "LIGHT_MODELS_GROUP",
    "light_model_class",
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

    Raises:
        InputError: for a count that is not an integer, or an angle that is not a finite number.
        CalibrationError: for a count below 1.

    Example:
        >>> ring_lights(8, zenith_deg=55.0).shape
        torch.Size([8, 3])
    """
    index = as_index(count)
    if index is None:
        raise InputError(f"ring_lights' count must be an integer (lights), got {count!r}")
    count = index
    if count < 1:
        raise CalibrationError(f"a ring needs at least one light, got count={count}")
    for name, angle in (("zenith_deg", zenith_deg), ("azimuth_offset_deg", azimuth_offset_deg)):
        try:
            finite = not isinstance(angle, bool) and math.isfinite(float(angle))
        except (TypeError, ValueError):
            finite = False
        if not finite:
            raise InputError(f"ring_lights' {name} must be a finite number of degrees, got {angle!r}")
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


def _unit_(x: Tensor) -> None:
    """Rows of a learnable (K, 3) parameter scaled to unit length, in place; plain tensors are left alone."""
    if isinstance(x, nn.Parameter):
        x.div_(x.norm(dim=-1, keepdim=True).clamp_min(1e-12))


def _positive_(x: Tensor) -> None:
    """A learnable parameter kept at or above the smallest normal number, in place; plain tensors are left alone."""
    if isinstance(x, nn.Parameter):
        x.clamp_(min=torch.finfo(x.dtype).tiny)


def _floats(x: Tensor) -> list:
    return x.detach().cpu().double().tolist()


# The entry-point group in which a package registers its light models: ``name = "package.module:Class"``.
LIGHT_MODELS_GROUP = "psmini.light_models"

# The kinds of psmini's own models, which no other class may take.
_BUILTIN_KINDS = ("directional", "point", "led")


@dataclass(frozen=True)
class LightField:
    r"""One per-light array of a light model: the shape of each light's entry, and whether it may be left out.

    A model's JSON object holds one list per field, its first dimension the K lights; ``shape`` is what follows:
    ``(3,)`` for a position or a direction (JSON ``[[x, y, z], ...]``), ``()`` for one number per light
    (``[a, b, ...]``), ``(None,)`` for a row of any width, the same for every light (a table, ``[[...], ...]``).
    :meth:`LightModel.from_dict` checks each field's shape and that every field counts the same K, and passes it to
    the model's constructor as a keyword argument: a tensor of shape :math:`(K, *shape)`, or ``None`` for an optional
    field the object leaves out (the constructor picks the default).

    Args:
        shape: the trailing shape after K: non-negative integers, or ``None`` for a length the data decides.
        optional: the object may leave the field out (or set it to ``null``).

    Raises:
        InputError: a shape entry that is neither a positive integer nor ``None``.

    Example:
        >>> LightField((None,)).describe()
        '(K, N)'
        >>> LightField((), optional=True).describe()
        '(K,)'
    """

    shape: tuple[int | None, ...] = ()
    optional: bool = False

    def __post_init__(self) -> None:
        shape = tuple(self.shape) if isinstance(self.shape, (tuple, list)) else self.shape
        if not isinstance(shape, tuple) or any(
                d is not None and (isinstance(d, bool) or not isinstance(d, int) or d < 1) for d in shape):
            raise InputError(f"a light field's shape must be a tuple of positive integers or None, got {self.shape!r}")
        object.__setattr__(self, "shape", shape)
        if not isinstance(self.optional, bool):
            raise InputError(f"a light field's optional must be True or False, got {self.optional!r}")

    def describe(self) -> str:
        """The field's shape as documentation writes it: ``(K, 3)``, ``(K,)``, ``(K, N)``."""
        names = iter("NMPQ")
        dims = ["K", *(str(d) if d is not None else next(names, "?") for d in self.shape)]
        return f"({dims[0]},)" if len(dims) == 1 else f"({', '.join(dims)})"

    def parse(self, value: Any, kind: str, name: str, dtype: torch.dtype) -> Tensor:
        """The field's JSON value as a tensor of shape :math:`(K, *shape)`; :class:`DataFormatError` otherwise."""
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as error:
            raise DataFormatError(f"light model {kind!r}: {name!r} must hold numbers of shape {self.describe()} "
                                  f"({error})") from error
        if array.ndim != 1 + len(self.shape) or any(
                want is not None and got != want for got, want in zip(array.shape[1:], self.shape, strict=True)):
            expected = ("a list of [x, y, z] triples" if self.shape == (3,) else "a list of numbers"
                        if self.shape == () else "a list of K rows")
            raise DataFormatError(f"light model {kind!r}: {name!r} must be {expected}, shape {self.describe()}, "
                                  f"got shape {array.shape}")
        if array.shape[0] < 1 or any(d == 0 for d in array.shape[1:]):
            raise DataFormatError(f"light model {kind!r}: {name!r} is empty (shape {array.shape})")
        return torch.as_tensor(array, dtype=dtype)


class LightModel(nn.Module):
    r"""What every light model is: K lights that give per-pixel light vectors and irradiance at 3-D points.

    psmini's built-in models are :class:`DirectionalLights`, :class:`PointLights` and :class:`LEDLights`; a user's
    model is a subclass like them, and the pipeline, the near-light solver, lights files, capture manifests, the
    command line and :func:`psmini.ledcal.fit_lights` take it without any change to psmini
    (``docs/guides/light-models.md`` walks through one). The contract:

    - ``forward(points)``: ``points`` are 3-D surface points, shape :math:`(B, 3, H, W)`, millimetres, camera frame
      (x right, y up, z toward the camera; the card plane at z = 0). It returns the unit vectors from each point
      toward each light, shape :math:`(B, K, 3, H, W)`, and the irradiance each light delivers there, shape
      :math:`(B, K, 1, H, W)`, so that a Lambertian point of albedo ρ and normal n reads
      ``ρ * irradiance * max(n · l, 0)``. The solver calls it at the points of the current depth on the pixel grid
      (and on subsampled grids), at the card plane for flat-fielded images, a few dozen times per capture: keep it to
      element-wise tensor operations (no Python loop over pixels, no ``.item()``; lengths as square roots of summed
      squares, since ``Tensor.norm`` along a dimension that is not the innermost one is 25-45 times slower on the
      CPU, see ``psmini._tensor``).
    - Devices and dtypes: the result is on ``points``' device and in its dtype. The model's tensors may live
      elsewhere (a float64 calibration used on float32 CUDA images): convert them with ``.to(points)`` inside
      ``forward``, as the built-ins do.
    - Differentiable: ``forward`` is built of differentiable torch operations, so gradients reach the points and the
      model's ``nn.Parameter`` s (what :func:`psmini.ledcal.fit_lights` and self-calibration need).
    - ``count``: the number of lights K (by default the first dimension of the first field).
    - ``is_near``: ``True`` (the default) when the light varies over the field, so that the near-light solver is
      used; ``False`` for distant lights, whose vectors are the same at every point.
    - ``fields``: the per-light arrays of the JSON form, in order, each a :class:`LightField` (a bare shape tuple
      means a required field). :meth:`to_dict` writes ``{"model": kind, field: values, ...}`` from the attributes of
      those names; :meth:`from_dict` checks the shapes and calls ``cls(**fields)``, so the constructor takes each
      field as a keyword argument (``None`` for an optional field left out). Extra keys are ignored.
    - ``kind``: the JSON name. Left out, it is the class's import path ``"package.module:Class"``, which a fresh
      process (the command line) can import; a short name needs an entry point in the group
      ``psmini.light_models`` (``name = "package.module:Class"``), see :func:`light_model_class`.
    - ``project_()`` (optional): called by :func:`psmini.ledcal.fit_lights` after each optimiser step to put the
      parameters back onto their constraints (unit directions, :math:`\mu \ge 0`, ...), in place, without gradients.

    Code asks the model (``is_near``, ``count``, ``forward``) instead of probing attributes.

    Example:
        >>> class Flash(LightModel):  # one isotropic point light per row of positions_mm, unit intensity
        ...     fields = {"positions_mm": LightField((3,))}
        ...     def __init__(self, positions_mm):
        ...         super().__init__()
        ...         self.positions_mm = positions_mm
        ...     def forward(self, points):
        ...         offsets = self.positions_mm.to(points)[None, :, :, None, None] - points[:, None]
        ...         squared = offsets.square().sum(dim=2, keepdim=True)
        ...         return offsets / squared.sqrt(), 1 / squared
        >>> flash = Flash(torch.tensor([[0.0, 0.0, 10.0]]))
        >>> flash.count, flash.kind.endswith(":Flash")
        (1, True)
        >>> round(float(flash(torch.zeros(1, 3, 1, 1))[1]), 6)  # 1 / (10 mm)²
        0.01
    """

    kind: ClassVar[str]
    is_near: ClassVar[bool] = True
    fields: ClassVar[Mapping[str, LightField]] = {}
    _KINDS: ClassVar[dict[str, type[LightModel]]] = {}  # every concrete kind defined so far, by name
    _ALIASES: ClassVar[dict[str, type[LightModel]]] = {}  # entry-point names and import paths already resolved

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "fields" in cls.__dict__:
            declared = cls.__dict__["fields"]
            if not isinstance(declared, Mapping) or not all(isinstance(k, str) for k in declared):
                raise InputError(f"{cls.__qualname__}.fields must map field names to LightField, got {declared!r}")
            cls.fields = {name: spec if isinstance(spec, LightField) else LightField(spec)
                          for name, spec in declared.items()}
        path = f"{cls.__module__}:{cls.__qualname__}"
        if "kind" not in cls.__dict__:
            cls.kind = path
        kind = cls.kind
        if not isinstance(kind, str) or not kind:
            raise InputError(f"{cls.__qualname__}.kind must be a non-empty string, got {kind!r}")
        existing = LightModel._KINDS.get(kind)
        if existing is not None and f"{existing.__module__}:{existing.__qualname__}" != path:
            if kind in _BUILTIN_KINDS:
                raise InputError(f"light model kind {kind!r} is psmini's built-in {existing.__name__}: give "
                                 f"{cls.__qualname__} another kind, or leave kind out (its import path {path!r})")
            warnings.warn(f"light model kind {kind!r} of {path} replaces the one of "
                          f"{existing.__module__}:{existing.__qualname__}", stacklevel=2)
        LightModel._KINDS[kind] = cls
        LightModel._ALIASES.pop(kind, None)

    @property
    def count(self) -> int:
        """Number of lights K: the first dimension of the first field."""
        if not self.fields:
            raise InputError(f"{type(self).__qualname__} declares no fields: declare them, or override count")
        return int(getattr(self, next(iter(self.fields))).shape[0])

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of this model: ``{"model": kind, field: values, ...}`` (see :func:`lights_to_dict`)."""
        data: dict[str, Any] = {"model": self.kind}
        for name in self.fields:
            value = getattr(self, name, None)
            if value is not None:
                data[name] = _floats(torch.as_tensor(value))
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, dtype: torch.dtype | None = None) -> LightModel:
        """The model of a JSON light object (its kind found by :func:`light_model_class`); see
        :func:`lights_from_dict`. Called on a subclass, the object must name that subclass or one of its own."""
        if not isinstance(data, Mapping):
            raise DataFormatError(f"a light model must be a JSON object, got {type(data).__name__}")
        target = light_model_class(data.get("model"))
        if not issubclass(target, cls):
            raise DataFormatError(f"light model {data.get('model')!r} is a {target.__qualname__}, not a "
                                  f"{cls.__qualname__}")
        kind = str(data.get("model"))
        if not target.fields:
            raise DataFormatError(f"light model {kind!r} ({target.__qualname__}) declares no fields to read")
        dtype = dtype or torch.get_default_dtype()
        values: dict[str, Tensor | None] = {}
        counted: tuple[str, int] | None = None
        for name, spec in target.fields.items():
            if data.get(name) is None:
                if not spec.optional:
                    raise DataFormatError(f"light model {kind!r} lacks {name!r} (shape {spec.describe()})")
                values[name] = None
                continue
            values[name] = tensor = spec.parse(data[name], kind, name, dtype)
            if counted is None:
                counted = (name, tensor.shape[0])
            elif tensor.shape[0] != counted[1]:
                raise DataFormatError(f"light model {kind!r}: {name!r} has {tensor.shape[0]} lights but "
                                      f"{counted[0]!r} has {counted[1]}; every field counts the same K lights")
        try:
            return target(**values)
        except TypeError as error:
            raise DataFormatError(
                f"light model {kind!r}: {target.__qualname__}({', '.join(f'{n}=...' for n in values)}) failed: "
                f"{error} (the constructor must take every field of {target.__qualname__}.fields as a keyword)"
            ) from error


def _check_model_class(obj: Any, kind: str, where: str) -> type[LightModel]:
    """``obj`` if it is a concrete LightModel subclass, else a DataFormatError naming ``where`` it came from."""
    if not (isinstance(obj, type) and issubclass(obj, LightModel)):
        raise DataFormatError(f"light model {kind!r}: {where} is {obj!r}, not a subclass of psmini.lights.LightModel")
    if obj.forward is nn.Module.forward:
        raise DataFormatError(f"light model {kind!r}: {obj.__qualname__} ({where}) defines no forward(points)")
    return obj


def _from_entry_points(kind: str) -> type[LightModel] | None:
    """The class an installed package registers under ``kind`` in the group ``psmini.light_models``, or None."""
    for entry in importlib.metadata.entry_points(group=LIGHT_MODELS_GROUP):
        if entry.name != kind:
            continue
        where = f"the entry point {kind} = {entry.value!r} of group {LIGHT_MODELS_GROUP!r}"
        try:
            loaded = entry.load()
        except Exception as error:  # a user's package: any failure to import it is a bad light model for us
            raise DataFormatError(f"light model {kind!r}: loading {where} failed: {type(error).__name__}: "
                                  f"{error}") from error
        return _check_model_class(loaded, kind, where)
    return None


def _from_import_path(kind: str) -> type[LightModel]:
    """The class at ``"package.module:Class"``, imported."""
    module_name, _, qualname = kind.partition(":")
    if not all(part.isidentifier() for part in (*module_name.split("."), *qualname.split("."))):
        raise DataFormatError(f"light model {kind!r}: not an import path \"package.module:Class\"")
    if module_name == "__main__" or "<locals>" in qualname:
        place = "a script run as __main__" if module_name == "__main__" else "a function"
        raise DataFormatError(
            f"light model {kind!r} was defined in {place}, which another process cannot import: define the class at "
            "the top level of a module on the Python path and write the lights file from there")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        if error.name is not None and module_name.startswith(error.name):
            raise DataFormatError(f"light model {kind!r}: no module named {error.name!r} (import path "
                                  f"{kind!r}): install the package that defines it, or put its folder on "
                                  "PYTHONPATH") from error
        raise DataFormatError(f"light model {kind!r}: importing {module_name!r} failed: {error}") from error
    except Exception as error:  # a user's module: whatever its import raises is a bad light model for us
        raise DataFormatError(f"light model {kind!r}: importing {module_name!r} failed: {type(error).__name__}: "
                              f"{error}") from error
    obj: Any = module
    for part in qualname.split("."):
        if not hasattr(obj, part):
            raise DataFormatError(f"light model {kind!r}: module {module_name!r} has no {qualname!r}")
        obj = getattr(obj, part)
    return _check_model_class(obj, kind, f"the import path {kind!r}")


def light_model_class(kind: Any) -> type[LightModel]:
    """The :class:`LightModel` subclass a JSON light object names in ``"model"``.

    Looked for, in order: among the built-ins (``directional``, ``point``, ``led``) and every subclass already
    defined in this process (under its ``kind``); among the entry points of the group ``psmini.light_models``
    (a package registers ``name = "package.module:Class"`` in its ``pyproject.toml``:
    ``[project.entry-points."psmini.light_models"]``); then, for a name ``"package.module:Class"``, by importing
    that module (the default ``kind`` of a subclass is its import path, so the JSON of a model defined in a
    module on the Python path reads back in a fresh process). Importing runs the module's code: read lights files
    and captures from people you trust, as you would run their code.

    Args:
        kind: the ``"model"`` value: a built-in name, an entry-point name or an import path (anything else, a
            number or a list, is refused as unknown).

    Returns:
        the class.

    Raises:
        DataFormatError: ``kind`` names nothing in any of the three places (the message lists them and says how
            to register a model); its module is missing or fails to import; what
            it names is not a :class:`LightModel` subclass with a ``forward``.

    Example:
        >>> light_model_class("led").__name__
        'LEDLights'
        >>> light_model_class("psmini.lights:PointLights").kind
        'point'
    """
    found = (LightModel._KINDS.get(kind) or LightModel._ALIASES.get(kind)) if isinstance(kind, str) and kind else None
    if found is None:
        if isinstance(kind, str) and kind:
            found = _from_entry_points(kind)
            if found is None and ":" in kind:
                found = _from_import_path(kind)
        if found is None:
            builtin = sorted(_BUILTIN_KINDS)
            imported = sorted(k for k, c in LightModel._KINDS.items()
                              if k not in _BUILTIN_KINDS and not c.__qualname__.startswith("_"))
            entries = sorted({e.name for e in importlib.metadata.entry_points(group=LIGHT_MODELS_GROUP)})
            raise DataFormatError(
                f"light model must be one of the built-ins {builtin}, a model already imported "
                f"({', '.join(imported) if imported else 'none'}), an entry point of group "
                f"{LIGHT_MODELS_GROUP!r} ({', '.join(entries) if entries else 'none installed'}) or an import path "
                f"\"package.module:Class\"; got {kind!r}. Register a model with "
                f"[project.entry-points.\"{LIGHT_MODELS_GROUP}\"] name = \"package.module:Class\" in its "
                "package's pyproject.toml, or write its import path as \"model\""
            )
        LightModel._ALIASES[kind] = found
    return found


def lights_to_dict(lights: LightModel) -> dict[str, Any]:
    """The JSON object of a light model (``capture.json``'s ``lights``, lights files, LED fits).

    Args:
        lights: a :class:`LightModel` (``DirectionalLights``, ``PointLights``, ``LEDLights`` or a user's subclass).

    Returns:
        ``{"model": "directional", "directions": [[x, y, z], ...], "intensities": [...]}``,
        ``{"model": "point", "positions_mm": ..., "intensities": ...}``,
        ``{"model": "led", "positions_mm": ..., "principal_directions": ..., "intensities": ..., "mu": ...}``, or for
        a user's model ``{"model": its kind, field: values, ...}`` (see :class:`LightModel`).

    Raises:
        InputError: for anything that is not a :class:`LightModel`.

    Example:
        >>> lights_to_dict(DirectionalLights(torch.eye(3)))["model"]
        'directional'
    """
    if not isinstance(lights, LightModel):
        raise InputError(
            "lights must be a psmini.lights.LightModel (DirectionalLights, PointLights, LEDLights or a subclass), "
            f"got {type(lights).__name__}"
        )
    return lights.to_dict()


def lights_from_dict(data: Mapping[str, Any], *, dtype: torch.dtype | None = None) -> LightModel:
    """The light model of a JSON light object (inverse of :func:`lights_to_dict`).

    Args:
        data: a light object as in ``docs/capture-format.md``: ``"model"`` names the class (a built-in, a model
            registered by an entry point, or an import path ``"package.module:Class"``: see
            :func:`light_model_class`), the other keys are its fields (:class:`LightField`); ``intensities`` (and
            ``mu`` for LEDs) may be omitted (ones).
        dtype: floating dtype of the parameters (default: torch's default dtype).

    Returns:
        the model: ``DirectionalLights``, ``PointLights``, ``LEDLights`` or the user's class.

    Raises:
        DataFormatError: an unknown model (saying where it was looked for), a missing key, values that are not
            numbers of the field's shape, fields that count different numbers of lights.
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
    fields = {"directions": LightField((3,)), "intensities": LightField((), optional=True)}

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

    def project_(self) -> None:
        """Back onto the constraints after an optimiser step (learnable parameters only): unit directions,
        intensities > 0."""
        with torch.no_grad():
            _unit_(self.directions)
            _positive_(self.intensities)

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
    fields = {"positions_mm": LightField((3,)), "intensities": LightField((), optional=True)}

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

    def project_(self) -> None:
        """Back onto the constraints after an optimiser step (learnable parameters only): intensities > 0."""
        with torch.no_grad():
            _positive_(self.intensities)

    def _offsets(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Vectors from the points to the lights, (B, K, 3, H, W), and their lengths (B, K, 1, H, W)."""
        _check_points(points)
        offsets = self.positions_mm.to(points)[None, :, :, None, None] - points[:, None]
        # the summed squares, not Tensor.norm: a norm along dim 2 is 45 times slower on the CPU (psmini._tensor)
        squared = offsets.square().sum(dim=2, keepdim=True)
        # not checked inside torch.compile (a graph break would split the light field in two): a solve's surface lies
        # millimetres below its lights
        if not torch.compiler.is_compiling() and bool((squared.detach() <= 0).any()):
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
    fields = {"positions_mm": LightField((3,)), "principal_directions": LightField((3,)),
              "intensities": LightField((), optional=True), "mu": LightField((), optional=True)}

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

    def project_(self) -> None:
        """Back onto the constraints after an optimiser step (learnable parameters only): intensities > 0, unit
        principal directions, mu >= 0."""
        super().project_()
        with torch.no_grad():
            _unit_(self.principal_directions)
            if isinstance(self.mu, nn.Parameter):
                self.mu.clamp_(min=0.0)

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
