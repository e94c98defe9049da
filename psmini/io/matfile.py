"""A small reader of MATLAB level-5 MAT-files (``save -v6`` / ``-v7``): numeric and logical arrays only.

DiLiGenT ships its ground truth as ``Normal_gt.mat`` (v5, zlib-compressed, one double array). Reading it
needs about a hundred lines, so psmini carries this reader instead of a runtime dependency on SciPy
(a dev extra only; the tests compare this reader with ``scipy.io.loadmat``). Format: "MAT-File Format",
The MathWorks, sections "Level 5 MAT-File Format": a 128-byte header, then tagged data elements; a
``miMATRIX`` element holds array flags, dimensions, a name and the real (and imaginary) part, stored
column-major and possibly in a smaller type than the array's class; ``miCOMPRESSED`` wraps an element in zlib.

Cells, structs, sparse arrays, strings and function handles are skipped (logged at debug level); v7.3
files (HDF5) and v4 files are refused with a clear message.
"""

from __future__ import annotations

import logging
import struct
import zlib
from pathlib import Path

import numpy as np

from psmini.errors import DataFormatError

__all__ = ["read_mat"]

logger = logging.getLogger(__name__)

_MI_MATRIX, _MI_COMPRESSED = 14, 15
# data types of the elements (miINT8 ... miUINT64)
_MI_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8", 12: "i8", 13: "u8"}
# classes of numeric arrays (mxDOUBLE_CLASS ... mxUINT64_CLASS)
_MX_DTYPES = {6: "f8", 7: "f4", 8: "i1", 9: "u1", 10: "i2", 11: "u2", 12: "i4", 13: "u4", 14: "i8", 15: "u8"}
_FLAG_COMPLEX, _FLAG_LOGICAL = 0x0800, 0x0200


class _Reader:
    """Walks the tagged data elements of one byte buffer."""

    def __init__(self, data: bytes, endian: str, path: Path) -> None:
        self.data, self.endian, self.path, self.pos = data, endian, path, 0

    def fail(self, reason: str) -> DataFormatError:
        return DataFormatError(f"corrupt MAT-file {self.path}: {reason} (at byte {self.pos})")

    def tag(self) -> tuple[int, int, bool]:
        """Return (type, byte count, small) and advance past the tag."""
        if self.pos + 8 > len(self.data):
            raise self.fail("truncated element tag")
        first, second = struct.unpack_from(self.endian + "II", self.data, self.pos)
        if first >> 16:  # small data element: count and type packed in 4 bytes, data in the next 4
            self.pos += 4
            return first & 0xFFFF, first >> 16, True
        self.pos += 8
        return first, second, False

    def element(self) -> tuple[int, bytes]:
        """Return the type and payload of the next element, advancing past its padding."""
        kind, count, small = self.tag()
        if self.pos + count > len(self.data):
            raise self.fail(f"element of {count} bytes runs past the end")
        payload = self.data[self.pos : self.pos + count]
        padded = 4 if small else (count if kind == _MI_COMPRESSED else (count + 7) // 8 * 8)
        self.pos += padded
        return kind, payload

    def numbers(self) -> np.ndarray:
        kind, payload = self.element()
        if kind not in _MI_DTYPES:
            raise self.fail(f"unexpected data type {kind} for numeric data")
        return np.frombuffer(payload, dtype=np.dtype(self.endian + _MI_DTYPES[kind]))


def _matrix(payload: bytes, endian: str, path: Path) -> tuple[str, np.ndarray | None]:
    """Decode one miMATRIX payload into (name, array); array is None for unsupported classes."""
    sub = _Reader(payload, endian, path)
    flags = sub.numbers()
    if flags.size < 1:
        raise sub.fail("missing array flags")
    mx_class, flag_bits = int(flags[0]) & 0xFF, int(flags[0])
    dims = tuple(int(d) for d in sub.numbers())
    _, name_bytes = sub.element()
    name = name_bytes.decode("ascii", errors="replace")
    if mx_class not in _MX_DTYPES:
        logger.debug("skipping MAT variable %r of class %d in %s (not a numeric array)", name, mx_class, path)
        return name, None
    real = sub.numbers()
    values = real.astype(_MX_DTYPES[mx_class])
    if flag_bits & _FLAG_COMPLEX:
        values = values + 1j * sub.numbers().astype(_MX_DTYPES[mx_class])
    if values.size != int(np.prod(dims)):
        raise sub.fail(f"variable {name!r} has {values.size} values for dimensions {dims}")
    array = values.reshape(dims, order="F")
    return name, array.astype(bool) if flag_bits & _FLAG_LOGICAL else array


def read_mat(path: str | Path) -> dict[str, np.ndarray]:
    """Read the numeric and logical arrays of a level-5 MAT-file.

    Args:
        path: a ``.mat`` file written by MATLAB ``save`` (v6 or v7, compressed or not) or by
            ``scipy.io.savemat``.

    Returns:
        variable name → array, with MATLAB's shape (at least 2-D) and class (``double`` → ``float64``,
        ``uint8`` → ``uint8``, ``logical`` → ``bool``, complex classes → complex arrays).

    Raises:
        DataFormatError: missing file, not a MAT-file, a v7.3 (HDF5) or v4 file, truncated or corrupt data.

    Example:
        >>> read_mat("Normal_gt.mat")["Normal_gt"].shape  # doctest: +SKIP
        (512, 612, 3)
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"MAT-file {path} does not exist")
    data = path.read_bytes()
    if len(data) < 128 or not data.startswith(b"MATLAB"):
        raise DataFormatError(f"{path} is not a level-5 MAT-file (no 'MATLAB 5.0' header; v4 files are not supported)")
    endian = {b"IM": "<", b"MI": ">"}.get(data[126:128])
    if endian is None:
        raise DataFormatError(f"{path} has no MAT-file endian indicator; the file is corrupt")
    version = struct.unpack_from(endian + "H", data, 124)[0]
    if version != 0x0100:
        raise DataFormatError(
            f"{path} is a MAT-file of version 0x{version:04x} (v7.3 files are HDF5); expected a level-5 file "
            "(re-save it in MATLAB with save(..., '-v7'))"
        )
    top = _Reader(data, endian, path)
    top.pos = 128
    variables: dict[str, np.ndarray] = {}
    while top.pos < len(data):
        kind, payload = top.element()
        if kind == _MI_COMPRESSED:
            try:
                payload = zlib.decompress(payload)
            except zlib.error as error:
                raise top.fail(f"cannot decompress a zlib element: {error}") from error
            kind, payload = _Reader(payload, endian, path).element()
        if kind != _MI_MATRIX:
            logger.debug("skipping MAT element of type %d in %s", kind, path)
            continue
        name, array = _matrix(payload, endian, path)
        if array is not None:
            variables[name] = array
    return variables
