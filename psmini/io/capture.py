"""The psmini capture folder, version 1: what the rig and the synthesiser write and ``reconstruct`` reads.

The specification is ``docs/capture-format.md``: a ``capture.json`` manifest beside one image per LED, an
optional dark frame and mask, an optional ``gt/`` folder of ground truth, and a reference to the
flat-field (matte card) capture taken under the same LEDs. Folders are written atomically (temporary
sibling, then rename) and validated fully on reading.
"""

from __future__ import annotations

import datetime
import functools
import json
import logging
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np
import torch
from torch import Tensor

from psmini.errors import DataFormatError, InputError, PsminiError
from psmini.io._atomic import atomic_folder
from psmini.io._npy import read_npy
from psmini.io.images import read_gray, read_image_stack, rgb_to_gray, write_image
from psmini.lights import LightModel, lights_from_dict, lights_to_dict

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "KINDS",
    "MANIFEST_NAME",
    "Capture",
    "read_manifest",
    "read_capture",
    "write_capture",
]

logger = logging.getLogger(__name__)

FORMAT_NAME = "psmini-capture"
FORMAT_VERSION = 1
MANIFEST_NAME = "capture.json"
KINDS = ("sample", "flatfield", "sphere", "focus")
BIT_DEPTHS = (8, 10, 12, 16)
_GT_SHAPES = {"normals": "(3, H, W)", "depth": "(H, W)", "albedo": "(H, W)", "mask": "(H, W)"}


# ------------------------------------------------------------------------------------------------ reading


@dataclass
class Capture:
    """A capture folder in memory (see ``docs/capture-format.md``).

    Attributes:
        path: the folder.
        kind: ``"sample"``, ``"flatfield"``, ``"sphere"`` or ``"focus"``.
        images: one gray image per LED (or focus position), shape :math:`(K, H, W)`, ``float32`` in [0, 1]
            (raw values divided by ``2**bit_depth - 1``).
        lights: the light model (None only for ``kind: "focus"`` captures without one).
        bit_depth: the sensor's bit depth (8, 10, 12 or 16).
        pixel_pitch_mm: size of one pixel on the object, mm.
        dark: all-LEDs-off frame, shape :math:`(1, H, W)`, same scale as ``images``, or None.
        mask: shape :math:`(1, H, W)` bool, or None.
        flatfield_path: the referenced flat-field capture folder (resolved), or None.
        card_albedo: the card's albedo: for a ``sample`` the referenced card's, for a ``flatfield`` its own.
        gt: ground truth tensors by name: ``normals`` :math:`(3, H, W)`, ``depth``, ``albedo`` :math:`(1, H, W)`,
            ``mask`` :math:`(1, H, W)` bool, and ``lights`` (a light module) when given.
        positions_mm: z position of each image, for ``kind: "focus"``; else None.
        crop: ``[x, y, w, h]`` of the sensor frame, or None.
        camera: camera settings as recorded.
        metadata: free-form metadata.
        manifest: the parsed ``capture.json``.
    """

    path: Path
    kind: str
    images: Tensor
    lights: LightModel | None
    bit_depth: int
    pixel_pitch_mm: float
    dark: Tensor | None = None
    mask: Tensor | None = None
    flatfield_path: Path | None = None
    card_albedo: float | None = None
    gt: dict[str, Any] = field(default_factory=dict)
    positions_mm: list[float] | None = None
    crop: list[int] | None = None
    camera: dict[str, Any] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)
    manifest: dict[str, Any] = field(default_factory=dict)


def _fail(folder: Path, reason: str) -> DataFormatError:
    return DataFormatError(f"capture {folder / MANIFEST_NAME}: {reason}")


def _is_number(x: Any) -> TypeGuard[float]:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _check_file_name(folder: Path, key: str, name: Any) -> None:
    if not isinstance(name, str) or not name or Path(name).is_absolute():
        raise _fail(folder, f"{key} must be a file name relative to the folder, got {name!r}")


