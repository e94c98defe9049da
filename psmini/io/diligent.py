"""Reader of DiLiGenT object folders (Shi et al., "A Benchmark Dataset and Evaluation for Non-Lambertian and
Uncalibrated Photometric Stereo", CVPR 2016 / TPAMI 2019).

A folder holds ``filenames.txt`` (one image file per line), ``light_directions.txt`` (K×3, camera frame: x
right, y up, z toward the camera), ``light_intensities.txt`` (K×3, RGB), ``mask.png``, the 16-bit RGB
images and, for objects with ground truth, ``Normal_gt.mat`` (variable ``Normal_gt``, H×W×3). The images
are prepared exactly as the published least-squares baseline: each channel divided by its light's
intensity, clamped at 0, then converted to gray with MATLAB's ``rgb2gray`` weights 0.2989/0.5870/0.1140.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np
import torch

from psmini.errors import DataFormatError
from psmini.io.images import DILIGENT_GRAY_WEIGHTS, read_gray, read_image_stack, rgb_to_gray
from psmini.io.matfile import read_mat
from psmini.io.sample import Sample
from psmini.lights import DirectionalLights

__all__ = ["read_diligent", "is_diligent_folder"]

logger = logging.getLogger(__name__)

_REQUIRED = ("filenames.txt", "light_directions.txt", "light_intensities.txt", "mask.png")


def is_diligent_folder(folder: str | Path) -> bool:
    """True when ``folder`` has DiLiGenT's ``filenames.txt`` and ``light_directions.txt``."""
    folder = Path(folder)
    return (folder / "filenames.txt").is_file() and (folder / "light_directions.txt").is_file()


def _read_table(path: Path) -> np.ndarray:
    """A K×3 table of numbers from a text file."""
    try:
        with warnings.catch_warnings():  # numpy's "Empty input file" warning: the error below says it in one line
            warnings.simplefilter("ignore", UserWarning)
            table = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as error:
        raise DataFormatError(f"cannot parse {path} as rows of 3 numbers: {error}") from error
    if table.size == 0:
        raise DataFormatError(f"{path} is empty; expected one row of 3 numbers per light")
    if table.shape[1] != 3:
        raise DataFormatError(f"{path} must have 3 numbers per row, got {table.shape[1]} (shape {table.shape})")
    if not np.isfinite(table).all():
        raise DataFormatError(f"{path} holds NaN or infinite values")
    return table


