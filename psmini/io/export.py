"""Export of reconstructions: albedo and normal-map PNGs, depth (``.npy`` + a shaded-relief preview), PLY files.

Inputs are tensors (or arrays) with a batch of one or none: albedo and depth :math:`(1, 1, H, W)`,
:math:`(1, H, W)` or :math:`(H, W)`; normals :math:`(1, 3, H, W)` or :math:`(3, H, W)`. OpenCV writes
BGR, so every colour image is swapped before writing (through :func:`psmini.io.images.write_image`).
"""

from __future__ import annotations

import datetime
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from torch import Tensor

from psmini.errors import DataFormatError, InputError, ShapeError
from psmini.geometry import depth_to_points
from psmini.io._atomic import atomic_folder
from psmini.io.images import write_image

__all__ = [
    "ALBEDO_PERCENTILE",
    "robust_max",
    "save_albedo_png",
    "save_normal_png",
    "save_depth",
    "save_ply",
    "save_mesh_ply",
    "save_normal_std",
    "write_outputs",
]

logger = logging.getLogger(__name__)

#: Albedo images are divided by this percentile of the albedo over the mask, so that a few specular or
#: badly solved pixels do not darken the whole picture; the brightest 0.5% saturate at 255.
ALBEDO_PERCENTILE = 99.5


def _as_array(x: Any, name: str) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().to("cpu", torch.float64 if x.is_floating_point() else x.dtype).numpy()
    if isinstance(x, np.ndarray):
        return x
    raise InputError(f"{name} must be a torch.Tensor or numpy array, got {type(x).__name__}")


def _planes(x: Any, name: str, channels: int) -> np.ndarray:
    """``x`` as (channels, H, W): accepts a batch of one, no batch, and (H, W) when channels == 1."""
    array = _as_array(x, name)
    if array.ndim == 4 and array.shape[0] == 1:
        array = array[0]
    if array.ndim == 2 and channels == 1:
        array = array[None]
    if array.ndim != 3 or array.shape[0] != channels:
        expected = f"(1, {channels}, H, W) or ({channels}, H, W)" + (" or (H, W)" if channels == 1 else "")
        raise ShapeError(f"{name} must have shape {expected} (a batch of one), got {array.shape}")
    return array


def _mask(mask: Any, height: int, width: int) -> np.ndarray:
    """The (H, W) bool mask; all True when ``mask`` is None."""
    if mask is None:
        return np.ones((height, width), dtype=bool)
    array = _planes(mask, "mask", 1)[0]
    if array.shape != (height, width):
        raise ShapeError(f"mask must be {height}x{width} (HxW) like the image, got {array.shape}")
    return array != 0


def _finite_inside(values: np.ndarray, inside: np.ndarray, name: str) -> None:
    bad = int(np.count_nonzero(~np.isfinite(values) & inside))  # no gathered copy: 0.08 ms where it took 2.7
    if bad:
        raise InputError(f"{name} holds {bad} NaN or infinite value(s) inside the mask")


def robust_max(values: Any, mask: Any = None, percentile: float = ALBEDO_PERCENTILE) -> float:
    """The ``percentile``-th percentile of ``values`` over ``mask`` (1.0 when nothing positive is there).

    Args:
        values: e.g. albedo, shape :math:`(N,)`, :math:`(H, W)` or with leading ones.
        mask: where to look, same number of elements, or None for everywhere.
        percentile: in (0, 100].

    Returns:
        the value used to scale ``values`` to [0, 1] for display.

    Raises:
        InputError: a percentile outside (0, 100].

    Example:
        >>> robust_max(np.arange(1001, dtype=float))
        995.0
    """
    if not 0 < percentile <= 100:
        raise InputError(f"percentile must be in (0, 100], got {percentile}")
    flat = _as_array(values, "values").reshape(-1)
    if mask is not None:
        flat = flat[_as_array(mask, "mask").reshape(-1) != 0]
    flat = flat[np.isfinite(flat)]
    if flat.size == 0:
        return 1.0
    top = float(np.percentile(flat, percentile))
    return top if top > 0 else 1.0


