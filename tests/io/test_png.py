"""The fast PNG path against OpenCV: the same pixels for every file it takes, None (OpenCV's turn) for the rest."""

import struct
import zlib

import cv2
import numpy as np
import pytest

from psmini.errors import DataFormatError
from psmini.io import _png
from psmini.io.images import read_image_raw, write_image

pytestmark = pytest.mark.skipif(not _png.available(), reason="isal (ISA-L) is not installed: no fast PNG path")


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def encode(pixels: np.ndarray, filters: list[int], extra: tuple[tuple[bytes, bytes], ...] = (),
           interlace: int = 0) -> bytes:
    """An independent PNG writer (stdlib zlib, the specification's None / Sub / Up filters, one per row)."""
    height, width = pixels.shape[:2]
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    colour = {1: 0, 3: 2, 4: 6}[channels]
    bits = 8 * pixels.itemsize
    raw = np.ascontiguousarray(pixels.astype(pixels.dtype.newbyteorder(">"))).view(np.uint8).reshape(height, -1)
    step = channels * pixels.itemsize
    lines = []
    for row, kind in enumerate(filters):
        line = raw[row].astype(np.int16)
        if kind == 1:
            line[step:] -= raw[row, :-step]
        elif kind == 2 and row > 0:
            line -= raw[row - 1]
        lines.append(bytes([kind]) + (line % 256).astype(np.uint8).tobytes())
    header = struct.pack(">IIBBBBB", width, height, bits, colour, 0, 0, interlace)
    body = b"".join(_chunk(kind, data) for kind, data in extra)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + body + _chunk(b"IDAT", zlib.compress(b"".join(lines)))
            + _chunk(b"IEND", b""))


def opencv(data: bytes) -> np.ndarray:
    """OpenCV's decode in RGB(A) order, as read_image_raw returns it."""
    pixels = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels.ndim == 3:
        pixels = pixels[:, :, [2, 1, 0, 3][: pixels.shape[2]]]
    return pixels


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("size", [(1, 1), (1, 7), (9, 1), (37, 53), (64, 400)])
def test_opencv_default_files(rng, dtype, channels, size):
    # random pixels beside smooth ones: large and small byte differences, every wrap of the running sums
    shape = size if channels == 1 else (*size, channels)
    noise = rng.integers(0, np.iinfo(dtype).max + 1, shape, dtype=np.int64)
    ramp = np.indices(size).sum(0).reshape(size + (1,) * (len(shape) - 2)) * 997
    pixels = np.where(rng.random(shape) < 0.5, noise, ramp % (np.iinfo(dtype).max + 1)).astype(dtype)
    data = cv2.imencode(".png", pixels if channels == 1 else pixels[:, :, [2, 1, 0, 3][:channels]])[1].tobytes()
    got = _png.decode_png(data)
    assert got is not None and got.dtype == dtype
    np.testing.assert_array_equal(got, opencv(data))
    np.testing.assert_array_equal(got, pixels)


@pytest.mark.parametrize("filters", ["none", "up", "runs"])
def test_none_and_up_rows(rng, filters):
    pixels = rng.integers(0, 65536, (12, 9, 3), dtype=np.int64).astype(np.uint16)
    rows = {"none": [0] * 12, "up": [2] * 12, "runs": [1, 1, 1, 2, 2, 2, 2, 2, 0, 0, 2, 1]}[filters]
    data = encode(pixels, rows)
    np.testing.assert_array_equal(opencv(data), pixels)  # the test's writer is a valid PNG writer
    np.testing.assert_array_equal(_png.decode_png(data), pixels)


def test_adaptive_filters_are_left_to_opencv(rng, tmp_path):
    # OpenCV at level 9 picks a filter per row (Average and Paeth among them): OpenCV decodes those files
    pixels = (np.indices((60, 80)).sum(0) * 300 + rng.integers(0, 50, (60, 80))).astype(np.uint16)
    data = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, 9])[1].tobytes()
    rows = zlib.decompress(b"".join(_idat(data)))
    assert max(rows[:: 80 * 2 + 1]) > 2
    assert _png.decode_png(data) is None
    (tmp_path / "a.png").write_bytes(data)
    np.testing.assert_array_equal(read_image_raw(tmp_path / "a.png")[0], pixels)


