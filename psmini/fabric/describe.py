"""Structure descriptors of a reconstruction and a code-free fabric classifier on them.

:func:`describe` gathers the ISO 25178-2 parameters (:func:`~psmini.fabric.iso25178`) and the yarn structure
(:func:`~psmini.fabric.fabric_structure`) of each sample into one JSON-ready dict; :func:`structure_row` flattens
it into the scalar columns of a feature table (``psmini batch --describe``); :func:`descriptor_vector` turns it
into the fixed-length, orientation-free vector a classifier uses. :class:`FabricClassifier` is a multinomial
logistic regression (standardised features, softmax of a linear map) stored as plain numbers with a format
version: loading it runs no code (no pickle).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psmini._tensor import masked_median
from psmini.errors import DataFormatError, InputError, ShapeError
from psmini.fabric.structure import StructureOptions, fabric_structure
from psmini.fabric.surface import (
    ISO_PARAMETERS,
    SurfaceOptions,
    iso25178,
    iso_s_cutoff_mm,
    scale_limited_surface,
    valid_pixels,
)

__all__ = ["WAVINESS_OPTIONS", "COUPLING_OPTIONS", "DESCRIBE_SURFACE_OPTIONS", "describe_surface_options",
           "DESCRIPTOR_NAMES", "MODEL_FORMAT", "MODEL_VERSION", "FabricClassifier", "albedo_periodicity",
           "albedo_relief_coupling", "describe", "describe_reconstruction", "descriptor_vector", "structure_row",
           "structure_surface", "reconstruct_for_description"]

#: The form removal and L-filter of the scale-limited surface on which :func:`describe` reports the ISO parameters:
#: plane removed, an L-filter of 2.5 mm (an ISO 25178-3 nesting index; it removes wrinkles and drape, keeps yarn
#: repeats up to ~1.5 mm). :func:`describe_surface_options` adds the S-filter that the pixel pitch calls for.
DESCRIBE_SURFACE_OPTIONS = SurfaceOptions(form_degree=1, l_cutoff_mm=2.5)


def describe_surface_options(pixel_pitch_mm: float) -> SurfaceOptions:
    """:data:`DESCRIBE_SURFACE_OPTIONS` with the S-filter ISO 25178-3 pairs with the pixel pitch
    (:func:`~psmini.fabric.iso_s_cutoff_mm`: 80 µm at 25 µm per pixel); none where that is not shorter than the
    L-filter.

    Without an S-filter, Sa and Sq depend on the relief of 2-3 pixels, which the slopes of photometric stereo
    sample differently from camera to camera (a pixel's mean slope, a central difference, a lens blur) and no
    integration restores: on psmini's satin (a 3.2-pixel warp) the true normals integrated read 2.7% / 4.6%
    short without it and 0.0% / 0.7% with it.

    Args:
        pixel_pitch_mm: pixel size on the cloth, mm.

    Returns:
        the :class:`~psmini.fabric.SurfaceOptions` :func:`describe` uses by default.

    Raises:
        InputError: a pitch that is not a positive number.

    Example:
        >>> describe_surface_options(0.025).s_cutoff_mm, describe_surface_options(0.025).l_cutoff_mm
        (0.08, 2.5)
    """
    s_cutoff = iso_s_cutoff_mm(pixel_pitch_mm)
    limit = DESCRIBE_SURFACE_OPTIONS.l_cutoff_mm
    if limit is not None and not s_cutoff < limit:
        return DESCRIBE_SURFACE_OPTIONS
    return replace(DESCRIBE_SURFACE_OPTIONS, s_cutoff_mm=s_cutoff)

#: The repeats :func:`descriptor_vector` gives an indicator each (the last one: this many threads or more): a
#: repeat is a category (a 5-end satin is no "more" a weave than a 4-end twill), which a linear classifier can
#: only use as one; :class:`~psmini.fabric.structure.StructureOptions`' default ``max_repeat``.
_REPEAT_CATEGORIES = 8

#: The entries of :func:`descriptor_vector`, in order (none depends on the cloth's orientation).
DESCRIPTOR_NAMES = (
    "Sq_um", "Ssk", "Sku", "Sz_um", "Sa_um", "Sdq", "Sdr_pct", "Sal_mm", "Str",
    "structure_found", "log_density_1", "log_density_2", "density_ratio", "crossing_angle_deg",
    "weave_repeat", "crimp_um", "openness", "log_sq_over_sal", "log_waviness_um", "albedo_relief_coupling",
    "log_albedo_periodicity", "repeat_min", "regular_weave",
    *(f"regular_repeat_is_{k}" for k in range(1, _REPEAT_CATEGORIES + 1)),
    *(f"irregular_repeat_is_{k}" for k in range(1, _REPEAT_CATEGORIES + 1)),
    *(f"repeat_min_is_{k}" for k in range(1, _REPEAT_CATEGORIES + 1)),
)

#: The band of :func:`describe`'s ``waviness_um``: relief between the yarn scale and the L-filter (prints, felting,
#: pilling), the Sq of the surface S-filtered at 0.5 mm and L-filtered at 2.5 mm.
WAVINESS_OPTIONS = SurfaceOptions(form_degree=1, s_cutoff_mm=0.5, l_cutoff_mm=2.5)

#: The band of :func:`describe`'s ``albedo_relief_coupling``: above the yarns' scale (0.5 mm S-filter), below
#: wrinkles and drape (1.25 mm L-filter), where a print's blotch edges and an ink layer's relief live.
COUPLING_OPTIONS = SurfaceOptions(form_degree=1, s_cutoff_mm=0.5, l_cutoff_mm=1.25)

#: :func:`describe`'s default structure options.
_STRUCTURE = StructureOptions()

MODEL_FORMAT = "psmini-fabric-classifier"
#: 4 since the structure descriptors of a reconstruction are read from its slopes (:func:`describe_reconstruction`):
#: a model trained on version 3's, read from near light's depth, would be fed values of another distribution.
MODEL_VERSION = 4


def reconstruct_for_description(sample: Any, config: Any = None) -> Any:
    """The one place where :func:`describe` callers reconstruct a loaded sample: psmini's default pipeline.

    Args:
        sample: a :class:`psmini.io.Sample`.
        config: the :class:`~psmini.config.ReconstructionConfig` (default: the default one: near light for the
            rig's LED captures, least squares for directional lights).

    Returns:
        a :class:`psmini.pipeline.Reconstruction` (batch of one).

    Raises:
        InputError: as :func:`psmini.pipeline.reconstruct`: something that is not a loaded sample (a tensor of
            images), a ``config`` that is not a ReconstructionConfig, a configuration that does not fit the sample.

    Example:
        >>> from psmini.io import Sample
        >>> from psmini.lights import DirectionalLights, ring_lights
        >>> lights = DirectionalLights(ring_lights(8, 55.0))
        >>> sample = Sample(name="s", images=torch.rand(8, 16, 16) + 0.1, lights=lights)
        >>> reconstruct_for_description(sample).depth.shape
        torch.Size([1, 1, 16, 16])
    """
    from psmini.pipeline import reconstruct

    return reconstruct(sample, config)


def albedo_relief_coupling(height: Tensor, albedo: Tensor, pixel_pitch_mm: float,
                           mask: Tensor | None = None) -> Tensor:
    r"""How the relief follows the albedo: the correlation of their gradients in the :data:`COUPLING_OPTIONS` band.

    .. math:: c = \frac{\sum \nabla h \cdot \nabla a}{\sqrt{\sum |\nabla h|^2 \sum |\nabla a|^2}}

    over the pixels whose central differences are valid, with h and a the height and the albedo (divided by its
    median) band-passed between 0.5 and 1.25 mm (ISO 16610-61 Gaussian S- and L-filters). An ink layer raised
    where it darkens the cloth gives c < 0 at the print's edges; a dye or print with no relief of its own, c near
    0 (or what the reconstruction's shading leaks into the albedo). Dimensionless, in [-1, 1]; invariant to the
    albedo's and the height's scale. Photometric stereo recovers albedo and relief separately, so this is a
    relief measurement conditioned on the albedo, not the albedo itself.

    Args:
        height: :math:`(B, 1, H, W)`, mm.
        albedo: :math:`(B, 1, H, W)`, any positive scale.
        pixel_pitch_mm: pixel size, mm.
        mask: optional valid pixels :math:`(B, 1, H, W)`.

    Returns:
        :math:`(B,)`; NaN where the band holds no gradient (a flat albedo or height).

    Raises:
        ShapeError: albedo of another shape than the height. InputError, ShapeError: as
            :func:`~psmini.fabric.scale_limited_surface`.

    Example:
        >>> y, x = torch.meshgrid(torch.arange(128.0), torch.arange(128.0), indexing="ij")
        >>> ink = torch.sigmoid(torch.cos(2 * math.pi * x / 64) * torch.cos(2 * math.pi * y / 64) * 8)[None, None]
        >>> round(float(albedo_relief_coupling(0.004 * ink, 0.8 - 0.6 * ink, 0.025)[0]), 3)
        -1.0
    """
    if not isinstance(albedo, Tensor) or albedo.shape != height.shape:
        raise ShapeError(f"albedo must have the height's shape {tuple(height.shape)}, got "
                         f"{tuple(albedo.shape) if isinstance(albedo, Tensor) else type(albedo).__name__}")
    valid = valid_pixels(height, mask) & torch.isfinite(albedo) & (albedo > 0)
    dt = height.dtype
    h, valid = scale_limited_surface(height, pixel_pitch_mm, valid, COUPLING_OPTIONS)
    a, _ = scale_limited_surface(_relative(albedo.to(dt), valid), pixel_pitch_mm, valid, COUPLING_OPTIONS)

    def gradient(z: Tensor) -> tuple[Tensor, Tensor]:
        return z[..., 1:-1, 2:] - z[..., 1:-1, :-2], z[..., :-2, 1:-1] - z[..., 2:, 1:-1]

    inner = valid[..., 1:-1, 1:-1] & valid[..., 1:-1, 2:] & valid[..., 1:-1, :-2] & valid[..., :-2, 1:-1] \
        & valid[..., 2:, 1:-1]
    (hx, hy), (ax, ay) = gradient(h), gradient(a)
    w = inner.to(dt)
    count = w.sum(dim=(1, 2, 3)).clamp_min(1)
    cross = ((hx * ax + hy * ay) * w).sum(dim=(1, 2, 3))
    hh = ((hx.square() + hy.square()) * w).sum(dim=(1, 2, 3))
    aa = ((ax.square() + ay.square()) * w).sum(dim=(1, 2, 3))
    # no gradient in the band: below 1e-5 of relative albedo and 1 nm of height per pixel (rounding of a flat map
    # through the filters; a print's edge is ~1e-2 per pixel, the faintest relief ~1e-4 mm)
    flat = (aa / count < 1e-10) | (hh / count < 1e-12) | (count < 2)
    norm = torch.sqrt(hh * aa).clamp_min(torch.finfo(dt).tiny)
    return torch.where(flat, torch.full_like(norm, math.nan), cross / norm)


def albedo_periodicity(albedo: Tensor, pixel_pitch_mm: float, mask: Tensor | None = None) -> Tensor:
    """The relative amplitude of the albedo's strongest periodic component (yarns of another colour or material).

    The albedo divided by its median is searched for spectral peaks exactly as a height is
    (:func:`~psmini.fabric.fabric_structure`: levelled, Hann-windowed, 18 dB above the local background, sub-bin
    refined), and the largest peak amplitude is returned: 0.2 for an albedo ``m (1 + 0.2 cos(2 pi f x))``. A dye
    scales the albedo and leaves it unchanged; a printed motif of blotches has no spectral peak; yarns of another
    colour or a metallic tape every few threads (a yarn-dyed stripe, Lurex) give one. 0 when no peak stands out.

    Args:
        albedo: :math:`(B, 1, H, W)`, any positive scale.
        pixel_pitch_mm: pixel size, mm.
        mask: optional valid pixels :math:`(B, 1, H, W)` (non-finite or non-positive albedo is excluded too).

    Returns:
        :math:`(B,)`, dimensionless.

    Raises:
        InputError, ShapeError: as :func:`~psmini.fabric.fabric_structure`.

    Example:
        >>> x = torch.arange(200.0).view(1, 200).expand(200, 200) * 0.025
        >>> albedo = 0.6 * (1 + 0.2 * torch.cos(2 * math.pi * x / 0.3))
        >>> round(float(albedo_periodicity(albedo[None, None], 0.025)[0]), 3)
        0.2
    """
    if not isinstance(albedo, Tensor) or albedo.ndim != 4 or albedo.shape[1] != 1:
        raise ShapeError(f"albedo must have shape (B, 1, H, W), got "
                         f"{tuple(albedo.shape) if isinstance(albedo, Tensor) else type(albedo).__name__}")
    valid = valid_pixels(albedo, mask) & (albedo > 0)
    found = fabric_structure(_relative(albedo, valid), pixel_pitch_mm, valid)
    return torch.tensor([max((p.amplitude_um for p in f.peaks), default=0.0) / 1000 for f in found],
                        dtype=albedo.dtype, device=albedo.device)


def _relative(albedo: Tensor, valid: Tensor) -> Tensor:
    """The albedo divided by each item's median over its valid pixels (1 for an item without any), 0 elsewhere."""
    return torch.where(valid, albedo / masked_median(albedo, valid), torch.zeros_like(albedo))


def describe(height: Tensor, pixel_pitch_mm: float, mask: Tensor | None = None, albedo: Tensor | None = None,
             surface: SurfaceOptions | None = None, structure: StructureOptions = _STRUCTURE,
             structure_height: Tensor | None = None) -> list[dict[str, Any]]:
    """ISO 25178-2 parameters and the yarn structure of each sample, as JSON-ready dicts.

    Args:
        height: :math:`(B, 1, H, W)`, mm.
        pixel_pitch_mm: pixel size, mm.
        mask: optional valid pixels :math:`(B, 1, H, W)` (unsolved pixels False).
        albedo: optional :math:`(B, 1, H, W)`; its mean and spread over the valid pixels are reported (not used
            by :func:`descriptor_vector`: dye and print are not structure), the :func:`albedo_relief_coupling` and
            the :func:`albedo_periodicity` (which are).
        surface: the scale-limited surface of the ISO parameters (default: :func:`describe_surface_options` of the
            pitch: plane removed, the ISO S-filter of the pitch, an L-filter of 2.5 mm).
        structure: options of :func:`~psmini.fabric.fabric_structure`.
        structure_height: optional :math:`(B, 1, H, W)` mm, the surface the yarn structure (densities, directions,
            repeat, crimp, openness, peaks) is read from instead of ``height``: a reconstruction's
            :func:`structure_surface`. The ISO parameters, the waviness and the coupling stay on ``height``.

    Returns:
        one dict per sample: ``threads_per_cm``, ``thread_angles_deg``, ``weave_repeat``, ``float_length``,
        ``wales_per_cm``, ``courses_per_cm``, ``crimp_um``, ``openness``, ``structure_found``,
        ``structure_reason``, ``iso25178`` (name to value, units in ``iso25178_units``), ``waviness_um`` (Sq of
        the band between 0.5 and 2.5 mm: relief between the yarns' scale and the L-filter), ``albedo_mean``,
        ``albedo_std``, ``albedo_relief_coupling`` and ``albedo_periodicity`` (None without albedo),
        ``pixel_pitch_mm``, ``peaks`` (the refined spectral peaks).

    Raises:
        InputError, ShapeError: as :func:`~psmini.fabric.iso25178`; a ``structure_height`` of another shape.

    Example:
        >>> y, x = torch.meshgrid(torch.arange(120.0), torch.arange(120.0), indexing="ij")
        >>> z = 0.03 * torch.cos(2 * math.pi * x * 0.025 / 0.2) * torch.cos(2 * math.pi * y * 0.025 / 0.2)
        >>> out = describe(z[None, None], 0.025)[0]
        >>> sorted(out["iso25178"])[:3], out["structure_found"]
        (['Sa', 'Sal', 'Sdq'], True)
    """
    from psmini.fabric.surface import ISO_UNITS, height_parameters, scale_limited_surface, valid_pixels

    if structure_height is not None and structure_height.shape != height.shape:
        raise ShapeError(f"structure_height must have the height's shape {tuple(height.shape)}, got "
                         f"{tuple(structure_height.shape)}")
    iso = iso25178(height, pixel_pitch_mm, mask, surface if surface is not None else describe_surface_options(
        pixel_pitch_mm))
    band, band_valid = scale_limited_surface(height, pixel_pitch_mm, mask, WAVINESS_OPTIONS)
    waviness = height_parameters(band, band_valid)["Sq"] * 1000
    found = fabric_structure(height if structure_height is None else structure_height, pixel_pitch_mm, mask,
                             structure)
    valid = valid_pixels(height, mask)
    coupling = albedo_relief_coupling(height, albedo, pixel_pitch_mm, mask) if albedo is not None else None
    periodicity = albedo_periodicity(albedo, pixel_pitch_mm, valid) if albedo is not None else None
    out = []
    for i, result in enumerate(found):
        entry = result.to_dict()
        entry["structure_found"] = entry.pop("found")
        entry["structure_reason"] = entry.pop("reason")
        entry["iso25178"] = {k: _number(v[i]) for k, v in iso.items()}
        entry["iso25178_units"] = dict(ISO_UNITS)
        entry["pixel_pitch_mm"] = float(pixel_pitch_mm)
        entry["waviness_um"] = _number(waviness[i])
        entry["albedo_relief_coupling"] = _number(coupling[i]) if coupling is not None else None
        entry["albedo_periodicity"] = _number(periodicity[i]) if periodicity is not None else None
        if albedo is not None:
            values = albedo[i][valid[i]]
            entry["albedo_mean"] = _number(values.mean()) if values.numel() else None
            entry["albedo_std"] = _number(values.std()) if values.numel() > 1 else None
        out.append(entry)
    return out


def structure_surface(p: Tensor, q: Tensor, pixel_pitch_mm: float, mask: Tensor | None = None,
                      max_slope_deg: float = 80.0) -> Tensor:
    r"""The surface a reconstruction's yarn structure is read from: its slopes integrated without weights.

    Frankot–Chellappa on the mirrored field (:func:`psmini.integrate.frankot_chellappa`) divides the slopes'
    spectrum by the derivative's own, :math:`i\omega`, at every frequency, so the lattice the slopes hold is this
    surface's, up to the finest threads (a silk's 2.4 pixels, which a least-squares solve's trapezoidal edges would
    damp to a quarter and lose). A reconstruction's ``depth`` is integrated for another aim: near light weighs each
    slope by its inverse variance, which is right for the height's error but lets the integration cut across the
    steep flanks between paired threads (a 2/2 rib's or basket's), and their groove, and with it every other thread
    of the density, can be lost (measured in ``docs/guides/fabric.md``). Amplitudes (the ISO parameters) are not
    read here: an unweighted integration carries a hole's step and a wall's noise into the relief.

    Unweighted, one grazing normal would carry a step of up to a hundred pixels' pitch (the :math:`n_z \ge 0.01`
    clamp of :func:`~psmini.normals.normals_to_gradients`) into every pixel beyond it: on psmini's jute a few
    hundred such pixels bent a 6.4 mm field by 1.2 mm and hid its lattice at 160 and 256 pixels. So each slope is
    limited to ``max_slope_deg`` from the card's plane along its own direction: a facet steeper than 80° is a wall
    that the rig's LEDs, about 32° above the cloth's plane, light at grazing incidence from half the ring at most,
    whose slope no reading determines (limits of 72-84° read psmini's cotton and jute alike).

    Args:
        p: :math:`\partial z/\partial x`, :math:`(B, 1, H, W)` (x right).
        q: :math:`\partial z/\partial y`, :math:`(B, 1, H, W)` (y up).
        pixel_pitch_mm: pixel size, mm.
        mask: optional solved pixels :math:`(B, 1, H, W)`; a slope outside it is no measurement and is taken as 0
            (what a reconstruction folder's ``normals.png`` holds there, so that a folder and the reconstruction in
            memory read alike).
        max_slope_deg: the steepest facet kept, degrees in (0, 90); a steeper slope is scaled down to it.

    Returns:
        height, mm, :math:`(B, 1, H, W)`, zero mean.

    Raises:
        InputError, ShapeError: as :func:`~psmini.integrate.frankot_chellappa`; a mask of another shape; a
            ``max_slope_deg`` outside (0, 90).

    Example:
        >>> x = torch.arange(64.0).expand(64, 64) * 0.025
        >>> p = (0.02 * 2 * math.pi / 0.5 * torch.cos(2 * math.pi * x / 0.5))[None, None]
        >>> z = structure_surface(p, torch.zeros_like(p), 0.025)
        >>> round(float(z.max() - z.min()), 3)
        0.04
    """
    from psmini.integrate import frankot_chellappa

    if p.shape != q.shape:
        raise ShapeError(f"p and q must have one shape, got {tuple(p.shape)} and {tuple(q.shape)}")
    if not 0 < max_slope_deg < 90:
        raise InputError(f"max_slope_deg must be in (0, 90) degrees, got {max_slope_deg!r}")
    if mask is not None and mask.shape != p.shape:
        raise ShapeError(f"mask must have the slopes' shape {tuple(p.shape)}, got {tuple(mask.shape)}")
    limit = math.tan(math.radians(max_slope_deg))
    scale = limit * torch.rsqrt((p.square() + q.square()).clamp_min(limit**2))  # 1 up to the limit; smooth at 0
    if mask is not None:
        scale = scale * mask
    return frankot_chellappa(p * scale, q * scale, pixel_pitch_mm)


def describe_reconstruction(reconstruction: Any, pixel_pitch_mm: float, surface: SurfaceOptions | None = None,
                            structure: StructureOptions = _STRUCTURE) -> list[dict[str, Any]]:
    """:func:`describe` of a reconstruction: the ISO parameters of its depth over its mask, with its albedo, and
    the yarn structure from its slopes (:func:`structure_surface`).

    Args:
        reconstruction: anything with ``depth`` and ``mask`` :math:`(B, 1, H, W)`, ``p`` and ``q`` (the slopes,
            :math:`(B, 1, H, W)`; None: the structure read from the depth, as for a height map alone) and
            optionally ``albedo`` (a :class:`psmini.pipeline.Reconstruction` has them all).
        pixel_pitch_mm: pixel size, mm.
        surface: as :func:`describe`.
        structure: as :func:`describe`.

    Returns:
        one :func:`describe` dict per sample.

    Raises:
        InputError, ShapeError: as :func:`describe`; an InputError for something that is not a reconstruction (no
            ``depth`` or ``mask``: a height tensor goes to :func:`describe`).

    Example:
        >>> from psmini.result import Reconstruction
        >>> x = torch.arange(128.0).expand(128, 128) * 0.025
        >>> z = (0.02 * torch.sin(2 * math.pi * x / 0.25))[None, None]
        >>> p = 0.02 * 2 * math.pi / 0.25 * torch.cos(2 * math.pi * x / 0.25)[None, None]
        >>> rec = Reconstruction(torch.ones_like(z), torch.zeros(1, 3, 128, 128), p, torch.zeros_like(z), z, z > -1)
        >>> round(describe_reconstruction(rec, 0.025)[0]["threads_per_cm"][0], 2)
        40.0
    """
    _check_reconstruction(reconstruction)
    p, q, mask = getattr(reconstruction, "p", None), getattr(reconstruction, "q", None), reconstruction.mask
    structure_height = structure_surface(p, q, pixel_pitch_mm, mask) if p is not None and q is not None else None
    return describe(reconstruction.depth, pixel_pitch_mm, mask, getattr(reconstruction, "albedo", None), surface,
                    structure, structure_height)


def _check_reconstruction(reconstruction: Any) -> None:
    """Raise :class:`InputError` unless ``reconstruction`` has ``depth`` and ``mask`` (a height tensor failed as a
    bare AttributeError, or as a "height must be a torch.Tensor, got NoneType" in :func:`structure_row`)."""
    missing = [name for name in ("depth", "mask") if not hasattr(reconstruction, name)]
    if missing:
        raise InputError(f"reconstruction must have depth and mask (a psmini.pipeline.Reconstruction), got "
                         f"{type(reconstruction).__name__} without {' or '.join(missing)}; describe a height map "
                         "with describe(height, pixel_pitch_mm, mask)")


def _number(x: Tensor | float) -> float | None:
    """A finite float, or None (JSON has no NaN or infinity)."""
    value = float(x)
    return value if math.isfinite(value) else None


def structure_row(reconstruction: Any, pixel_pitch_mm: float | None) -> dict[str, Any]:
    """The scalar columns a feature table (``summary.csv`` of ``psmini batch --describe``) gets for one sample.

    Args:
        reconstruction: a :class:`psmini.pipeline.Reconstruction` with a batch of one, or anything with its
            ``depth``, ``mask``, ``p`` and ``q`` (:func:`describe_reconstruction`: the ISO parameters from the depth,
            the structure from the slopes; ``p`` or ``q`` None, from the depth).
        pixel_pitch_mm: the sample's pixel size, mm; ``None`` (unknown, DiLiGenT) gives empty structure columns.

    Returns:
        ``{"threads_per_cm_1", "threads_per_cm_2", "thread_angle_1_deg", "thread_angle_2_deg", "weave_repeat",
        "repeat_threads_1", "repeat_threads_2", "crimp_um", "openness", "structure_found", "structure_reason",
        "Sq_um", ..., "Std_deg"}`` (the repeats along the two systems in the densities' order); numbers or
        ``None`` (empty cells) where not defined.

    Raises:
        InputError, ShapeError: as :func:`describe_reconstruction` (with a pixel pitch): an InputError for something
            that is not a reconstruction (no ``depth`` or ``mask``).

    Example:
        >>> from psmini.result import Reconstruction
        >>> z = torch.zeros(1, 1, 32, 32)
        >>> rec = Reconstruction(torch.ones_like(z), torch.zeros(1, 3, 32, 32), z, z, z, z > -1)
        >>> row = structure_row(rec, 0.025)
        >>> row["structure_found"], row["Sq_um"]
        (False, 0.0)
    """
    columns = ["threads_per_cm_1", "threads_per_cm_2", "thread_angle_1_deg", "thread_angle_2_deg", "weave_repeat",
               "repeat_threads_1", "repeat_threads_2", "crimp_um", "openness", "structure_found", "structure_reason"]
    iso_columns = [f"{k}_{_unit_suffix(k)}" if _unit_suffix(k) else k for k in ISO_PARAMETERS]
    if pixel_pitch_mm is None:
        row = dict.fromkeys(columns + iso_columns)
        row["structure_found"] = False
        row["structure_reason"] = "the pixel pitch is unknown: no lengths in mm"
        return row
    _check_reconstruction(reconstruction)

    def first_sample(name: str) -> Tensor | None:
        value = getattr(reconstruction, name, None)
        return None if value is None else value[:1]

    first = SimpleNamespace(**{name: first_sample(name) for name in ("depth", "mask", "p", "q")})
    entry = describe_reconstruction(first, pixel_pitch_mm)[0]
    density = (entry["threads_per_cm"] or []) + [None, None]
    angles = (entry["thread_angles_deg"] or []) + [None, None]
    repeats = (entry.get("repeat_threads") or []) + [None, None]
    row = {"threads_per_cm_1": density[0], "threads_per_cm_2": density[1], "thread_angle_1_deg": angles[0],
           "thread_angle_2_deg": angles[1], "weave_repeat": entry["weave_repeat"], "repeat_threads_1": repeats[0],
           "repeat_threads_2": repeats[1], "crimp_um": entry["crimp_um"],
           "openness": entry["openness"], "structure_found": entry["structure_found"],
           "structure_reason": entry["structure_reason"]}
    for key, column in zip(ISO_PARAMETERS, iso_columns, strict=True):
        row[column] = entry["iso25178"][key]
    return row


def _unit_suffix(name: str) -> str:
    from psmini.fabric.surface import ISO_UNITS

    return {"um": "um", "%": "pct", "mm": "mm", "deg": "deg"}.get(ISO_UNITS[name], "")


def descriptor_vector(entry: dict[str, Any]) -> np.ndarray:
    """The orientation-free feature vector (:data:`DESCRIPTOR_NAMES`) of one :func:`describe` entry.

    Densities enter as logarithms (a scale change is a shift), the two systems' crossing angle instead of their
    directions, the repeat as the larger (``weave_repeat``) and the smaller of the two systems' repeats (a 2/2 rib:
    4 and 2), ``regular_weave`` 1 for a weave whose interlacing one shift generates (plain, twill, satin; not a
    basket or a rib), and a missing structure as zeros with ``structure_found`` 0; without albedo, the coupling as
    0 and the albedo periodicity as log(0.001). Both repeats also enter as indicators (k = 1..8, the last for 8 or
    more): a repeat is a category, and a linear classifier on the number alone cannot tell a 2/2 basket (4) from a
    3/1 twill (4) and a 5-end satin (5) apart from the amplitudes, which change with the capture
    (``benchmarks/fabric_recognition.py --protocol shift`` measures it). The larger repeat's indicators are split
    by ``regular_weave`` (``regular_repeat_is_k``: one shift generates the interlacing; ``irregular_repeat_is_k``:
    none does, or no interlacing was resolved, a repeat of 1 included), because a weave is its repeat *and* how
    its crossings are placed in it: a 2/2 basket and a 3/1 twill share the repeat 4, and from one indicator of the
    repeat and one of regularity a linear model must learn their conjunction; strongly regularised, it leaned on
    amplitudes instead (baskets read as 3/1 twills under shift). ``repeat_min_is_k`` are the smaller repeat's.

    Raises:
        InputError: an entry that is not a dict with an ``iso25178`` dict (one :func:`describe` entry, not the list
            of them).

    Example:
        >>> entry = {"iso25178": dict.fromkeys(ISO_PARAMETERS, 1.0), "structure_found": False}
        >>> descriptor_vector(entry).shape
        (47,)
    """
    iso = _iso_of_entry(entry)

    def num(x: Any) -> float:
        return float(x) if x is not None and math.isfinite(float(x)) else 0.0

    density = list(entry.get("threads_per_cm") or [])
    angles = list(entry.get("thread_angles_deg") or [])
    found = bool(entry.get("structure_found"))
    d1 = density[0] if found and density else 0.0
    d2 = density[1] if found and len(density) > 1 else 0.0
    crossing = abs((angles[0] - angles[1] + 90.0) % 180.0 - 90.0) if found and len(angles) > 1 else 0.0
    repeats = list(entry.get("repeat_threads") or []) if found else []
    sal = num(iso.get("Sal"))
    regular = 1.0 if found and num(entry.get("weave_repeat")) >= 2 and entry.get("float_length") is not None else 0.0
    values = [num(iso.get("Sq")), num(iso.get("Ssk")), num(iso.get("Sku")), num(iso.get("Sz")), num(iso.get("Sa")),
              num(iso.get("Sdq")), num(iso.get("Sdr")), sal, num(iso.get("Str")), float(found),
              math.log(d1) if d1 > 0 else 0.0, math.log(d2) if d2 > 0 else 0.0, d2 / d1 if d1 > 0 else 0.0, crossing,
              num(entry.get("weave_repeat")), num(entry.get("crimp_um")), num(entry.get("openness")),
              math.log(num(iso.get("Sq")) / 1000 / sal) if sal > 0 and num(iso.get("Sq")) > 0 else 0.0,
              math.log(num(entry.get("waviness_um"))) if num(entry.get("waviness_um")) > 0 else 0.0,
              num(entry.get("albedo_relief_coupling")), math.log(num(entry.get("albedo_periodicity")) + 1e-3),
              float(min(repeats)) if repeats else 0.0,
              regular]
    largest = int(num(entry.get("weave_repeat"))) if found else 0
    smallest = min(repeats) if repeats else 0
    largest_is = [float(min(largest, _REPEAT_CATEGORIES) == k) for k in range(1, _REPEAT_CATEGORIES + 1)]
    values += [regular * v for v in largest_is] + [(1.0 - regular) * v for v in largest_is]
    values += [float(min(smallest, _REPEAT_CATEGORIES) == k) for k in range(1, _REPEAT_CATEGORIES + 1)]
    return np.asarray(values, dtype=np.float64)


def _iso_of_entry(entry: object) -> dict[str, Any]:
    """The ``iso25178`` dict of one :func:`describe` entry (``{}`` failed as a bare KeyError)."""
    iso = entry.get("iso25178") if isinstance(entry, dict) else None
    if not isinstance(iso, dict):
        got = (f"a dict without an iso25178 dict (keys: {list(entry)[:6]})" if isinstance(entry, dict)
               else type(entry).__name__)
        raise InputError(f"entry must be one describe() entry, a dict with an iso25178 dict, got {got}"
                         + ("; pass the list's entries one by one" if isinstance(entry, list) else ""))
    return iso


@dataclass(frozen=True)
class FabricClassifier:
    """Multinomial logistic regression on standardised descriptors: ``softmax(((x - mean) / scale) W^T + b)``.

    Attributes:
        classes: class names, length C.
        feature_names: the descriptor names, length D (:data:`DESCRIPTOR_NAMES` for :func:`descriptor_vector`).
        mean, scale: standardisation, length D each.
        coef: weights, C x D.
        intercept: length C.
    """

    classes: tuple[str, ...]
    feature_names: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    coef: tuple[tuple[float, ...], ...]
    intercept: tuple[float, ...]

    def __post_init__(self) -> None:
        c, d = len(self.classes), len(self.feature_names)
        if c < 2 or d < 1:
            raise InputError(f"a classifier needs at least 2 classes and 1 feature, got {c} and {d}")
        if len(self.mean) != d or len(self.scale) != d or len(self.intercept) != c or len(self.coef) != c \
                or any(len(row) != d for row in self.coef):
            raise InputError(f"classifier arrays do not match {c} classes x {d} features")
        numbers = [*self.mean, *self.scale, *self.intercept, *(v for row in self.coef for v in row)]
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in numbers):
            raise InputError("classifier parameters must be finite numbers")
        if any(s <= 0 for s in self.scale):
            raise InputError("classifier scales must be positive")

    def predict_proba(self, features: np.ndarray) -> np.ndarray:
        """Class probabilities, shape (N, C), for features (N, D) or (D,).

        Example:
            >>> model = FabricClassifier(("a", "b"), ("x",), (0.0,), (1.0,), ((-1.0,), (1.0,)), (0.0, 0.0))
            >>> model.predict_proba(np.array([2.0])).round(3).tolist()
            [[0.018, 0.982]]
        """
        x = np.atleast_2d(np.asarray(features, dtype=np.float64))
        if x.shape[1] != len(self.feature_names):
            raise InputError(f"expected {len(self.feature_names)} features, got {x.shape[1]}")
        z = (x - np.asarray(self.mean)) / np.asarray(self.scale)
        logits = z @ np.asarray(self.coef).T + np.asarray(self.intercept)
        logits -= logits.max(axis=1, keepdims=True)
        p = np.exp(logits)
        return p / p.sum(axis=1, keepdims=True)

    def predict(self, features: np.ndarray) -> list[str]:
        """The most probable class of each row."""
        return [self.classes[k] for k in self.predict_proba(features).argmax(axis=1)]

    def to_dict(self) -> dict[str, Any]:
        """The JSON form, with :data:`MODEL_FORMAT` and :data:`MODEL_VERSION`."""
        return {"format": MODEL_FORMAT, "version": MODEL_VERSION, "classes": list(self.classes),
                "feature_names": list(self.feature_names), "mean": list(self.mean), "scale": list(self.scale),
                "coef": [list(r) for r in self.coef], "intercept": list(self.intercept)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FabricClassifier:
        """Read the JSON form; a :class:`DataFormatError` for another format or version, or missing fields.

        Example:
            >>> FabricClassifier.from_dict({"format": MODEL_FORMAT, "version": 99})
            Traceback (most recent call last):
            ...
            psmini.errors.DataFormatError: fabric model version 99 is not supported; this psmini reads version 4
        """
        if not isinstance(data, dict) or data.get("format") != MODEL_FORMAT:
            raise DataFormatError(f"not a fabric model: expected format {MODEL_FORMAT!r}, got "
                                  f"{data.get('format') if isinstance(data, dict) else type(data).__name__!r}")
        if data.get("version") != MODEL_VERSION:
            raise DataFormatError(f"fabric model version {data.get('version')} is not supported; this psmini reads "
                                  f"version {MODEL_VERSION}")
        try:
            return cls(tuple(str(c) for c in data["classes"]), tuple(str(f) for f in data["feature_names"]),
                       tuple(float(v) for v in data["mean"]), tuple(float(v) for v in data["scale"]),
                       tuple(tuple(float(v) for v in row) for row in data["coef"]),
                       tuple(float(v) for v in data["intercept"]))
        except (KeyError, TypeError, ValueError, InputError) as error:
            raise DataFormatError(f"fabric model is incomplete or malformed: {error}") from error
