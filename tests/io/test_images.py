"""Image reading and writing: bit-exact 16-bit round trips, RGB order, gray weights, stacks, error paths."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from psmini import DataFormatError, InputError
from psmini.io.images import (
    DILIGENT_GRAY_WEIGHTS,
    read_gray,
    read_image,
    read_image_raw,
    read_image_stack,
    read_image_tensor,
    rgb_to_gray,
    write_image,
)
from tests.conftest import shared_data


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


class TestRoundTrip:
    @pytest.mark.parametrize("suffix", [".png", ".tif"])
    @pytest.mark.parametrize("channels", [1, 3, 4])
    def test_16_bit_survives_bit_exact(self, tmp_path, rng, suffix, channels):
        shape = (7, 9) if channels == 1 else (7, 9, channels)
        pixels = rng.integers(0, 65536, size=shape, dtype=np.uint16)
        write_image(tmp_path / f"x{suffix}", pixels)
        raw, bits = read_image_raw(tmp_path / f"x{suffix}")
        assert bits == 16 and raw.dtype == np.uint16
        np.testing.assert_array_equal(raw, pixels)
        image, bits = read_image(tmp_path / f"x{suffix}")
        assert image.dtype == np.float32 and bits == 16
        np.testing.assert_array_equal(np.rint(image.astype(np.float64) * 65535).astype(np.uint16), pixels)

    @pytest.mark.parametrize("suffix", [".png", ".bmp", ".tif"])
    def test_8_bit_rgb(self, tmp_path, rng, suffix):
        pixels = rng.integers(0, 256, size=(5, 6, 3), dtype=np.uint8)
        write_image(tmp_path / f"x{suffix}", pixels)
        image, bits = read_image(tmp_path / f"x{suffix}")
        assert bits == 8
        np.testing.assert_allclose(image, pixels / 255.0, atol=1e-7)

    def test_jpeg_reads_8_bit(self, tmp_path):
        pixels = np.full((8, 8, 3), (200, 100, 50), dtype=np.uint8)
        write_image(tmp_path / "x.jpg", pixels)
        image, bits = read_image(tmp_path / "x.jpg")
        assert bits == 8 and image.shape == (8, 8, 3)
        np.testing.assert_allclose(image[4, 4] * 255, [200, 100, 50], atol=3)

    def test_channel_order_is_rgb(self, tmp_path):
        # written by OpenCV directly in BGR order: pure red must come back in channel 0
        bgr = np.zeros((2, 2, 3), dtype=np.uint16)
        bgr[..., 2] = 65535
        cv2.imwrite(str(tmp_path / "red.png"), bgr)
        image, _ = read_image(tmp_path / "red.png")
        np.testing.assert_array_equal(image[0, 0], [1.0, 0.0, 0.0])

    def test_rgba_order(self, tmp_path):
        bgra = np.array([[[10, 20, 30, 40]]], dtype=np.uint8)
        cv2.imwrite(str(tmp_path / "a.png"), bgra)
        raw, _ = read_image_raw(tmp_path / "a.png")
        assert raw[0, 0].tolist() == [30, 20, 10, 40]

    def test_tensor_variant(self, tmp_path, rng):
        pixels = rng.integers(0, 65536, size=(4, 5, 3), dtype=np.uint16)
        write_image(tmp_path / "x.png", pixels)
        tensor, bits = read_image_tensor(tmp_path / "x.png", dtype=torch.float64)
        assert tensor.shape == (3, 4, 5) and tensor.dtype == torch.float64 and bits == 16
        torch.testing.assert_close(tensor, torch.from_numpy(pixels.transpose(2, 0, 1) / 65535.0), rtol=0, atol=1e-7)
        write_image(tmp_path / "g.png", pixels[..., 0])
        gray, _ = read_image_tensor(tmp_path / "g.png")
        assert gray.shape == (1, 4, 5)

    def test_tensor_variant_errors(self, tmp_path):  # its missing and corrupt files: TestErrors
        write_image(tmp_path / "x.png", np.full((2, 3), 128, np.uint8))
        # an integer dtype truncated the [0, 1] image to zeros; a dtype's name failed as a bare TypeError of to()
        with pytest.raises(InputError, match="dtype must be a floating torch dtype .* got torch.int64"):
            read_image_tensor(tmp_path / "x.png", dtype=torch.int64)
        with pytest.raises(InputError, match="got 'float32'"):
            read_image_tensor(tmp_path / "x.png", dtype="float32")

    def test_16_bit_diligent_file_keeps_16_bits(self):
        image, bits = read_image(shared_data("DiLiGenT", "ball", "001.png"))
        assert bits == 16 and image.shape == (512, 612, 3)
        codes = np.rint(image * 65535).astype(np.int64)
        assert np.any(codes % 256 != 0)  # the low byte is there, not truncated


class TestGray:
    def test_weights_are_matlab_rgb2gray(self, tmp_path):
        assert DILIGENT_GRAY_WEIGHTS == (0.2989, 0.5870, 0.1140)
        pixels = np.zeros((1, 3, 3), dtype=np.uint16)
        pixels[0, 0, 0], pixels[0, 1, 1], pixels[0, 2, 2] = 65535, 65535, 65535
        write_image(tmp_path / "x.png", pixels)
        gray, bits = read_gray(tmp_path / "x.png")
        np.testing.assert_allclose(gray[0], [0.2989, 0.5870, 0.1140], rtol=1e-6)
        assert bits == 16

    def test_gray_file_is_unchanged(self, tmp_path):
        write_image(tmp_path / "g.png", np.array([[0, 255]], dtype=np.uint8))
        gray, _ = read_gray(tmp_path / "g.png")
        np.testing.assert_array_equal(gray, [[0.0, 1.0]])

    def test_bad_weights(self):
        with pytest.raises(InputError, match="3 numbers"):
            rgb_to_gray(np.zeros((2, 2, 3), np.float32), (0.5, 0.5))

    def test_read_gray_errors(self, tmp_path):  # its missing and corrupt files: TestErrors
        write_image(tmp_path / "x.png", np.zeros((2, 3, 3), np.uint8))
        # None failed as a bare TypeError of len(), letters as a ValueError of numpy; a NaN weight made a NaN image
        with pytest.raises(InputError, match="weights must hold 3 numbers \\(R, G, B\\), finite, got None"):
            read_gray(tmp_path / "x.png", None)
        with pytest.raises(InputError, match="got 'abc'"):
            read_gray(tmp_path / "x.png", "abc")
        with pytest.raises(InputError, match="got \\(nan, 0.5, 0.5\\)"):
            read_gray(tmp_path / "x.png", (float("nan"), 0.5, 0.5))
        gray, _ = read_gray(tmp_path / "x.png", np.array([0.2, 0.3, 0.5]))  # an array of three, as before
        assert gray.shape == (2, 3)


class TestStack:
    def test_stack_and_transform(self, tmp_path):
        paths = []
        for i in range(3):
            write_image(tmp_path / f"{i}.png", np.full((4, 5), i * 1000, dtype=np.uint16))
            paths.append(tmp_path / f"{i}.png")
        stack, bits = read_image_stack(paths, lambda index, image: image * (index + 1))
        assert stack.shape == (3, 4, 5) and bits == 16
        np.testing.assert_allclose(stack[:, 0, 0], [0.0, 2000 / 65535, 6000 / 65535], rtol=1e-6)

    @pytest.mark.parametrize("channels", [None, 3])
    def test_max_value_scales_the_codes(self, tmp_path, channels):
        """10-bit codes in 16-bit files read as code / 1023, with or without a transform, gray or RGB: equal to
        each file's float image rescaled (within float32 rounding) and exact on the codes 0 and 1023."""
        rng = np.random.default_rng(0)
        shape = (6, 7) if channels is None else (6, 7, channels)
        codes = [rng.integers(0, 1024, shape).astype(np.uint16) for _ in range(3)]
        codes[1][0, 0] = 1023
        paths = []
        for i, code in enumerate(codes):
            write_image(tmp_path / f"{i}.png", code)
            paths.append(tmp_path / f"{i}.png")
        stack, bits = read_image_stack(paths, max_value=1023)
        expected = np.stack([read_image(path)[0] * (65535 / 1023) for path in paths])
        assert bits == 16 and stack.dtype == np.float32 and stack.shape == (3, *shape)
        np.testing.assert_allclose(stack, expected, rtol=1e-6, atol=1e-7)
        assert stack[1, 0, 0].tolist() == ([1.0] * channels if channels else 1.0)
        transformed, _ = read_image_stack(paths, lambda index, image: image, max_value=1023)
        np.testing.assert_array_equal(transformed, stack)

    @pytest.mark.parametrize("bad", [0, -3, 2.5, "1023"])
    def test_bad_max_value(self, tmp_path, bad):
        write_image(tmp_path / "a.png", np.zeros((4, 5), np.uint16))
        with pytest.raises(InputError, match="max_value must be a positive integer"):
            read_image_stack([tmp_path / "a.png"], max_value=bad)

    def test_size_mismatch_names_first_differing_file(self, tmp_path):
        write_image(tmp_path / "a.png", np.zeros((4, 5), np.uint16))
        write_image(tmp_path / "b.png", np.zeros((4, 5), np.uint16))
        write_image(tmp_path / "c.png", np.zeros((4, 6), np.uint16))
        write_image(tmp_path / "d.png", np.zeros((3, 6), np.uint16))
        with pytest.raises(DataFormatError, match=r"c\.png is 6x4 \(WxH\) but .*a\.png is 5x4"):
            read_image_stack([tmp_path / n for n in ("a.png", "b.png", "c.png", "d.png")])

    def test_bit_depth_mismatch(self, tmp_path):
        write_image(tmp_path / "a.png", np.zeros((4, 5), np.uint16))
        write_image(tmp_path / "b.png", np.zeros((4, 5), np.uint8))
        with pytest.raises(DataFormatError, match=r"b\.png is 8-bit but .*a\.png is 16-bit"):
            read_image_stack([tmp_path / "a.png", tmp_path / "b.png"])

    def test_channel_mismatch(self, tmp_path):
        write_image(tmp_path / "a.png", np.zeros((4, 5), np.uint8))
        write_image(tmp_path / "b.png", np.zeros((4, 5, 3), np.uint8))
        with pytest.raises(DataFormatError, match="3 channel"):
            read_image_stack([tmp_path / "a.png", tmp_path / "b.png"])

    def test_expected_bit_depth(self, tmp_path):
        write_image(tmp_path / "a.png", np.zeros((4, 5), np.uint8))
        with pytest.raises(DataFormatError, match="8-bit; expected 16-bit"):
            read_image_stack([tmp_path / "a.png"], expected_bit_depth=16)

    def test_empty_list(self):
        with pytest.raises(DataFormatError, match="empty"):
            read_image_stack([])