def read_manifest(folder: str | Path) -> dict[str, Any]:
    """Parse and validate ``capture.json`` alone (no image is read).

    Args:
        folder: a capture folder.

    Returns:
        the manifest as a dict, validated: format name and version, kind, image list, light model and its
        count, bit depth, pixel pitch, flat-field reference, card albedo, focus positions, ground truth keys.

    Raises:
        DataFormatError: missing folder or manifest, invalid JSON (with the position and reason), a wrong
            format name, a newer or invalid version, or any field of the wrong type or value.

    Example:
        >>> read_manifest("captures/denim")["kind"]  # doctest: +SKIP
        'sample'
    """
    folder = Path(folder)
    path = folder / MANIFEST_NAME
    if not path.is_file():
        raise DataFormatError(f"{folder} is not a capture folder: {MANIFEST_NAME} is missing")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as error:
        raise DataFormatError(f"{path} is not UTF-8 text: {error}") from error
    except json.JSONDecodeError as error:
        raise DataFormatError(f"{path} is not valid JSON: {error}") from error
    if not isinstance(manifest, dict):
        raise _fail(folder, f"the manifest must be a JSON object, got {type(manifest).__name__}")
    if manifest.get("format") != FORMAT_NAME:
        raise _fail(folder, f"format must be {FORMAT_NAME!r}, got {manifest.get('format')!r}")
    version = manifest.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise _fail(folder, f"version must be a positive integer, got {version!r}")
    if version > FORMAT_VERSION:
        raise _fail(folder, f"version {version} is newer than this psmini reads ({FORMAT_VERSION}); upgrade psmini")
    kind = manifest.get("kind")
    if kind not in KINDS:
        raise _fail(folder, f"kind must be one of {list(KINDS)}, got {kind!r}")
    images = manifest.get("images")
    if not isinstance(images, list) or not images:
        raise _fail(folder, f"images must be a non-empty list of file names, got {images!r}")
    for name in images:
        _check_file_name(folder, "each entry of images", name)
    for key in ("dark", "mask"):
        if manifest.get(key) is not None:
            _check_file_name(folder, key, manifest[key])
    if manifest.get("bit_depth") not in BIT_DEPTHS:
        raise _fail(folder, f"bit_depth must be one of {list(BIT_DEPTHS)}, got {manifest.get('bit_depth')!r}")
    pitch = manifest.get("pixel_pitch_mm")
    if not _is_number(pitch) or pitch <= 0:
        raise _fail(folder, f"pixel_pitch_mm must be a positive number, got {pitch!r}")
    _check_lights_entry(folder, manifest, len(images))
    _check_kind_fields(folder, manifest, len(images))
    _check_gt_entry(folder, manifest.get("gt"))
    crop = manifest.get("crop")
    if crop is not None and not (isinstance(crop, list) and len(crop) == 4 and all(isinstance(c, int) for c in crop)):
        raise _fail(folder, f"crop must be null or [x, y, w, h] integers, got {crop!r}")
    for key in ("camera", "metadata"):
        if manifest.get(key) is not None and not isinstance(manifest[key], dict):
            raise _fail(folder, f"{key} must be a JSON object, got {type(manifest[key]).__name__}")
    return manifest


def _check_lights_entry(folder: Path, manifest: dict[str, Any], count: int) -> None:
    lights = manifest.get("lights")
    if lights is None and manifest["kind"] == "focus":
        return
    if not isinstance(lights, dict):
        raise _fail(folder, f"lights must be a light model object, got {lights!r}")
    try:
        lights_count = _light_count(json.dumps(lights, sort_keys=True))
    except PsminiError as error:
        raise _fail(folder, f"bad light model: {error}") from error
    if lights_count != count:
        raise _fail(folder, f"{count} images but the light model has {lights_count} lights; they must be equal")


@functools.lru_cache(maxsize=64)
def _light_count(text: str) -> int:
    """The number of lights of a light object given as canonical JSON, validated by building its model once per
    content: a batch run reads the same object in every sample's manifest and its card's (the model's tensors and
    checks were half of each manifest's 0.8 ms). An invalid object raises, and is not remembered."""
    return lights_from_dict(json.loads(text)).count


