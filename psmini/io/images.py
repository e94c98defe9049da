"""Reading and writing images without losing bits: OpenCV's ``IMREAD_UNCHANGED``, RGB order, [0, 1] floats.

Pillow reduces 16-bit RGB PNGs to 8 bits; OpenCV with ``IMREAD_UNCHANGED`` keeps every bit but returns
BGR(A). Every reader here goes through OpenCV, swaps to RGB(A), and scales ``uint8`` by 255 and ``uint16``
by 65535 (or by ``2**bit_depth - 1`` for 10- and 12-bit sensors stored in 16-bit files). The PNGs that OpenCV
writes at its default settings (psmini's capture files) are decoded by :mod:`psmini.io._png` instead, to the
same pixels in half the time, and PNGs are written by its encoder (the same kind of file); every other file, and
any file that decoder refuses, is OpenCV's.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from psmini.errors import DataFormatError, InputError
from psmini.io._png import decode_png, encode_png

__all__ = [
    "DILIGENT_GRAY_WEIGHTS",
    "read_image_raw",
    "read_image",
    "read_image_tensor",
    "read_gray",
    "read_image_stack",
    "rgb_to_gray",
    "write_image",
]

logger = logging.getLogger(__name__)

#: MATLAB's ``rgb2gray`` weights (R, G, B), used by the DiLiGenT baseline. kornia's ``rgb_to_grayscale``
#: uses 0.299/0.587/0.114 instead, which shifts DiLiGenT's published figures.
DILIGENT_GRAY_WEIGHTS: tuple[float, float, float] = (0.2989, 0.5870, 0.1140)

_BITS_OF_DTYPE = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}


def read_image_raw(path: str | Path) -> tuple[np.ndarray, int]:
    """Read an image file as stored: integer values, RGB(A) channel order.

    Args:
        path: an 8- or 16-bit PNG, TIFF, JPEG or BMP file, gray, RGB or RGBA.

    Returns:
        the pixels, ``uint8`` or ``uint16``, shape :math:`(H, W)` for gray or :math:`(H, W, C)` with C = 3
        (RGB) or 4 (RGBA); and the bit depth of the file's samples (8 or 16).

    Raises:
        DataFormatError: when the file is missing, cannot be decoded, or holds samples other than
            ``uint8``/``uint16`` (float TIFFs, 32-bit integers).

    Example:
        >>> pixels, bits = read_image_raw("led_00.png")  # doctest: +SKIP
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"image file {path} does not exist" if not path.exists() else f"{path} is not a file")
    # imdecode of the bytes rather than imread: imread returns None silently for unicode paths on some builds
    data = np.fromfile(path, dtype=np.uint8)
    pixels = decode_png(data)  # the PNGs OpenCV writes by default, at twice its speed; None: not one of them
    if pixels is not None:
        return pixels, _BITS_OF_DTYPE[pixels.dtype]
    pixels = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if pixels is None:
        raise DataFormatError(f"cannot decode image {path}: empty, corrupt, or not an image format OpenCV reads")
    if pixels.dtype not in _BITS_OF_DTYPE:
        raise DataFormatError(f"image {path} holds {pixels.dtype} samples; expected uint8 (8-bit) or uint16 (16-bit)")
    if pixels.ndim == 3:
        if pixels.shape[2] == 1:
            pixels = pixels[:, :, 0]
        elif pixels.shape[2] == 3:
            pixels = pixels[:, :, ::-1]
        elif pixels.shape[2] == 4:
            pixels = pixels[:, :, [2, 1, 0, 3]]
        else:
            raise DataFormatError(f"image {path} has {pixels.shape[2]} channels; expected 1 (gray), 3 (RGB) or "
                "4 (RGBA)")
    return np.ascontiguousarray(pixels), _BITS_OF_DTYPE[pixels.dtype]


def _scale(pixels: np.ndarray, max_value: int) -> np.ndarray:
    return np.multiply(pixels, np.float32(1.0 / max_value), dtype=np.float32)  # one pass: cast and scale


def read_image(path: str | Path) -> tuple[np.ndarray, int]:
    """Read an image as ``float32`` in [0, 1], RGB(A) order, never truncating 16-bit data.

    Args:
        path: an 8- or 16-bit PNG, TIFF, JPEG or BMP file, gray, RGB or RGBA.

    Returns:
        the image, ``float32``, shape :math:`(H, W)` (gray) or :math:`(H, W, C)` (C = 3 RGB, 4 RGBA), values
        divided by 255 (8-bit) or 65535 (16-bit); and the bit depth of the file (8 or 16).

    Raises:
        DataFormatError: missing file, undecodable file, or samples that are not ``uint8``/``uint16``.

    Example:
        >>> image, bits = read_image("001.png")  # doctest: +SKIP
        >>> image.dtype, bits  # doctest: +SKIP
        (dtype('float32'), 16)
    """
    pixels, bits = read_image_raw(path)
    return _scale(pixels, 2**bits - 1), bits