def save_albedo_png(path: str | Path, albedo: Any, mask: Any = None, *, percentile: float = ALBEDO_PERCENTILE) -> float:
    """Write albedo as an 8-bit gray PNG, divided by its robust maximum.

    ``value = round(255 * clip(albedo / robust_max, 0, 1))`` where ``robust_max`` is the ``percentile``-th
    percentile (default 99.5) of the albedo inside the mask; pixels outside the mask are 0.

    Args:
        path: the PNG file.
        albedo: shape :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`.
        mask: optional, same shapes, non-zero inside.
        percentile: the percentile taken as white.

    Returns:
        the albedo that maps to 255 (to recover albedo ≈ value / 255 · scale).

    Raises:
        ShapeError: bad shapes. InputError: NaN or infinite albedo inside the mask.
        DataFormatError: the file cannot be written.

    Example:
        >>> save_albedo_png("albedo.png", torch.rand(1, 1, 8, 8))  # doctest: +SKIP
    """
    values = _planes(albedo, "albedo", 1)[0]
    inside = _mask(mask, *values.shape)
    _finite_inside(values, inside, "albedo")
    scale = robust_max(values, inside, percentile)
    scaled = np.where(inside, np.clip(np.nan_to_num(values) / scale, 0.0, 1.0), 0.0)
    write_image(path, np.rint(scaled * 255).astype(np.uint8))
    return scale


def save_normal_png(path: str | Path, normals: Any, mask: Any = None, *, bit_depth: int = 8) -> None:
    """Write a normal map as an RGB PNG with ``RGB = (n + 1) / 2``, the usual blue-ish picture.

    R holds n_x (right), G n_y (up), B n_z (toward the camera), so a flat surface facing the camera is
    (128, 128, 255) in 8 bits. Channels are swapped to BGR for OpenCV, so viewers show RGB as intended.
    Pixels outside the mask are black. Read back with ``n = value / (2**bit_depth - 1) * 2 - 1``.

    Args:
        path: the PNG file.
        normals: unit normals, shape :math:`(1, 3, H, W)` or :math:`(3, H, W)`, camera frame.
        mask: optional, :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`, non-zero inside.
        bit_depth: 8 or 16.

    Raises:
        InputError: a bit depth other than 8 or 16, NaN or infinite normals inside the mask.
        ShapeError: bad shapes. DataFormatError: the file cannot be written.

    Example:
        >>> flat = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 4, 4)
        >>> save_normal_png("normals.png", flat)  # doctest: +SKIP
    """
    if bit_depth not in (8, 16):
        raise InputError(f"bit_depth must be 8 or 16, got {bit_depth!r}")
    values = _planes(normals, "normals", 3)
    inside = _mask(mask, *values.shape[1:])
    _finite_inside(values, inside, "normals")
    top = 2**bit_depth - 1
    rgb = np.clip((np.nan_to_num(values).transpose(1, 2, 0) + 1.0) / 2.0, 0.0, 1.0) * inside[..., None]
    write_image(path, np.rint(rgb * top).astype(np.uint8 if bit_depth == 8 else np.uint16))