READERS = [read_image, read_image_tensor, read_gray]


class TestErrors:
    @pytest.mark.parametrize("reader", READERS)
    def test_missing_file(self, tmp_path, reader):
        with pytest.raises(DataFormatError, match="none.png does not exist"):
            reader(tmp_path / "none.png")

    def test_folder_is_not_a_file(self, tmp_path):
        with pytest.raises(DataFormatError, match="not a file"):
            read_image(tmp_path)

    @pytest.mark.parametrize("reader", READERS)
    @pytest.mark.parametrize("content", [b"", b"not an image at all", b"\x89PNG\r\n\x1a\n\x00\x00garbage"])
    def test_corrupt_file(self, tmp_path, content, reader):
        (tmp_path / "bad.png").write_bytes(content)
        with pytest.raises(DataFormatError, match="cannot decode"):
            reader(tmp_path / "bad.png")

    def test_truncated_png(self, tmp_path):
        write_image(tmp_path / "x.png", np.random.default_rng(1).integers(0, 65535, (64, 64), dtype=np.uint16))
        data = (tmp_path / "x.png").read_bytes()
        (tmp_path / "x.png").write_bytes(data[: len(data) // 2])
        with pytest.raises(DataFormatError, match="cannot decode"):
            read_image(tmp_path / "x.png")

    def test_float_tiff_is_refused(self, tmp_path):
        cv2.imwrite(str(tmp_path / "f.tif"), np.zeros((4, 4), np.float32))
        with pytest.raises(DataFormatError, match=r"float32 samples; expected uint8 .* or uint16"):
            read_image(tmp_path / "f.tif")

    def test_write_refuses_float(self, tmp_path):
        with pytest.raises(InputError, match="uint8 or uint16"):
            write_image(tmp_path / "x.png", np.zeros((2, 2), np.float32))

    def test_write_refuses_bad_shape(self, tmp_path):
        with pytest.raises(InputError, match="shape"):
            write_image(tmp_path / "x.png", np.zeros((2, 2, 2), np.uint8))

    def test_write_unknown_extension(self, tmp_path):
        with pytest.raises(DataFormatError, match="cannot encode"):
            write_image(tmp_path / "x.unknownext", np.zeros((2, 2), np.uint8))

    def test_write_into_missing_folder(self, tmp_path):
        with pytest.raises(DataFormatError, match="cannot write"):
            write_image(tmp_path / "no" / "x.png", np.zeros((2, 2), np.uint8))
