"""The classical pipeline in one differentiable module: flat-field → least-squares normals → gradients → depth.

This is the seed paper's method (Woodham's least squares with flat-fielding by a matte card, Frankot–Chellappa
integration) on batched tensors. Light models that are not distant (points, LEDs) are used here through their
distant approximation at the field centre, which is what a mirror sphere at the centre would measure; the
near-light solver lives beside it.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from psmini._checks import check_mask, check_shape, check_tensor
from psmini.errors import InputError
from psmini.flatfield import flatfield
from psmini.integrate import integrate
from psmini.lights import DirectionalLights, check_spans_3d
from psmini.nearlight import NearLightOptions, solve_near_light
from psmini.nonlambertian import nonlambertian_normals
from psmini.normals import albedo_normals, normals_to_gradients
from psmini.robust import ROBUST_METHODS, robust_normals
from psmini.result import Reconstruction

__all__ = ["NORMAL_METHODS", "Reconstruction", "PhotometricStereo", "distant_light_matrix", "reconstruct"]

# Normal estimators of the distant-light solver: least squares, those of :mod:`psmini.robust`, and the
# Lambertian + specular lobe fit of :mod:`psmini.nonlambertian`.
NORMAL_METHODS = ("lstsq", "robust") + ROBUST_METHODS + ("nonlambertian",)


def distant_light_matrix(lights: nn.Module, flatfielded: bool, reference: Tensor) -> Tensor:
    r"""The :math:`(K, 3)` light matrix of least squares for a light model, seen from the field centre.

    The model is evaluated at the origin (on the optical axis, at the card plane). Without flat-fielding the
    rows are unit directions times irradiance. After division by a flat card's image the irradiance cancels and
    a pixel reads :math:`\rho\,(n \cdot l_k) / (e_z \cdot l_k)`, so the rows are :math:`l_k / l_{k,z}`.

    Args:
        lights: a light model of :mod:`psmini.lights`.
        flatfielded: whether the images were divided by a card image.
        reference: a tensor whose device and dtype the result takes.

    Returns:
        light matrix :math:`(K, 3)`.

    Example:
        >>> from psmini.lights import ring_lights
        >>> matrix = distant_light_matrix(DirectionalLights(ring_lights(8, 60.0)), True, torch.zeros(1))
        >>> round(float(matrix[0, 2]), 6)
        1.0
    """
    centre = torch.zeros(1, 3, 1, 1, device=reference.device, dtype=reference.dtype)
    directions, irradiance = lights(centre)
    directions, irradiance = directions[0, :, :, 0, 0], irradiance[0, :, :, 0, 0]
    if not flatfielded:
        return directions * irradiance
    facing = directions[:, 2:3]
    if bool((facing <= 0).any()):
        raise InputError("flat-fielding needs every light above the card plane (positive z)")
    return directions / facing


def _as_light_model(lights: nn.Module | Tensor) -> nn.Module:
    if isinstance(lights, Tensor):
        check_spans_3d(lights)
        norms = lights.norm(dim=-1)
        return DirectionalLights(lights, norms)
    if not isinstance(lights, nn.Module):
        raise InputError(f"lights must be a psmini light model or a (K, 3) tensor, got {type(lights).__name__}")
    return lights


_SOLVERS = ("auto", "distant", "near")


class PhotometricStereo(nn.Module):
    """Flat-field, normals and depth in one differentiable module, for distant lights or near LEDs.

    With ``solver="distant"`` the lights are used as seen from the field centre (:func:`distant_light_matrix`):
    flat-field, least squares, integration, the classical pipeline. With ``solver="near"`` the point or LED model is
    evaluated on the surface itself (:func:`psmini.nearlight.solve_near_light`, on the same flat-fielded images).
    ``"auto"`` picks ``"near"`` for models with positions (:class:`~psmini.lights.PointLights`, :class:`~psmini.lights.LEDLights`)
    and ``"distant"`` otherwise.

    Args:
        lights: a light model of :mod:`psmini.lights`, or a :math:`(K, 3)` tensor of directions scaled by
            intensity.
        integrator: integration method of :func:`psmini.integrate.integrate`; ``None``: ``"fc"``
            (Frankot–Chellappa) for distant lights, the near-light options' (``"masked"``) for near ones.
        pixel_pitch_mm: size of one pixel on the cloth, mm; ``None`` integrates in pixel units (distant only).
        min_reference: see :func:`psmini.flatfield.flatfield`.
        saturation_level: raw level at which an observation counts as saturated and is dropped; ``None`` keeps all.
        solver: ``"auto"``, ``"distant"`` or ``"near"``.
        method: normal estimator of the distant solver, one of :data:`NORMAL_METHODS`: ``"lstsq"`` (least squares,
            :func:`psmini.normals.albedo_normals`) or a robust one of :func:`psmini.robust.robust_normals`
            (``"robust"``: the recommended one), or ``"nonlambertian"``
            (:func:`psmini.nonlambertian.nonlambertian_normals`, a Lambertian + Blinn–Phong fit started from the
            robust one). The near solver takes ``"lstsq"`` only.
        **near_options: ``card_height_mm`` (height of the card plane when its images were taken, mm; 0 by default)
            and fields of :class:`~psmini.nearlight.NearLightOptions` (e.g. ``max_iterations``, ``estimate_offset``),
            or ``options=`` a whole :class:`~psmini.nearlight.NearLightOptions`.

    Raises:
        InputError: for an unknown solver or method, ``"near"`` without light positions or pixel pitch, or
            ``"near"`` with a method other than ``"lstsq"``.

    Example:
        >>> from psmini.lights import LEDLights, ring_lights
        >>> ps = PhotometricStereo(ring_lights(8, 55.0), pixel_pitch_mm=0.025)
        >>> ps(torch.rand(2, 8, 32, 32)).depth.shape
        torch.Size([2, 1, 32, 32])
        >>> ring = ring_lights(8, 58.0)
        >>> PhotometricStereo(LEDLights(ring * 18.6, -ring)).solver                 # LEDs: near light
        'near'
    """

    def __init__(
        self,
        lights: nn.Module | Tensor,
        integrator: str | None = None,
        pixel_pitch_mm: float | None = 0.025,
        min_reference: float = 0.02,
        saturation_level: float | None = None,
        solver: str = "auto",
        method: str = "lstsq",
        **near_options,
    ) -> None:
        super().__init__()
        if solver not in _SOLVERS:
            raise InputError(f"solver must be one of {', '.join(_SOLVERS)}, got {solver!r}")
        self.lights = _as_light_model(lights)
        has_positions = hasattr(self.lights, "positions_mm")
        self.solver = ("near" if has_positions else "distant") if solver == "auto" else solver
        if self.solver == "near" and (not has_positions or pixel_pitch_mm is None):
            raise InputError(
                f"the near-light solver needs a point or LED model and a pixel pitch; got {type(self.lights).__name__} "
                f"and pixel_pitch_mm={pixel_pitch_mm}"
            )
        if method not in NORMAL_METHODS:
            raise InputError(f"method must be one of {', '.join(NORMAL_METHODS)}, got {method!r}")
        if self.solver == "near" and method != "lstsq":
            raise InputError(f"method {method!r} is for distant lights; the near-light solver has its own estimator")
        self.method = method
        self.integrator = integrator or ("masked" if self.solver == "near" else "fc")
        self.pixel_pitch_mm, self.min_reference, self.saturation_level = pixel_pitch_mm, min_reference, saturation_level
        self.card_height_mm = float(near_options.pop("card_height_mm", 0.0))
        base = near_options.pop("options", None) or NearLightOptions()
        if self.solver == "near" and integrator is not None:
            near_options.setdefault("integrator", integrator)
        self.near_options = base.replace(**near_options)  # validated here, before any work
        if self.solver == "near":
            self.integrator = self.near_options.integrator

    def forward(
        self,
        images: Tensor,
        reference: Tensor | None = None,
        dark: Tensor | None = None,
        reference_dark: Tensor | None = None,
        mask: Tensor | None = None,
        card_albedo: float = 1.0,
    ) -> Reconstruction:
        """Reconstruct ``images`` :math:`(B, K, H, W)`; see :func:`psmini.flatfield.flatfield` for the rest."""
        sizes = check_shape(images, ["B", "K", "H", "W"], "images")
        mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
        flat = flatfield(
            images, reference, dark, reference_dark, card_albedo, self.min_reference, self.saturation_level
        )
        if self.solver == "near":
            card_height = self.card_height_mm if reference is not None else None
            return solve_near_light(flat.images, self.lights, self.pixel_pitch_mm, card_height, flat.valid, mask,
                                    self.near_options)
        matrix = distant_light_matrix(self.lights, reference is not None, images)
        weights = None if bool(flat.valid.all()) else flat.valid
        if self.method == "lstsq":
            albedo, normals = albedo_normals(flat.images, matrix, mask, weights)
        elif self.method == "nonlambertian":
            albedo, normals = nonlambertian_normals(flat.images, matrix, mask, weights)
        else:
            albedo, normals = robust_normals(flat.images, matrix, self.method, mask, weights)
        solved = albedo > 0
        p, q = normals_to_gradients(normals)  # 0 where not solved: the normal there is (0, 0, 1)
        depth = integrate(p, q, method=self.integrator, pixel_pitch_mm=self.pixel_pitch_mm or 1.0, mask=solved)
        return Reconstruction(albedo, normals, p, q, depth, solved)


def reconstruct(
    sample,
    *,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
    integrator: str | None = None,
    light_model: str = "distant",
    min_reference: float = 0.02,
    method: str = "lstsq",
) -> Reconstruction:
    """Reconstruct one loaded sample (:func:`psmini.io.load_sample`).

    Args:
        sample: a :class:`psmini.io.Sample` (DiLiGenT or capture folder).
        device: where to compute.
        dtype: floating dtype of the computation.
        integrator: integration method; ``None`` takes the model's default (``"fc"`` for distant lights,
            ``"masked"`` for near lights).
        light_model: the :class:`PhotometricStereo` solver: ``"distant"`` (the classical pipeline, lights seen
            from the field centre), ``"near"`` (near-light photometric stereo with the sample's point or LED model;
            needs a pixel pitch) or ``"auto"`` (near for point and LED models).
        min_reference: see :func:`psmini.flatfield.flatfield`.
        method: normal estimator of the distant solver (see :class:`PhotometricStereo`).

    Returns:
        :class:`Reconstruction` with batch size 1, on ``device``.

    Raises:
        InputError: for an unknown ``light_model`` or ``method``, or ``"near"`` without positions or pixel pitch.

    Example:
        >>> from psmini.io import Sample
        >>> from psmini.lights import DirectionalLights, ring_lights
        >>> sample = Sample(name="random", images=torch.rand(8, 16, 16) + 0.1, lights=DirectionalLights(ring_lights(8, 55.0)))
        >>> reconstruct(sample).normals.shape
        torch.Size([1, 3, 16, 16])
    """
    check_tensor(sample.images, "sample.images")

    def batch(x: Tensor | None) -> Tensor | None:
        return None if x is None else x.to(device=device, dtype=dtype).unsqueeze(0)

    mask = None if sample.mask is None else sample.mask.to(device).unsqueeze(0)
    model = PhotometricStereo(
        sample.lights.to(device=device, dtype=dtype),
        integrator=integrator,
        pixel_pitch_mm=sample.pixel_pitch_mm,
        min_reference=min_reference,
        saturation_level=sample.saturation_level,
        solver=light_model,
        method=method,
    )
    return model(
        batch(sample.images),
        reference=batch(sample.reference),
        dark=batch(sample.dark),
        reference_dark=batch(sample.reference_dark),
        mask=mask,
        card_albedo=sample.card_albedo or 1.0,
    )