def _check_kind_fields(folder: Path, manifest: dict[str, Any], count: int) -> None:
    kind = manifest["kind"]
    if kind == "flatfield":
        albedo = manifest.get("card_albedo")
        if not _is_number(albedo) or albedo <= 0:
            raise _fail(folder, f"a flatfield capture needs card_albedo, a positive number; got {albedo!r}")
    if kind == "focus":
        positions = manifest.get("positions_mm")
        if not isinstance(positions, list) or len(positions) != count or not all(map(_is_number, positions)):
            raise _fail(folder, f"a focus capture needs positions_mm, {count} numbers (one per image); got "
                f"{positions!r}")
    reference = manifest.get("flatfield")
    if reference is None:
        return
    if not isinstance(reference, dict) or not isinstance(reference.get("path"), str) or not reference["path"]:
        raise _fail(folder, f'flatfield must be null or {{"path": ..., "albedo": ...}}, got {reference!r}')
    albedo = reference.get("albedo")
    if albedo is not None and (not _is_number(albedo) or albedo <= 0):
        raise _fail(folder, f"flatfield albedo must be a positive number, got {albedo!r}")


def _check_gt_entry(folder: Path, gt: Any) -> None:
    if gt is None:
        return
    if not isinstance(gt, dict):
        raise _fail(folder, f"gt must be null or an object of file names, got {type(gt).__name__}")
    for key, value in gt.items():
        if key == "lights":
            continue
        if key not in _GT_SHAPES:
            raise _fail(folder, f"unknown ground-truth entry {key!r}; expected some of {sorted(_GT_SHAPES)} or "
                "'lights'")
        _check_file_name(folder, f"gt.{key}", value)


def _existing(folder: Path, name: str, what: str) -> Path:
    path = folder / name
    if not path.is_file():
        raise _fail(folder, f"{what} file {name!r} does not exist")
    return path


def _container_bits(bit_depth: int) -> int:
    return 8 if bit_depth == 8 else 16


def _read_frames(folder: Path, names: list[str], bit_depth: int) -> np.ndarray:
    """Gray frames (K, H, W) scaled by 2**bit_depth - 1; values above that code raise."""
    paths = [_existing(folder, name, "image") for name in names]
    largest = 2**bit_depth - 1
    try:
        # integers straight into the float stack, scaled once by the capture's own largest code
        frames, _ = read_image_stack(paths, expected_bit_depth=_container_bits(bit_depth), max_value=largest)
    except DataFormatError as error:
        raise _fail(folder, str(error)) from error
    if bit_depth not in (8, 16):  # 10- or 12-bit codes in 16-bit files: nothing above the largest code
        peaks = frames.reshape(len(names), -1).max(axis=1)
        above = np.flatnonzero(peaks > (largest + 0.5) / largest)
        if above.size:
            raise _fail(folder, f"{names[above[0]]} holds values above {largest}, the largest {bit_depth}-bit code")
    return rgb_to_gray(frames) if frames.ndim == 4 else frames  # (an RGB capture is stacked in colour first)


def _read_plain(folder: Path, name: str, what: str, height: int, width: int, bit_depth: int | None) -> np.ndarray:
    image, bits = read_gray(_existing(folder, name, what))
    if image.shape != (height, width):
        raise _fail(folder, f"{what} {name!r} is {image.shape[1]}x{image.shape[0]} (WxH) but the images are "
            f"{width}x{height}")
    if bit_depth is not None:
        if bits != _container_bits(bit_depth):
            raise _fail(folder, f"{what} {name!r} is {bits}-bit but the images are {_container_bits(bit_depth)}-bit")
        image = image * np.float32((2**bits - 1) / (2**bit_depth - 1))
    return image