def read_image_tensor(
    path: str | Path, *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> tuple[Tensor, int]:
    """Read an image as a channel-first tensor in [0, 1] (see :func:`read_image`).

    Args:
        path: the image file.
        device: device of the result.
        dtype: floating dtype of the result.

    Returns:
        the image, shape :math:`(C, H, W)` with C = 1 (gray), 3 (RGB) or 4 (RGBA); and the file's bit depth.

    Raises:
        DataFormatError: as :func:`read_image`.
        InputError: a ``dtype`` that is not a floating torch dtype.

    Example:
        >>> image, bits = read_image_tensor("001.png")  # doctest: +SKIP
        >>> image.shape  # doctest: +SKIP
        torch.Size([3, 512, 612])
    """
    # an integer dtype truncated [0, 1] to zeros and ones; a dtype's name failed as a bare TypeError of to()
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise InputError(f"dtype must be a floating torch dtype (torch.float32, torch.float64), got {dtype!r}")
    image, bits = read_image(path)
    tensor = torch.from_numpy(image[None] if image.ndim == 2 else np.ascontiguousarray(image.transpose(2, 0, 1)))
    return tensor.to(device=device, dtype=dtype), bits


def rgb_to_gray(image: np.ndarray, weights: Sequence[float] = DILIGENT_GRAY_WEIGHTS) -> np.ndarray:
    """Weighted sum of the R, G, B channels (the last axis); alpha, if any, is ignored.

    Args:
        image: ``float32`` image, shape :math:`(..., C)` with C = 3 or 4 in RGB(A) order, or already gray
            (returned unchanged when ``image.ndim == 2``).
        weights: the three weights of R, G and B (default: MATLAB's ``rgb2gray``, as DiLiGenT).

    Returns:
        the gray image, shape :math:`(...)`, ``float32``.

    Raises:
        InputError: when ``weights`` does not hold three finite numbers.

    Example:
        >>> round(float(rgb_to_gray(np.ones((2, 2, 3), np.float32))[0, 0]), 4)
        0.9999
    """
    # None failed as a bare TypeError of len(), letters as a ValueError of numpy; a NaN weight made a NaN image
    try:
        values = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError):
        values = np.empty(0)
    if values.shape != (3,) or not np.isfinite(values).all():
        raise InputError(f"weights must hold 3 numbers (R, G, B), finite, got {weights!r:.80}")
    if image.ndim == 2:
        return image
    return (image[..., :3] @ np.asarray(weights, dtype=np.float32)).astype(np.float32)


def read_gray(path: str | Path, weights: Sequence[float] = DILIGENT_GRAY_WEIGHTS) -> tuple[np.ndarray, int]:
    """Read an image as gray ``float32`` in [0, 1]; colour images are weighted by ``weights``.

    Args:
        path: the image file (gray, RGB or RGBA; alpha is ignored).
        weights: R, G, B weights (default: DiLiGenT's 0.2989/0.5870/0.1140).

    Returns:
        the gray image, shape :math:`(H, W)`, and the file's bit depth.

    Raises:
        DataFormatError: as :func:`read_image`.
        InputError: ``weights`` that are not three finite numbers (as :func:`rgb_to_gray`).

    Example:
        >>> gray, bits = read_gray("001.png")  # doctest: +SKIP
    """
    image, bits = read_image(path)
    return rgb_to_gray(image, weights), bits