def read_normal_png(path: str | Path) -> np.ndarray:
    """Read the normals :func:`save_normal_png` wrote: ``n = value / (2**bit_depth - 1) * 2 - 1``.

    Args:
        path: an 8- or 16-bit RGB ``normals.png``.

    Returns:
        the normals, ``float32``, :math:`(3, H, W)`, renormalised to unit length (the 8-bit file's rounding moves
        a normal by up to 0.3 degrees); outside the writer's mask (black pixels) NaN.

    Raises:
        DataFormatError: a missing, corrupt or non-RGB file.

    Example:
        >>> normals = read_normal_png("out/normals.png")  # doctest: +SKIP
        >>> normals.shape  # doctest: +SKIP
        (3, 400, 400)
    """
    from psmini.io.images import read_image

    image, _ = read_image(path)  # in [0, 1] whatever the bit depth
    if image.ndim != 3 or image.shape[2] != 3:
        raise DataFormatError(f"{path}: normals must be an RGB image, got shape {image.shape}")
    outside = ~image.any(axis=2)
    values = image.transpose(2, 0, 1) * np.float32(2) - np.float32(1)
    length = np.sqrt((values**2).sum(axis=0, keepdims=True))
    normals = values / np.maximum(length, np.float32(1e-6))
    normals[:, outside] = np.nan
    return normals


def save_depth(path: str | Path, depth: Any, mask: Any = None, *, units: str = "mm",
               pixel_pitch_mm: float | None = None) -> list[Path]:
    """Write depth as ``.npy`` (``float32``, NaN outside the mask), a picture to look at, and a JSON sidecar.

    The ``.npy`` file is the exact data. The ``.png`` is the preview of :func:`psmini.viz.depth_preview`: an 8-bit
    RGB hill-shaded relief in viridis between the 1st and 99th percentiles of the height over the mask, a colour
    bar with those limits and the unit, a scale bar (mm with ``pixel_pitch_mm``, else pixels), and unsolved pixels
    hatched in light gray and white. The sidecar ``<stem>.json`` records ``units``, the exact ``min`` and ``max``,
    the preview's ``preview_limits`` and how the preview is drawn.

    Args:
        path: the ``.npy`` file; the preview and sidecar take the same stem (``depth.png``, ``depth.json``).
        depth: height toward the camera, shape :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`.
        mask: optional, same shapes, non-zero inside.
        units: the unit of ``depth``, recorded in the sidecar (``"pixels"`` when no pixel pitch is known).
        pixel_pitch_mm: size of a pixel, mm, for the preview's shading and scale bar; None when unknown.

    Returns:
        the three paths written (``.npy``, ``.png``, ``.json``).

    Raises:
        ShapeError: bad shapes. InputError: NaN or infinite depth inside the mask, or an empty mask.
        DataFormatError: a file cannot be written.

    Example:
        >>> save_depth("depth.npy", torch.zeros(1, 1, 8, 8))  # doctest: +SKIP
    """
    from psmini.viz import depth_preview, robust_limits

    path = Path(path)
    values = _planes(depth, "depth", 1)[0]
    inside = _mask(mask, *values.shape)
    if not inside.any():
        raise InputError("the mask is empty: there is no depth to write")
    _finite_inside(values, inside, "depth")
    exact = np.where(inside, values, np.nan).astype(np.float32)
    low, high = float(np.min(exact[inside])), float(np.max(exact[inside]))
    limits = robust_limits(exact, inside)
    preview = depth_preview(exact, inside, pixel_pitch_mm, limits=limits, units=units)
    sidecar = {
        "npy": path.name,
        "png": path.with_suffix(".png").name,
        "units": units,
        "min": low,
        "max": high,
        "preview_limits": list(limits),
        "png_encoding": "a picture, not data: viridis between preview_limits (1st-99th percentile over the mask), "
        "hill-shaded from the upper left, scale bar and colour bar drawn in; unsolved pixels hatched gray/white",
    }
    try:
        np.save(path.with_suffix(".npy"), exact)
        path.with_suffix(".json").write_text(json.dumps(sidecar, indent=2) + "\n", encoding="utf-8")
    except OSError as error:
        raise DataFormatError(f"cannot write depth next to {path}: {error}") from error
    write_image(path.with_suffix(".png"), preview)
    return [path.with_suffix(".npy"), path.with_suffix(".png"), path.with_suffix(".json")]