def _read_gt(folder: Path, entries: dict[str, Any], height: int, width: int) -> dict[str, Any]:
    gt: dict[str, Any] = {}
    for key, value in entries.items():
        if key == "lights":
            try:
                gt["lights"] = lights_from_dict(value)
            except PsminiError as error:
                raise _fail(folder, f"bad ground-truth light model: {error}") from error
            continue
        path = _existing(folder, value, f"ground truth {key}")
        try:
            array = read_npy(path, "ground truth")  # empty, cut short or foreign: a DataFormatError
        except DataFormatError as error:
            raise _fail(folder, str(error)) from error
        expected = (3, height, width) if key == "normals" else (height, width)
        if array.shape != expected:
            raise _fail(folder, f"ground truth {value!r} must have shape {expected}, got {array.shape}")
        tensor = torch.from_numpy(np.ascontiguousarray(array, dtype=bool if key == "mask" else np.float32))
        gt[key] = tensor if key == "normals" else tensor[None]
    return gt


def read_capture(folder: str | Path, *, ground_truth: bool = True) -> Capture:
    """Read and validate a capture folder.

    RGB images are converted to gray with the 0.2989/0.5870/0.1140 weights. Images are stored in 8-bit
    files when ``bit_depth`` is 8 and in 16-bit files otherwise (10- and 12-bit codes unshifted), and
    scaled to [0, 1] by ``2**bit_depth - 1``; the dark frame is on the same scale.

    Args:
        folder: the capture folder (holding ``capture.json``).
        ground_truth: read the ground truth the manifest lists (``gt``); ``False`` leaves ``gt`` empty without
            opening its files (a batch that does not score them: ~4 ms of a 400^2 synthetic capture's decoding).

    Returns:
        a :class:`Capture`.

    Raises:
        DataFormatError: as :func:`read_manifest`; a referenced file (image, dark, mask, ground truth) missing;
            images, dark frame, mask or ground truth of different sizes; files whose bit depth is not the
            manifest's; 10/12-bit codes out of range; a flat-field reference that is not a ``kind:
            "flatfield"`` capture folder or whose albedo disagrees with the card's.

    Example:
        >>> capture = read_capture("captures/denim")  # doctest: +SKIP
        >>> capture.images.shape  # doctest: +SKIP
        torch.Size([8, 400, 400])
    """
    folder = Path(folder)
    manifest = read_manifest(folder)
    bit_depth = manifest["bit_depth"]
    frames = _read_frames(folder, manifest["images"], bit_depth)
    height, width = frames.shape[1:]
    dark = mask = None
    if manifest.get("dark") is not None:
        dark = torch.from_numpy(_read_plain(folder, manifest["dark"], "dark frame", height, width, bit_depth))[None]
    if manifest.get("mask") is not None:
        mask = torch.from_numpy(_read_plain(folder, manifest["mask"], "mask", height, width, None) > 0)[None]
    flatfield_path, card_albedo = _resolve_flatfield(folder, manifest)
    lights = lights_from_dict(manifest["lights"]) if manifest.get("lights") is not None else None
    gt = _read_gt(folder, manifest["gt"], height, width) if ground_truth and manifest.get("gt") else {}
    logger.info(
        "read capture %s: %s, %d images %dx%d, %d-bit", folder, manifest["kind"], len(frames), width, height, bit_depth
    )
    return Capture(
        path=folder,
        kind=manifest["kind"],
        images=torch.from_numpy(frames),
        lights=lights,
        bit_depth=bit_depth,
        pixel_pitch_mm=float(manifest["pixel_pitch_mm"]),
        dark=dark,
        mask=mask,
        flatfield_path=flatfield_path,
        card_albedo=card_albedo,
        gt=gt,
        positions_mm=manifest.get("positions_mm"),
        crop=manifest.get("crop"),
        camera=manifest.get("camera") or {},
        metadata=manifest.get("metadata") or {},
        manifest=manifest,
    )