def read_image_stack(
    paths: Sequence[str | Path],
    transform: Callable[[int, np.ndarray], np.ndarray] | None = None,
    *,
    expected_bit_depth: int | None = None,
    max_value: int | None = None,
) -> tuple[np.ndarray, int]:
    """Read images that must all share one size, channel count and bit depth, and stack them.

    Args:
        paths: the image files, K of them.
        transform: optional ``f(index, image) -> array`` applied to each ``float32`` image (as returned by
            :func:`read_image`, or divided by ``max_value``) before stacking, e.g. a per-image colour correction
            and gray conversion; it keeps memory at one image's worth per file.
        expected_bit_depth: when given (8 or 16), files of another depth raise.
        max_value: the code that reads as 1 (default: the files' largest, 255 or 65535), e.g. 1023 for 10-bit
            codes in 16-bit files. Without a transform, each file's integers are converted as they are copied into
            the stack and the stack is scaled once (two passes in all, where a float image per file costs five).

    Returns:
        the stack, shape :math:`(K, ...)` of the (transformed) images, and the common bit depth.

    Raises:
        DataFormatError: an empty list; a file missing or unreadable; the first file whose size, channel count
            or bit depth differs from the first file's (both named, with both values).
        InputError: a ``max_value`` that is not a positive integer.

    Example:
        >>> stack, bits = read_image_stack(["001.png", "002.png"])  # doctest: +SKIP
    """
    if len(paths) == 0:
        raise DataFormatError("no image files to read: the list is empty")
    if max_value is not None and not (isinstance(max_value, (int, np.integer)) and max_value > 0):
        raise InputError(f"max_value must be a positive integer code, got {max_value!r}")
    stack: np.ndarray | None = None
    first_shape: tuple[int, ...] = ()
    first_path, first_bits = Path(paths[0]), 0
    for index, path in enumerate(paths):
        image, bits = read_image_raw(path)
        if index == 0:
            first_bits, first_shape = bits, image.shape
            if expected_bit_depth is not None and bits != expected_bit_depth:
                raise DataFormatError(f"image {path} is {bits}-bit; expected {expected_bit_depth}-bit images")
        elif image.shape[:2] != first_shape[:2]:
            raise DataFormatError(
                f"image {path} is {image.shape[1]}x{image.shape[0]} (WxH) but {first_path} is "
                f"{first_shape[1]}x{first_shape[0]}: all images must have the same size"
            )
        elif image.shape != first_shape:
            raise DataFormatError(
                f"image {path} has {_channels(image.shape)} channel(s) but {first_path} has {_channels(first_shape)}: "
                "all images must have the same channels"
            )
        elif bits != first_bits:
            raise DataFormatError(
                f"image {path} is {bits}-bit but {first_path} is {first_bits}-bit: all images must share one bit depth"
            )
        largest = 2**bits - 1 if max_value is None else max_value
        out = image if transform is None else transform(index, _scale(image, largest))
        if stack is None:
            stack = np.empty((len(paths), *out.shape), dtype=np.float32)
        stack[index] = out  # integers become float32 in this copy
    if stack is None:  # paths is not empty (checked above): the loop filled a stack
        raise DataFormatError("no image files to read: the list is empty")
    if transform is None:
        stack *= np.float32(1.0 / largest)
    return stack, first_bits


def _channels(shape: tuple[int, ...]) -> int:
    return 1 if len(shape) == 2 else shape[2]


def write_image(path: str | Path, pixels: np.ndarray) -> None:
    """Write integer pixels (RGB(A) order) to an image file, keeping 16-bit data (PNG or TIFF).

    Args:
        path: destination; the extension picks the format.
        pixels: ``uint8`` or ``uint16``, shape :math:`(H, W)` or :math:`(H, W, C)` with C = 3 (RGB) or 4 (RGBA).

    Raises:
        InputError: a dtype other than ``uint8``/``uint16``, or a bad shape.
        DataFormatError: when OpenCV cannot encode or write the file (unknown extension, 16-bit JPEG, I/O error).

    Example:
        >>> write_image("gray.png", np.zeros((4, 4), np.uint16))  # doctest: +SKIP
    """
    path = Path(path)
    if pixels.dtype not in _BITS_OF_DTYPE:
        raise InputError(f"pixels must be uint8 or uint16 to write {path.name}, got {pixels.dtype}")
    encoded = encode_png(pixels) if path.suffix.lower() == ".png" else None  # ISA-L: 4.5x OpenCV's encoder
    if encoded is not None:
        try:
            path.write_bytes(encoded)
        except OSError as error:
            raise DataFormatError(f"cannot write {path}: {error}") from error
        logger.debug("wrote %s (%s, %s)", path, pixels.dtype, pixels.shape)
        return
    if pixels.ndim == 3 and pixels.shape[2] in (3, 4):
        pixels = pixels[:, :, [2, 1, 0, 3][: pixels.shape[2]]]  # OpenCV writes BGR(A)
    elif pixels.ndim != 2:
        raise InputError(f"pixels must have shape (H, W), (H, W, 3) or (H, W, 4), got {pixels.shape}")
    try:
        ok, buffer = cv2.imencode(path.suffix, np.ascontiguousarray(pixels))
    except cv2.error as error:
        raise DataFormatError(f"cannot encode {path} ({pixels.dtype}, shape {pixels.shape}): {error}") from error
    if not ok:
        raise DataFormatError(f"cannot encode {path} ({pixels.dtype}, shape {pixels.shape})")
    try:
        buffer.tofile(path)
    except OSError as error:
        raise DataFormatError(f"cannot write {path}: {error}") from error
    logger.debug("wrote %s (%s, %s)", path, pixels.dtype, pixels.shape)