def _read_filenames(path: Path) -> list[str]:
    try:
        names = [line.strip() for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
    except UnicodeDecodeError as error:
        raise DataFormatError(f"{path} is not a UTF-8 text file: {error}") from error
    if not names:
        raise DataFormatError(f"{path} lists no image files")
    return names


def _read_normals_gt(path: Path, height: int, width: int) -> torch.Tensor:
    variables = read_mat(path)
    if "Normal_gt" not in variables:
        raise DataFormatError(f"{path} has no variable 'Normal_gt'; it holds "
            f"{sorted(variables) or 'no numeric arrays'}")
    normals = variables["Normal_gt"]
    if normals.shape != (height, width, 3):
        raise DataFormatError(
            f"Normal_gt in {path} must have shape ({height}, {width}, 3) like the images, got {normals.shape}"
        )
    return torch.from_numpy(np.ascontiguousarray(normals.transpose(2, 0, 1), dtype=np.float32))


def read_diligent(folder: str | Path) -> Sample:
    """Read one DiLiGenT object folder the way the published least-squares baseline does.

    Each image's R, G, B channels are divided by that image's row of ``light_intensities.txt``, clamped at 0
    and weighted 0.2989/0.5870/0.1140 (MATLAB's ``rgb2gray``; kornia's 0.299/0.587/0.114 would shift the
    figures). The lights are therefore returned with unit intensities. ``Normal_gt.mat`` is read with
    psmini's own level-5 MAT-file reader (:func:`psmini.io.matfile.read_mat`), so SciPy is not needed.

    Args:
        folder: a DiLiGenT object folder (e.g. ``DiLiGenT/pmsData/ballPNG``).

    Returns:
        a :class:`Sample` with images :math:`(K, H, W)` ``float32``, ``DirectionalLights`` (K unit directions,
        unit intensities), mask :math:`(1, H, W)` bool, ``normals_gt`` :math:`(3, H, W)` (None without
        ``Normal_gt.mat``), ``pixel_pitch_mm`` None, ``saturation_level`` None, and ``meta`` with the
        source, bit depth, file names and the original light intensities (K×3 RGB).

    Raises:
        DataFormatError: a missing folder or required file; tables that are not K×3; different counts of image
            files, light directions and light intensities (all named); images of different sizes, channels or
            bit depths; a mask or ``Normal_gt`` whose size differs from the images'. 8-bit images are read but
            logged as a warning (DiLiGenT's are 16-bit).

    Example:
        >>> sample = read_diligent("../shared/data/DiLiGenT/ball")  # doctest: +SKIP
        >>> sample.images.shape, sample.normals_gt.shape  # doctest: +SKIP
        (torch.Size([96, 512, 612]), torch.Size([3, 512, 612]))
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataFormatError(f"DiLiGenT folder {folder} does not exist or is not a folder")
    missing = [name for name in _REQUIRED if not (folder / name).is_file()]
    if missing:
        raise DataFormatError(f"DiLiGenT folder {folder} lacks {', '.join(missing)}")
    filenames = _read_filenames(folder / "filenames.txt")
    directions = _read_table(folder / "light_directions.txt")
    intensities = _read_table(folder / "light_intensities.txt")
    if not (len(filenames) == len(directions) == len(intensities)):
        raise DataFormatError(
            f"DiLiGenT folder {folder}: filenames.txt lists {len(filenames)} images but light_directions.txt has "
            f"{len(directions)} lights and light_intensities.txt {len(intensities)}; the counts must be equal"
        )
    if (intensities <= 0).any():
        raise DataFormatError(f"light_intensities.txt in {folder} holds values <= 0; intensities must be positive")

    scale = (1.0 / intensities).astype(np.float32)
    gray_scale = (1.0 / (intensities @ np.asarray(DILIGENT_GRAY_WEIGHTS))).astype(np.float32)

    def to_gray(index: int, image: np.ndarray) -> np.ndarray:
        if image.ndim == 2:  # a gray camera: divide by the gray-weighted intensity
            return np.maximum(image * gray_scale[index], 0.0)
        return rgb_to_gray(np.maximum(image[..., :3] * scale[index], 0.0))

    images, bit_depth = read_image_stack([folder / name for name in filenames], to_gray)
    if bit_depth != 16:
        logger.warning(
            "DiLiGenT folder %s has %d-bit images; DiLiGenT's are 16-bit, so these may have been reduced "
            "(e.g. by Pillow) and the published figures will not be reproduced exactly",
            folder,
            bit_depth,
        )
    height, width = images.shape[1:]
    mask, _ = read_gray(folder / "mask.png")
    if mask.shape != (height, width):
        raise DataFormatError(
            f"mask.png in {folder} is {mask.shape[1]}x{mask.shape[0]} (WxH) but the images are {width}x{height}"
        )
    gt_path = folder / "Normal_gt.mat"
    normals_gt = _read_normals_gt(gt_path, height, width) if gt_path.is_file() else None
    logger.info("read DiLiGenT folder %s: %d images %dx%d, %d-bit", folder, len(filenames), width, height, bit_depth)
    return Sample(
        name=folder.name,
        images=torch.from_numpy(images),
        lights=DirectionalLights(torch.from_numpy(directions.astype(np.float32))),
        mask=torch.from_numpy(mask > 0)[None],
        normals_gt=normals_gt,
        meta={
            "source": "diligent",
            "path": str(folder),
            "bit_depth": bit_depth,
            "filenames": filenames,
            "light_intensities": intensities.tolist(),
        },
    )
