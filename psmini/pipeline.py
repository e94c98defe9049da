"""The one reconstruction pipeline: flat-field once → a normal solver → integration, driven by one configuration.

The solver stage is chosen by :class:`~psmini.config.ReconstructionConfig` and the light model: distant lights
(the seed paper's method: Woodham's least squares, or a robust or non-Lambertian estimator from
:data:`NORMAL_ESTIMATORS`, with the lights seen from the field centre) or near light (per-pixel LED vectors at the
current depth, :mod:`psmini.nearlight`, alternating with integration until the depth settles). Everything is
batched, differentiable and device-agnostic.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from psmini._checks import (
    all_true,
    check_light_module,
    check_mask,
    check_positive,
    check_same_size,
    check_shape,
    check_tensor,
    records_gradient,
)
from psmini._chunks import batch_part, chunks
from psmini.config import ReconstructionConfig
from psmini.errors import InputError
from psmini.flatfield import flatfield
from psmini.integrate import integrate
from psmini.lights import DirectionalLights, LightModel, check_spans_3d
from psmini.nearlight import NearLightResult, near_light_vectors, solve_near_light
from psmini.nonlambertian import nonlambertian_normals
from psmini.normals import _slopes_of, _solve_with_pinv, albedo_normals
from psmini.result import Reconstruction
from psmini.robust import ROBUST_METHODS, robust_normals

__all__ = ["NORMAL_ESTIMATORS", "Reconstruction", "PhotometricStereo", "distant_light_matrix", "reconstruct"]


def _robust(method: str):
    return lambda images, matrix, mask, weights, options: robust_normals(images, matrix, method, mask, weights,
                                                                         options)


#: The registry of distant-light normal estimators: name → ``f(images, light_matrix, mask, weights, options)``
#: returning ``(albedo, normals)``. Least squares (:func:`~psmini.normals.albedo_normals`), the robust estimators of
#: :mod:`psmini.robust` (``robust``: the recommended one) and the Lambertian + specular lobe fit of
#: :mod:`psmini.nonlambertian`.
NORMAL_ESTIMATORS = {
    "lstsq": lambda images, matrix, mask, weights, options: albedo_normals(images, matrix, mask, weights),
    **{name: _robust(name) for name in ("robust",) + ROBUST_METHODS},
    "nonlambertian": lambda images, matrix, mask, weights, options: nonlambertian_normals(images, matrix, mask,
                                                                                          weights, options),
}


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

    Raises:
        InputError: ``lights`` that is not a light model (a :math:`(K, 3)` tensor of directions: wrap it in a
            :class:`~psmini.lights.DirectionalLights`), a ``reference`` that is not a tensor, or a light below the
            card plane when ``flatfielded``.

    Example:
        >>> from psmini.lights import ring_lights
        >>> matrix = distant_light_matrix(DirectionalLights(ring_lights(8, 60.0)), True, torch.zeros(1))
        >>> round(float(matrix[0, 2]), 6)
        1.0
    """
    _check_matrix_arguments(lights, reference)
    centre = torch.zeros(1, 3, 1, 1, device=reference.device, dtype=reference.dtype)
    directions, irradiance = lights(centre)
    directions, irradiance = directions[0, :, :, 0, 0], irradiance[0, :, :, 0, 0]
    if not flatfielded:
        return directions * irradiance
    facing = directions[:, 2:3]
    if bool((facing <= 0).any()):
        raise InputError("flat-fielding needs every light above the card plane (positive z)")
    return directions / facing


def _check_matrix_arguments(lights: object, reference: object) -> None:
    """Guards of :func:`distant_light_matrix`: a tensor of directions failed as "'Tensor' object is not callable"."""
    check_light_module(lights, "lights")
    if not isinstance(reference, Tensor):
        raise InputError(f"reference must be a tensor (the result takes its device and dtype), got "
                         f"{type(reference).__name__}")