def _with_idat(shape: tuple[int, int], bits: int, colour: int, idat: bytes) -> bytes:
    header = struct.pack(">IIBBBBB", shape[1], shape[0], bits, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def _idat(data: bytes) -> list[bytes]:
    position, parts = 8, []
    while position < len(data):
        (length,) = struct.unpack_from(">I", data, position)
        if data[position + 4 : position + 8] == b"IDAT":
            parts.append(data[position + 8 : position + 8 + length])
        position += 12 + length
    return parts


@pytest.mark.parametrize("case", ["transparency", "gamma", "time", "interlaced", "bit depth 4", "no IEND", "runs",
                                  "late Paeth", "extra data", "huge header"])
def test_files_it_does_not_take(rng, case):
    pixels = rng.integers(0, 256, (5, 6), dtype=np.int64).astype(np.uint8)
    if case == "transparency":
        data = encode(pixels, [1] * 5, extra=((b"tRNS", b"\x00\x07"),))
    elif case == "gamma":
        data = encode(pixels, [1] * 5, extra=((b"gAMA", struct.pack(">I", 45455)),))
    elif case == "time":  # MATLAB's imwrite adds tIME (DiLiGenT): another encoder's file, given up at once
        data = encode(pixels, [1] * 5, extra=((b"tIME", struct.pack(">HBBBBB", 2016, 1, 1, 0, 0, 0)),))
    elif case == "runs":  # None, Sub and Up only, but alternating row by row as an adaptive encoder does
        data = encode(rng.integers(0, 256, (20, 6), dtype=np.int64).astype(np.uint8), [0, 1, 2] * 6 + [0, 1])
    elif case == "late Paeth":  # the first rows pass; a Paeth row (type 4) far down the image is found
        tall = rng.integers(0, 256, (200, 6), dtype=np.int64).astype(np.uint8)
        raw = bytearray(zlib.decompress(b"".join(_idat(encode(tall, [1] * 200)))))
        raw[150 * 7] = 4  # row 150's filter byte (rows of 1 + 6 bytes)
        data = _with_idat(tall.shape, 8, 0, zlib.compress(bytes(raw)))
        assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) is not None  # a valid PNG
    elif case == "extra data":  # a stream holding more rows than the header's height
        data = _with_idat((5, 6), 8, 0, zlib.compress(bytes([1] + [0] * 6) * 6))
    elif case == "huge header":  # a header (CRC intact) promising 60000 x 60000: never allocated
        data = _with_idat((60000, 60000), 8, 0, zlib.compress(bytes(7 * 5)))
    elif case == "interlaced":
        data = encode(pixels, [1] * 5, interlace=1)
    elif case == "bit depth 4":
        data = bytearray(encode(pixels, [1] * 5))
        data[8 + 8 + 8] = 4  # the IHDR's bit depth, its CRC rewritten
        data[8 + 8 + 13 : 8 + 8 + 17] = struct.pack(">I", zlib.crc32(bytes(data[8 + 4 : 8 + 8 + 13])))
        data = bytes(data)
    else:
        data = encode(pixels, [1] * 5)[:-12]
    assert _png.decode_png(data) is None


def test_corrupt_files_fall_back_to_opencv_and_its_error(rng, tmp_path):
    pixels = rng.integers(0, 65536, (40, 30), dtype=np.int64).astype(np.uint16)
    data = bytearray(cv2.imencode(".png", pixels)[1].tobytes())
    data[60] ^= 0xFF  # a byte of the image data: its chunk's CRC no longer matches
    assert _png.decode_png(bytes(data)) is None
    (tmp_path / "bad.png").write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match="cannot decode"):
        read_image_raw(tmp_path / "bad.png")
    good = cv2.imencode(".png", pixels)[1].tobytes()
    assert _png.decode_png(good[: len(good) // 2]) is None  # truncated
    assert _png.decode_png(b"GIF89a" + good[6:]) is None  # not a PNG signature


def test_without_isal_opencv_decodes(rng, tmp_path, monkeypatch):
    pixels = rng.integers(0, 65536, (8, 8), dtype=np.int64).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "a.png"), pixels)
    monkeypatch.setattr(_png, "_ISAL", None)
    assert _png.decode_png((tmp_path / "a.png").read_bytes()) is None
    np.testing.assert_array_equal(read_image_raw(tmp_path / "a.png")[0], pixels)
    assert _png.encode_png(pixels) is None
    write_image(tmp_path / "b.png", pixels)  # OpenCV's encoder
    np.testing.assert_array_equal(read_image_raw(tmp_path / "b.png")[0], pixels)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("size", [(1, 1), (5, 1), (1, 6), (41, 29)])
def test_encoder_files_read_back(rng, tmp_path, dtype, channels, size):
    shape = size if channels == 1 else (*size, channels)
    pixels = rng.integers(0, np.iinfo(dtype).max + 1, shape, dtype=np.int64).astype(dtype)
    write_image(tmp_path / "a.png", pixels)
    data = (tmp_path / "a.png").read_bytes()
    assert data == _png.encode_png(pixels)
    np.testing.assert_array_equal(opencv(data), pixels)  # OpenCV (libpng) reads it
    np.testing.assert_array_equal(_png.decode_png(data), pixels)  # and the fast path takes it


def test_encoder_leaves_other_arrays_to_opencv():
    assert _png.encode_png(np.zeros((4, 4, 1), np.uint8)) is None
    assert _png.encode_png(np.zeros((4, 4, 2), np.uint8)) is None
    assert _png.encode_png(np.zeros((4, 4), np.float32)) is None
    assert _png.encode_png(np.zeros((0, 4), np.uint8)) is None