def _vertex_rows(x: Any, name: str, count: int | None) -> np.ndarray:
    """(N, C) rows from (N, C), (N,), or channel-first images (1, C, H, W) / (C, H, W)."""
    array = _as_array(x, name)
    if array.ndim == 4 and array.shape[0] == 1:
        array = array[0]
    if array.ndim == 3:
        array = array.reshape(array.shape[0], -1).T
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2 or (count is not None and array.shape[0] != count):
        expected = f"{count} rows" if count is not None else "(N, 3) or (3, H, W)"
        raise ShapeError(f"{name} must give {expected}, got shape {_as_array(x, name).shape}")
    return array


def _colors_uint8(colors: Any, count: int, inside: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB from uint8 colours, float RGB in [0, 1], or albedo (scaled by its robust max)."""
    rows = _vertex_rows(colors, "colors", count)
    if rows.shape[1] not in (1, 3):
        raise ShapeError(f"colors must have 1 (albedo) or 3 (RGB) channels, got {rows.shape[1]}")
    if rows.dtype == np.uint8:
        return np.repeat(rows, 3 // rows.shape[1], axis=1)
    _finite_inside(rows.T, inside, "colors")
    rows = np.nan_to_num(rows.astype(np.float64))
    if rows.shape[1] == 1:
        rows = np.repeat(rows / robust_max(rows[:, 0], inside), 3, axis=1)
    return np.rint(np.clip(rows, 0.0, 1.0) * 255).astype(np.uint8)


def save_ply(path: str | Path, points: Any, colors: Any = None, mask: Any = None) -> int:
    """Write a coloured point cloud as a binary little-endian PLY (with plyfile).

    Vertices have ``x, y, z`` (float32) and, with colours, ``red, green, blue`` (uchar).

    Args:
        path: the ``.ply`` file.
        points: shape :math:`(N, 3)`, or a point image :math:`(1, 3, H, W)` / :math:`(3, H, W)` (row-major).
        colors: optional, one per point: ``uint8`` RGB :math:`(N, 3)`; float RGB in [0, 1]; or albedo
            :math:`(N,)` / :math:`(1, H, W)` (gray, divided by its 99.5th percentile over the kept points).
        mask: optional points to keep, :math:`(N,)` or an image mask, non-zero = keep.

    Returns:
        the number of vertices written.

    Raises:
        ShapeError: shapes that do not give N points, colours or mask entries.
        InputError: NaN or infinite points (or float colours) among those kept.
        DataFormatError: the file cannot be written.

    Example:
        >>> save_ply("points.ply", torch.rand(100, 3), torch.rand(100))  # doctest: +SKIP
        100
    """
    xyz = _vertex_rows(points, "points", None)
    if xyz.shape[1] != 3:
        raise ShapeError(f"points must have 3 coordinates each, got shape {xyz.shape}")
    count = xyz.shape[0]
    inside = np.ones(count, dtype=bool) if mask is None else _vertex_rows(mask, "mask", count)[:, 0] != 0
    _finite_inside(xyz.T, inside, "points")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    rgb = None
    if colors is not None:
        rgb = _colors_uint8(colors, count, inside)[inside]
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertices = np.empty(int(inside.sum()), dtype=fields)
    for axis, key in enumerate("xyz"):
        vertices[key] = xyz[inside, axis]
    if rgb is not None:
        for channel, key in enumerate(("red", "green", "blue")):
            vertices[key] = rgb[:, channel]
    try:
        PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order="<").write(str(path))
    except OSError as error:
        raise DataFormatError(f"cannot write {path}: {error}") from error
    return int(vertices.shape[0])


def save_mesh_ply(path: str | Path, points: Any, colors: Any = None, mask: Any = None) -> tuple[int, int]:
    """Write the surface as a triangle mesh PLY: the pixel grid triangulated over the mask, coloured per vertex.

    Vertices are the mask's pixels (row-major, as in :func:`save_ply`); each 2×2 cell of the grid whose four
    corners are inside becomes two triangles, one with three corners inside becomes one
    (:func:`psmini.viz.triangulate_grid`), every face counter-clockwise seen from the camera. MeshLab, Blender
    and CloudCompare show it as a surface rather than a cloud of points.

    Args:
        path: the ``.ply`` file.
        points: a point image :math:`(1, 3, H, W)` or :math:`(3, H, W)` (e.g. :func:`psmini.geometry.depth_to_points`).
        colors: optional, as in :func:`save_ply`, one per pixel: albedo :math:`(1, H, W)` or RGB :math:`(3, H, W)`.
        mask: optional :math:`(H, W)` (or with leading ones), non-zero = a vertex.

    Returns:
        the number of vertices and of faces written.

    Raises:
        ShapeError: points that are not a 3-channel image, colours or mask of another size.
        InputError: NaN or infinite points (or float colours) inside the mask.
        DataFormatError: the file cannot be written.

    Example:
        >>> from psmini.geometry import depth_to_points
        >>> points = depth_to_points(torch.zeros(1, 1, 4, 4), 0.025)
        >>> save_mesh_ply("mesh.ply", points, torch.ones(1, 4, 4))  # doctest: +SKIP
        (16, 18)
    """
    from psmini.viz import triangulate_grid

    image = _planes(points, "points", 3)
    height, width = image.shape[1:]
    inside = _mask(mask, height, width)
    _finite_inside(image, inside, "points")
    index, faces = triangulate_grid(inside)
    xyz = image.reshape(3, -1)[:, index].T
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    rgb = None
    if colors is not None:
        rgb = _colors_uint8(colors, height * width, inside.reshape(-1))[index]
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertices = np.empty(index.size, dtype=fields)
    for axis, key in enumerate("xyz"):
        vertices[key] = xyz[:, axis]
    if rgb is not None:
        for channel, key in enumerate(("red", "green", "blue")):
            vertices[key] = rgb[:, channel]
    face_rows = np.empty(faces.shape[0], dtype=[("vertex_indices", "<i4", (3,))])
    face_rows["vertex_indices"] = faces
    elements = [PlyElement.describe(vertices, "vertex"),
                PlyElement.describe(face_rows, "face", len_types={"vertex_indices": "u1"})]
    try:
        PlyData(elements, text=False, byte_order="<").write(str(path))
    except OSError as error:
        raise DataFormatError(f"cannot write {path}: {error}") from error
    return int(index.size), int(faces.shape[0])


def _field(reconstruction: Any, name: str) -> Any:
    value = reconstruction.get(name) if isinstance(reconstruction, Mapping) else getattr(reconstruction, name, None)
    if value is None and name not in ("mask", "normal_std"):
        raise InputError(f"reconstruction lacks {name!r}; expected albedo, normals, depth (and optionally mask)")
    return value


#: ``normal_std.png`` maps a predicted error of this many degrees (or more) to white.
NORMAL_STD_PNG_MAX_DEG = 10.0


def _normal_std(values: Any, inside: np.ndarray) -> np.ndarray | None:
    """The (H, W) predicted angular errors of a reconstruction (None without them), like its mask, checked."""
    if values is None:
        return None
    array = _planes(values, "normal_std", 1)[0].astype(np.float32)
    if array.shape != inside.shape:
        raise ShapeError(f"normal_std must be {inside.shape[0]}x{inside.shape[1]} (HxW) like the image, got "
                         f"{array.shape}")
    if not np.isfinite(array[inside]).all() or (array[inside] < 0).any():
        raise InputError("normal_std must be finite and >= 0 (degrees) inside the mask")
    return array


def save_normal_std(path: str | Path, normal_std: Any, mask: Any = None) -> dict[str, float | None]:
    """Write each normal's predicted RMS angular error (near light's
    :attr:`~psmini.nearlight.NearLightResult.normal_std`): ``.npy`` float32 degrees, NaN outside the mask, and beside
    it a ``.png`` of the same name, 8-bit, 0 at 0° to 255 at :data:`NORMAL_STD_PNG_MAX_DEG` or more (0 outside).

    Args:
        path: destination ``.npy`` (the picture goes to the same path with ``.png``).
        normal_std: :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`, degrees.
        mask: the pixels to write, like ``normal_std`` (None: every pixel).

    Returns:
        ``{"normal_std_median_deg": m, "normal_std_png_max_deg": 10.0}`` (the median over the mask; None if empty).

    Raises:
        ShapeError: a map or mask of another shape. InputError: negative or non-finite values inside the mask.
        DataFormatError: the files cannot be written.

    Example:
        >>> save_normal_std("normal_std.npy", torch.full((1, 1, 4, 4), 0.5))  # doctest: +SKIP
        {'normal_std_median_deg': 0.5, 'normal_std_png_max_deg': 10.0}
    """
    path = Path(path)
    array = np.asarray(_planes(normal_std, "normal_std", 1)[0], dtype=np.float32)
    inside = _mask(mask, *array.shape)
    checked = _normal_std(array, inside)
    assert checked is not None
    try:
        np.save(path, np.where(inside, checked, np.nan).astype(np.float32))
    except OSError as error:
        raise DataFormatError(f"cannot write {path}: {error}") from error
    scaled = np.clip(checked / NORMAL_STD_PNG_MAX_DEG, 0, 1) * 255
    write_image(path.with_suffix(".png"), np.where(inside, np.round(scaled), 0).astype(np.uint8))
    median = float(np.median(checked[inside])) if inside.any() else None
    return {"normal_std_median_deg": median, "normal_std_png_max_deg": NORMAL_STD_PNG_MAX_DEG}


#: The bit depth of a reconstruction folder's ``normals.png``: ``psmini describe`` and ``batch --describe`` read the
#: folder's slopes back from it, and 8 bits round a normal by up to 0.3°, enough to move the repeat of a weak
#: interlacing (a fine plain weave's 1 µm).
NORMALS_BIT_DEPTH = 16


def write_outputs(
    out_dir: str | Path,
    reconstruction: Any,
    *,
    pixel_pitch_mm: float | None = None,
    normal_bit_depth: int = NORMALS_BIT_DEPTH,
    metadata: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> list[Path]:
    """Write a reconstruction's albedo, normals, depth and point cloud into ``out_dir``, atomically.

    Files: ``albedo.png`` (:func:`save_albedo_png`), ``normals.png`` (:func:`save_normal_png`), ``depth.npy``,
    ``depth.png``, ``depth.json`` (:func:`save_depth`), ``points.ply`` (:func:`save_ply`: orthographic points
    of :func:`psmini.geometry.depth_to_points` inside the mask, coloured by albedo), ``mesh.ply``
    (:func:`save_mesh_ply`: the same points triangulated over the mask) and ``outputs.json``
    (the file list, the albedo scale, the depth range, the pixel pitch, ``metadata``). A near-light result
    (:class:`~psmini.nearlight.NearLightResult`) adds each normal's predicted RMS angular error beside
    ``normals.png``: ``normal_std.npy`` (float32 degrees, NaN outside the mask) and ``normal_std.png``
    (:func:`save_normal_std`), with its median in ``outputs.json`` (``normal_std_median_deg``). Written into a
    temporary sibling folder and renamed into place.

    Args:
        out_dir: the output folder; must not exist unless ``overwrite``.
        reconstruction: a ``psmini.pipeline.Reconstruction`` or a mapping with ``albedo`` (:math:`(1, 1, H, W)`
            or :math:`(1, H, W)`), ``normals`` (:math:`(1, 3, H, W)` or :math:`(3, H, W)`), ``depth`` (like
            albedo, mm) and optionally ``mask`` (like albedo, bool) and ``normal_std`` (like albedo, degrees); a
            batch of one or none.
        pixel_pitch_mm: size of a pixel, mm, for the point cloud's x and y; None gives pixel units.
        normal_bit_depth: 8 or 16 for ``normals.png`` (:data:`NORMALS_BIT_DEPTH` by default).
        metadata: extra JSON-serialisable entries for ``outputs.json``.
        overwrite: replace an existing ``out_dir``.

    Returns:
        the paths of the files written, inside ``out_dir``.

    Raises:
        InputError, ShapeError: missing fields, bad shapes, non-finite values inside the mask.
        DataFormatError: ``out_dir`` exists (without ``overwrite``) or cannot be written; nothing is left at
            ``out_dir`` on failure.

    Example:
        >>> result = {"albedo": torch.rand(1, 1, 8, 8), "normals": torch.tensor([0.0, 0, 1]).view(1, 3, 1, 1)
        ...           .expand(1, 3, 8, 8), "depth": torch.zeros(1, 1, 8, 8)}
        >>> write_outputs("out", result, pixel_pitch_mm=0.025)  # doctest: +SKIP
    """
    out_dir = Path(out_dir)
    albedo = _planes(_field(reconstruction, "albedo"), "albedo", 1)
    normals = _planes(_field(reconstruction, "normals"), "normals", 3)
    depth = _planes(_field(reconstruction, "depth"), "depth", 1)
    height, width = albedo.shape[1:]
    if normals.shape[1:] != (height, width) or depth.shape[1:] != (height, width):
        raise ShapeError(
            f"albedo {albedo.shape[1:]}, normals {normals.shape[1:]} and depth {depth.shape[1:]} must share one size"
        )
    inside = _mask(_field(reconstruction, "mask"), height, width)
    normal_std = _normal_std(_field(reconstruction, "normal_std"), inside)  # checked before anything is written
    pitch = 1.0 if pixel_pitch_mm is None else float(pixel_pitch_mm)
    points = depth_to_points(torch.from_numpy(depth[None]), pitch)[0]
    names = ["albedo.png", "normals.png", "depth.npy", "depth.png", "depth.json", "points.ply", "mesh.ply"]
    names += ([] if normal_std is None else ["normal_std.npy", "normal_std.png"]) + ["outputs.json"]
    with atomic_folder(out_dir, overwrite) as target:
        scale = save_albedo_png(target / "albedo.png", albedo, inside)
        save_normal_png(target / "normals.png", normals, inside, bit_depth=normal_bit_depth)
        save_depth(target / "depth.npy", depth, inside, units="mm" if pixel_pitch_mm is not None else "pixels",
                   pixel_pitch_mm=pixel_pitch_mm)
        vertex_count = save_ply(target / "points.ply", points, albedo, inside[None])
        _, face_count = save_mesh_ply(target / "mesh.ply", points, albedo, inside)
        std_summary = {} if normal_std is None else save_normal_std(target / "normal_std.npy", normal_std, inside)
        summary = {
            "files": names[:-1],
            "size": [width, height],
            "albedo_scale": scale,
            "albedo_percentile": ALBEDO_PERCENTILE,
            "normal_bit_depth": normal_bit_depth,
            "pixel_pitch_mm": pixel_pitch_mm,
            "depth_units": "mm" if pixel_pitch_mm is not None else "pixels",
            "vertices": vertex_count,
            "faces": face_count,
            **std_summary,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "metadata": dict(metadata or {}),
        }
        try:
            text = json.dumps(summary, indent=2, allow_nan=False)
        except (TypeError, ValueError) as error:
            raise InputError(f"metadata does not serialise to JSON: {error}") from error
        (target / "outputs.json").write_text(text + "\n", encoding="utf-8")
    logger.info("wrote %s: %d vertices", out_dir, vertex_count)
    return [out_dir / name for name in names]