def _as_light_model(lights: LightModel | Tensor) -> LightModel:
    if isinstance(lights, Tensor):
        check_spans_3d(lights)
        norms = lights.norm(dim=-1)
        return DirectionalLights(lights, norms)
    if not isinstance(lights, LightModel):
        raise InputError(f"lights must be a psmini light model or a (K, 3) tensor, got {type(lights).__name__}")
    return lights


class PhotometricStereo(nn.Module):
    """Flat-field once, a normal solver, integration: the one reconstruction pipeline, as a module.

    ``config`` chooses the solver (:meth:`~psmini.config.ReconstructionConfig.solver_for`: near light for point
    and LED models, the classical distant-light pipeline for directions, unless forced), the estimator of the
    distant solver (:data:`NORMAL_ESTIMATORS`) and the integrator. Both solvers work on the same flat-fielded
    images: the distant solver uses the light model as seen from the field centre (:func:`distant_light_matrix`);
    the near solver evaluates it on the surface itself, alternating with integration until the depth settles
    (:func:`psmini.nearlight.solve_near_light`).

    Args:
        lights: a :class:`~psmini.lights.LightModel`, or a :math:`(K, 3)` tensor of directions scaled by
            intensity.
        pixel_pitch_mm: size of one pixel on the cloth, mm; ``None`` integrates in pixel units (distant lights
            only). There is no default: a made-up pitch would silently scale every depth.
        config: the :class:`~psmini.config.ReconstructionConfig` (its ``device`` and ``dtype`` are for the
            entry points that load data; this module computes where its inputs are).

    Raises:
        InputError: a configuration that does not fit the lights (near light without positions), near light
            without a pixel pitch; on a call, a batch item where the distant solver solves no pixel (dark images).

    Example:
        >>> from psmini.lights import LEDLights, ring_lights
        >>> ps = PhotometricStereo(ring_lights(8, 55.0), pixel_pitch_mm=0.025)
        >>> ps(torch.rand(2, 8, 32, 32)).depth.shape
        torch.Size([2, 1, 32, 32])
        >>> ring = ring_lights(8, 58.0)
        >>> PhotometricStereo(LEDLights(ring * 18.6, -ring), pixel_pitch_mm=0.025).solver   # LEDs: near light
        'near'
    """

    def __init__(
        self, lights: LightModel | Tensor, pixel_pitch_mm: float | None, config: ReconstructionConfig | None = None
    ) -> None:
        super().__init__()
        self.config = ReconstructionConfig() if config is None else config
        if not isinstance(self.config, ReconstructionConfig):
            raise InputError(f"config must be a ReconstructionConfig, got {type(self.config).__name__}")
        self.lights = _as_light_model(lights)
        self.solver = self.config.solver_for(self.lights)
        # the distant solver's estimator (``auto``: least squares)
        self.estimator = "lstsq" if self.config.estimator == "auto" else self.config.estimator
        if pixel_pitch_mm is not None:
            check_positive(pixel_pitch_mm, "pixel_pitch_mm")
        elif self.solver == "near":
            raise InputError("the near-light solver needs the pixel pitch (mm per pixel on the cloth); got None")
        if self.solver == "near" and self.config.integrator_options:
            raise InputError(f"integrator options {sorted(self.config.integrator_options)} are for the distant "
                             "solver's integrator; the near solver weights its own (set NearLightOptions)")
        self.pixel_pitch_mm = pixel_pitch_mm

    def forward(
        self,
        images: Tensor,
        reference: Tensor | None = None,
        dark: Tensor | None = None,
        reference_dark: Tensor | None = None,
        mask: Tensor | None = None,
        card_albedo: float = 1.0,
        saturation_level: float | None = None,
        card_height_mm: float = 0.0,
    ) -> Reconstruction:
        """Reconstruct ``images`` :math:`(B, K, H, W)`; see :func:`psmini.flatfield.flatfield` for the rest.

        ``saturation_level``: raw level at which an observation counts as saturated and is dropped (``None``
        keeps all). ``card_height_mm``: height of the card plane when its images were taken (near light).
        Returns a :class:`Reconstruction` (a :class:`~psmini.nearlight.NearLightResult` with near light) whose
        depth is in mm, or pixel units without a pitch.
        """
        config = self.config
        sizes = check_shape(images, ["B", "K", "H", "W"], "images")
        mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
        # the distant solver's light matrix once per call, not once per chunk (0.14 ms a chunk: 1.1 of 51 ms for a
        # batch of 8 x 400^2 on one thread of the 2-core Xeon), and its pseudo-inverse (an SVD: 0.1 ms a chunk)
        matrices = None
        if self.solver != "near":
            matrix = distant_light_matrix(self.lights, reference is not None, images)
            check_same_size(matrix.shape[0], sizes["K"], "the number of lights", "lights", "images")
            matrices = (matrix, torch.linalg.pinv(check_spans_3d(matrix)))
        # the flat-fielded images, the solver's largest temporaries, one capture at a time on the CPU (see
        # psmini._chunks); only what a solver returns is assembled
        workspace: list[Tensor] = []  # the first chunk's flat-fielded images, a buffer for the next chunks'

        def frames(part: slice) -> tuple[Tensor, Tensor | None, Tensor | None, Tensor | None, Tensor | None]:
            """The images, reference, dark, reference dark and mask of one chunk."""
            return (batch_part(images, images, part, "images"), batch_part(reference, images, part, "reference"),
                    batch_part(dark, images, part, "dark"), batch_part(reference_dark, images, part, "reference_dark"),
                    batch_part(mask, images, part, "mask"))

        parts = chunks(images)
        if matrices is None:  # near light
            results = [self._solve_near(*frames(part), card_albedo, saturation_level, card_height_mm)
                       for part in parts]
            return results[0] if len(results) == 1 else NearLightResult.concatenate(results)

        def solve(part: slice, into: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
            return self._solve_distant(*frames(part), card_albedo, saturation_level, matrices, into, workspace)

        albedo, normals, p, q = _assemble(parts, solve)  # p, q 0 where not solved: the normal there is (0, 0, 1)
        # least squares' albedo is a length (finite, >= 0): its cast to bool is the test > 0, in 0.22 ms where the
        # comparison took 0.76 ms on a batch of 8 x 400^2 (one thread); other estimators' fitted albedo is compared
        solved = albedo.bool() if self.estimator == "lstsq" else albedo > 0
        _check_some_solved(solved, mask is not None)
        integrator = config.integrator_for(self.solver, mask is not None)
        depth = integrate(p, q, integrator, self.pixel_pitch_mm or 1.0, solved, **config.integrator_options)
        return Reconstruction(albedo, normals, p, q, depth, solved)

    def _solve_near(self, images: Tensor, reference: Tensor | None, dark: Tensor | None,
                    reference_dark: Tensor | None, mask: Tensor | None, card_albedo: float,
                    saturation_level: float | None, card_height_mm: float) -> NearLightResult:
        """Flat-field and solve one chunk of the batch with near light."""
        config = self.config
        if self.pixel_pitch_mm is None:  # refused by __init__, unless the attribute was set to None since
            raise InputError("the near-light solver needs the pixel pitch (mm per pixel on the cloth); got None")
        # the card's readings that saturate are predicted from the light model's shading on the card (the LEDs
        # nearest a corner saturate it there, and would otherwise take every reading there out of the fit)
        shading = None
        if reference is not None and saturation_level is not None:  # (1, K, H, W): E_k l_z on the card
            plane = torch.full_like(images[:1, :1], card_height_mm)
            shading = near_light_vectors(self.lights, plane, self.pixel_pitch_mm)[:, :, 2]
        flat = flatfield(images, reference, dark, reference_dark, card_albedo, config.min_reference, saturation_level,
                         card_smoothing_px=config.card_smoothing_px, card_shading=shading)
        card_height = card_height_mm if reference is not None else None
        return solve_near_light(flat.images, self.lights, self.pixel_pitch_mm, card_height, flat.valid, mask,
                                config.near_options(mask is not None), flat.gain)

    def _solve_distant(self, images: Tensor, reference: Tensor | None, dark: Tensor | None,
                       reference_dark: Tensor | None, mask: Tensor | None, card_albedo: float,
                       saturation_level: float | None, matrices: tuple[Tensor, Tensor],
                       into: tuple[Tensor, Tensor] | None, workspace: list[Tensor]) -> tuple[Tensor, Tensor]:
        """Flat-field and solve one chunk of the batch with the distant solver: its albedo and normals with
        ``matrices``, the light matrix (:func:`distant_light_matrix`) and its pseudo-inverse, written into ``into``
        (albedo, normals) where least squares can write them there (no gradient to record).

        With least squares and no gradient to record, the flat-fielded images go into ``workspace[0]`` (the first
        chunk's, kept there; least squares returns nothing that aliases them): a fresh 5 MB tensor per capture was
        page-faulted in on first touch, and the dark subtraction writing it measured 1.3-1.7 ms per capture in
        profiles of a batch of 8 x 400^2 on one thread, against 0.57 ms into the reused buffer.
        """
        config = self.config
        matrix, pinv = matrices
        reusable = self.estimator == "lstsq" and not records_gradient(images, reference, dark, reference_dark)
        buffer = workspace[0][: images.shape[0]] if reusable and workspace else None
        flat = flatfield(images, reference, dark, reference_dark, card_albedo, config.min_reference, saturation_level,
                         card_smoothing_px=config.card_smoothing_px, out=buffer)
        if reusable and not workspace:
            workspace.append(flat.images)
        all_valid = flat.all_valid if flat.all_valid is not None else all_true(flat.valid)
        weights = None if all_valid else flat.valid
        if self.estimator == "lstsq":
            into = None if records_gradient(flat.images, pinv) else into
            if weights is None:
                # the flat-fielded images are finite (flatfield checked the frames), the pseudo-inverse the batch's
                return _solve_with_pinv(flat.images, pinv, None if mask is None else mask.bool(), out=into)
            return albedo_normals(flat.images, matrix, mask, weights, out=into)
        return NORMAL_ESTIMATORS[self.estimator](flat.images, matrix, mask, weights, config.estimator_options)


def _check_some_solved(solved: Tensor, masked: bool) -> None:
    """Refuse a batch item without any solved pixel: it failed in the integrator as "mask must select at least one
    pixel ..., got an empty mask", a mask the caller had not given (all-zero images)."""
    empty = ~solved.flatten(1).any(dim=1)
    if bool(empty.any()):
        where = " inside the mask" if masked else ""
        raise InputError(f"no pixel could be solved{where} in batch item(s) {empty.nonzero().flatten().tolist()}: "
                         "every pixel there has albedo 0 (dark images, readings all 0, or fewer than three usable "
                         "lights), so there is nothing to integrate")


def _assemble(parts: list[slice], solve: Callable[[slice, tuple[Tensor, Tensor] | None], tuple[Tensor, Tensor]]
              ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Albedo, normals and slopes p, q (:func:`~psmini.normals.normals_to_gradients`) of a batch solved chunk by
    chunk, ``solve(part)`` giving a chunk's albedo and normals.

    Each chunk's results are written into the batch's tensors as it comes, its slopes computed from its normals
    while they are still in the cache: concatenating the chunks afterwards, then taking the slopes of the whole
    batch, made two more passes over its normals (0.4-0.5 of 7.7 ms per 8 x 400^2 capture on one thread of the
    2-core Xeon). After the first chunk, ``solve(part, into)`` may write a chunk's albedo and normals straight
    into the batch's (``into``), and the slopes go straight into theirs, when no gradient is recorded: the copies
    of each chunk's results cost 0.3-0.4 ms per capture. Writes into slices are differentiable like a
    concatenation.
    """
    first_albedo, first_normals = solve(parts[0], None)
    if len(parts) == 1:
        return first_albedo, first_normals, *_slopes_of(first_normals)
    batch = parts[-1].stop
    albedo = first_albedo.new_empty((batch, *first_albedo.shape[1:]))
    normals = first_normals.new_empty((batch, *first_normals.shape[1:]))
    slopes = first_normals.new_empty((batch, 2, *first_normals.shape[2:]))
    for index, part in enumerate(parts):
        into = None if index == 0 else (albedo[part], normals[part])
        chunk_albedo, chunk_normals = (first_albedo, first_normals) if into is None else solve(part, into)
        if into is None or chunk_albedo.data_ptr() != into[0].data_ptr():
            albedo[part], normals[part] = chunk_albedo, chunk_normals
        if records_gradient(chunk_normals):
            slopes[part, 0:1], slopes[part, 1:2] = _slopes_of(chunk_normals)
        else:
            _slopes_of(chunk_normals, out=slopes[part])
    return albedo, normals, slopes[:, 0:1], slopes[:, 1:2]


def reconstruct(sample, config: ReconstructionConfig | None = None) -> Reconstruction:
    """Reconstruct one loaded sample (:func:`psmini.io.load_sample`) with ``config``.

    The pixel pitch, mask, card, dark frames and saturation level come from the sample: a DiLiGenT folder has no
    pitch, so its depth is in pixel units (and its mask makes ``auto`` integrate over the object only).

    Args:
        sample: a :class:`psmini.io.Sample` (DiLiGenT or capture folder).
        config: the :class:`~psmini.config.ReconstructionConfig` (default: ``ReconstructionConfig()``, near light
            for LED and point models, least squares for distant lights); its ``device`` and ``dtype`` say where
            and how to compute.

    Returns:
        :class:`Reconstruction` with batch size 1, on the config's device.

    Raises:
        InputError: a configuration that does not fit the sample (see :class:`PhotometricStereo`), or that is not
            a ReconstructionConfig; something that is not a loaded sample (a tensor of images: those go to
            :class:`PhotometricStereo`).

    Example:
        >>> from psmini.io import Sample
        >>> from psmini.lights import DirectionalLights, ring_lights
        >>> lights = DirectionalLights(ring_lights(8, 55.0))
        >>> sample = Sample(name="random", images=torch.rand(8, 16, 16) + 0.1, lights=lights)
        >>> reconstruct(sample).normals.shape
        torch.Size([1, 3, 16, 16])
    """
    if isinstance(sample, Tensor) or getattr(sample, "images", None) is None:  # psmini.io is a layer above
        raise InputError(f"reconstruct needs a loaded sample (psmini.io.Sample, e.g. from psmini.io.load_sample), "
                         f"got {type(sample).__name__}; reconstruct image tensors with "
                         "PhotometricStereo(lights, pixel_pitch_mm)(images)")
    check_tensor(sample.images, "sample.images")
    config = ReconstructionConfig() if config is None else config
    if not isinstance(config, ReconstructionConfig):  # a solver name failed as a bare AttributeError on device
        raise InputError(f"config must be a ReconstructionConfig, got {type(config).__name__}")
    device, dtype = torch.device(config.device), config.torch_dtype

    def batch(x: Tensor | None) -> Tensor | None:
        return None if x is None else x.to(device=device, dtype=dtype).unsqueeze(0)

    mask = None if sample.mask is None else sample.mask.to(device).unsqueeze(0)
    model = PhotometricStereo(sample.lights.to(device=device, dtype=dtype), sample.pixel_pitch_mm, config)
    return model(
        batch(sample.images),
        reference=batch(sample.reference),
        dark=batch(sample.dark),
        reference_dark=batch(sample.reference_dark),
        mask=mask,
        card_albedo=sample.card_albedo or 1.0,
        saturation_level=sample.saturation_level,
    )