def _resolve_flatfield(folder: Path, manifest: dict[str, Any]) -> tuple[Path | None, float | None]:
    """The flat-field folder and card albedo, after checking the folder is a ``flatfield`` capture."""
    if manifest["kind"] == "flatfield":
        return None, float(manifest["card_albedo"])
    reference = manifest.get("flatfield")
    if reference is None:
        return None, None
    path = (folder / reference["path"]).resolve()
    try:
        card = read_manifest(path)
    except DataFormatError as error:
        raise _fail(folder, f"the flatfield reference {reference['path']!r} is not a readable capture: "
            f"{error}") from error
    if card["kind"] != "flatfield":
        raise _fail(folder, f"the flatfield reference {reference['path']!r} is a {card['kind']!r} capture, not "
            "'flatfield'")
    albedo = reference.get("albedo")
    if albedo is not None and not math.isclose(albedo, card["card_albedo"], rel_tol=1e-6):
        raise _fail(
            folder,
            f"flatfield albedo {albedo} disagrees with card_albedo {card['card_albedo']} of {reference['path']!r}",
        )
    return path, float(card["card_albedo"])


# ------------------------------------------------------------------------------------------------ writing


def _as_numpy(x: Any, name: str) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().cpu().numpy()
    if isinstance(x, np.ndarray):
        return x
    raise InputError(f"{name} must be a torch.Tensor or numpy array, got {type(x).__name__}")


def _as_image(x: Any, name: str, ndim: int) -> np.ndarray:
    """``x`` as an array of ``ndim`` dimensions; a leading dimension of 1 is dropped when it has one more."""
    array = _as_numpy(x, name)
    if array.ndim == ndim + 1 and array.shape[0] == 1:
        array = array[0]
    if array.ndim != ndim:
        expected = "(K, H, W)" if ndim == 3 else "(H, W) or (1, H, W)"
        raise InputError(f"{name} must have shape {expected}, got {array.shape}")
    return array


def _quantise(array: np.ndarray, bit_depth: int, name: str) -> np.ndarray:
    """Floats in [0, 1] → codes 0 .. 2**bit_depth - 1; integer arrays must already be codes."""
    top = 2**bit_depth - 1
    storage = np.uint8 if bit_depth == 8 else np.uint16
    if np.issubdtype(array.dtype, np.floating):
        if not np.isfinite(array).all():
            raise InputError(f"{name} holds NaN or infinite values")
        low, high = float(array.min(initial=0.0)), float(array.max(initial=0.0))
        if low < 0 or high > 1:
            raise InputError(f"{name} must be floats in [0, 1] (scaled to {bit_depth}-bit codes), got [{low:g}, "
                f"{high:g}]")
        return np.rint(array * top).astype(storage)
    if np.issubdtype(array.dtype, np.integer) and not np.issubdtype(array.dtype, np.bool_):
        if array.size and (array.min() < 0 or array.max() > top):
            raise InputError(f"{name} holds codes outside 0..{top}, the range of {bit_depth}-bit data")
        return array.astype(storage)
    raise InputError(f"{name} must hold floats in [0, 1] or integer codes, got {array.dtype}")


def _led_names(count: int) -> list[str]:
    digits = max(2, len(str(count - 1)))
    return [f"led_{i:0{digits}d}.png" for i in range(count)]


def _gt_manifest(target: Path, gt: Mapping[str, Any], height: int, width: int) -> dict[str, Any]:
    entries: dict[str, Any] = {}
    unknown = set(gt) - set(_GT_SHAPES) - {"lights"}
    if unknown:
        raise InputError(f"unknown ground-truth entries {sorted(unknown)}; expected some of "
            f"{sorted(_GT_SHAPES)} or 'lights'")
    (target / "gt").mkdir()
    for key, value in gt.items():
        if key == "lights":
            entries["lights"] = dict(value) if isinstance(value, Mapping) else lights_to_dict(value)
            continue
        array = _as_image(value, f"gt[{key!r}]", 3 if key == "normals" else 2)
        expected = (3, height, width) if key == "normals" else (height, width)
        if array.shape != expected:
            raise InputError(f"gt[{key!r}] must have shape {_GT_SHAPES[key]} = {expected}, got {array.shape}")
        np.save(target / "gt" / f"{key}.npy", array.astype(bool if key == "mask" else np.float32))
        entries[key] = f"gt/{key}.npy"
    return entries


def write_capture(
    folder: str | Path,
    images: Tensor | np.ndarray,
    lights: LightModel | Mapping[str, Any] | None,
    *,
    pixel_pitch_mm: float,
    kind: str = "sample",
    bit_depth: int = 16,
    dark: Tensor | np.ndarray | None = None,
    mask: Tensor | np.ndarray | None = None,
    flatfield: Mapping[str, Any] | None = None,
    card_albedo: float | None = None,
    gt: Mapping[str, Any] | None = None,
    positions_mm: list[float] | None = None,
    crop: list[int] | None = None,
    camera: Mapping[str, Any] | None = None,
    metadata: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a capture folder atomically (temporary sibling folder, renamed into place when complete).

    Args:
        folder: destination folder; must not exist unless ``overwrite``.
        images: gray images in LED order, shape :math:`(K, H, W)`: floats in [0, 1] (rounded to
            ``bit_depth``-bit codes) or integer codes in ``0 .. 2**bit_depth - 1``.
        lights: a light module of :mod:`psmini.lights` (or its JSON object) with K lights; None only for
            ``kind="focus"``.
        pixel_pitch_mm: size of one pixel on the object, mm.
        kind: ``"sample"``, ``"flatfield"``, ``"sphere"`` or ``"focus"``.
        bit_depth: 8 (8-bit PNGs) or 10, 12, 16 (16-bit PNGs).
        dark: all-LEDs-off frame, shape :math:`(H, W)` or :math:`(1, H, W)`, same scale as ``images``.
        mask: pixels to reconstruct, shape :math:`(H, W)` or :math:`(1, H, W)`, non-zero inside.
        flatfield: ``{"path": ..., "albedo": ...}``: the card capture; an absolute path is stored relative
            to ``folder``; ``albedo`` may be omitted (the card capture's ``card_albedo`` is used).
        card_albedo: for ``kind="flatfield"``: the card's albedo (required there).
        gt: ground truth: ``normals`` :math:`(3, H, W)`, ``depth`` (mm, NaN where undefined), ``albedo``,
            ``mask`` :math:`(H, W)`, and ``lights`` (a light module or object) when the true lights differ.
        positions_mm: for ``kind="focus"``: the z position of each image.
        crop: ``[x, y, w, h]`` of the sensor frame.
        camera: camera settings as read back from the device.
        metadata: anything else that serialises to JSON.
        overwrite: replace an existing folder.

    Returns:
        the folder.

    Raises:
        InputError: bad shapes, values out of range, an unknown kind or bit depth, K images but a different
            number of lights, values that do not serialise to JSON.
        DataFormatError: the folder exists (without ``overwrite``), or a file cannot be written. Nothing is
            left at ``folder`` when writing fails.

    Example:
        >>> from psmini.lights import ring_lights
        >>> write_capture("denim", torch.rand(8, 40, 40), DirectionalLights(ring_lights(8, 55.0)),
        ...               pixel_pitch_mm=0.025)  # doctest: +SKIP
    """
    folder = Path(folder)
    if kind not in KINDS:
        raise InputError(f"kind must be one of {list(KINDS)}, got {kind!r}")
    if bit_depth not in BIT_DEPTHS:
        raise InputError(f"bit_depth must be one of {list(BIT_DEPTHS)}, got {bit_depth!r}")
    if not _is_number(pixel_pitch_mm) or pixel_pitch_mm <= 0:
        raise InputError(f"pixel_pitch_mm must be a positive number, got {pixel_pitch_mm!r}")
    codes = _quantise(_as_image(images, "images", 3), bit_depth, "images")
    count, height, width = codes.shape
    lights_entry = None
    if lights is not None:
        # a JSON object goes through the module too: validated and normalised like a module's
        module = lights_from_dict(lights) if isinstance(lights, Mapping) else lights
        lights_entry = lights_to_dict(module)  # InputError for anything but a light model
        if module.count != count:
            raise InputError(f"{count} images but {module.count} lights; they must be equal")
    elif kind != "focus":
        raise InputError(f"lights are required for a {kind!r} capture")
    kind_fields: dict[str, Any] = {}  # the manifest's fields of this kind of capture
    if kind == "flatfield":
        if not _is_number(card_albedo) or card_albedo <= 0:
            raise InputError(f"a flatfield capture needs card_albedo, a positive number; got {card_albedo!r}")
        kind_fields["card_albedo"] = float(card_albedo)
    if kind == "focus":
        if positions_mm is None or len(positions_mm) != count:
            raise InputError(f"a focus capture needs positions_mm with {count} numbers, got {positions_mm!r}")
        kind_fields["positions_mm"] = [float(p) for p in positions_mm]
    dark_codes = None
    if dark is not None:
        dark_codes = _quantise(_as_image(dark, "dark", 2), bit_depth, "dark")
        if dark_codes.shape != (height, width):
            raise InputError(f"dark must be {height}x{width} (HxW) like the images, got {dark_codes.shape}")
    mask_codes = None
    if mask is not None:
        mask_array = _as_image(mask, "mask", 2)
        if mask_array.shape != (height, width):
            raise InputError(f"mask must be {height}x{width} (HxW) like the images, got {mask_array.shape}")
        mask_codes = np.where(mask_array != 0, 255, 0).astype(np.uint8)
    names = _led_names(count)
    manifest: dict[str, Any] = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "kind": kind,
        "images": names,
        "dark": "dark.png" if dark_codes is not None else None,
        "mask": "mask.png" if mask_codes is not None else None,
        "bit_depth": bit_depth,
        "pixel_pitch_mm": float(pixel_pitch_mm),
        "crop": list(crop) if crop is not None else None,
        "camera": dict(camera or {}),
        "lights": lights_entry,
        "flatfield": _flatfield_entry(folder, flatfield),
        "gt": None,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "software": _software(),
        "metadata": dict(metadata or {}),
    }
    manifest.update(kind_fields)
    with atomic_folder(folder, overwrite) as target:
        for name, frame in zip(names, codes, strict=True):
            write_image(target / name, frame)
        if dark_codes is not None:
            write_image(target / "dark.png", dark_codes)
        if mask_codes is not None:
            write_image(target / "mask.png", mask_codes)
        if gt:
            manifest["gt"] = _gt_manifest(target, gt, height, width)
        try:
            text = json.dumps(manifest, indent=2, allow_nan=False)
        except (TypeError, ValueError) as error:
            raise InputError(f"the manifest does not serialise to JSON (check metadata and camera): {error}") from error
        (target / MANIFEST_NAME).write_text(text + "\n", encoding="utf-8")
    logger.info("wrote capture %s: %s, %d images %dx%d, %d-bit", folder, kind, count, width, height, bit_depth)
    return folder


def _flatfield_entry(folder: Path, flatfield: Mapping[str, Any] | None) -> dict[str, Any] | None:
    if flatfield is None:
        return None
    if not isinstance(flatfield, Mapping) or "path" not in flatfield:
        raise InputError(f'flatfield must be {{"path": ..., "albedo": ...}}, got {flatfield!r}')
    path = Path(flatfield["path"])
    if path.is_absolute():
        path = Path(os.path.relpath(path, folder.resolve()))
    entry: dict[str, Any] = {"path": path.as_posix()}
    albedo = flatfield.get("albedo")
    if albedo is not None:
        if not _is_number(albedo) or albedo <= 0:
            raise InputError(f"flatfield albedo must be a positive number, got {albedo!r}")
        entry["albedo"] = float(albedo)
    return entry


def _software() -> str:
    from psmini import __version__  # late: psmini/__init__ imports this module

    return f"psmini {__version__}"
