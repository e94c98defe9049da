"""Focus measures: against independent NumPy/SciPy versions, symmetric in polarity and orientation, monotone in blur."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from psmini.errors import InputError, ShapeError
from psmini.focus import (
    FOCUS_MEASURES,
    FOCUS_NAMES,
    FocusMeasure,
    brenner,
    focus_measure,
    gaussian_derivative,
    image_contrast,
    normalized_variance,
    parse_roi,
    tenengrad,
    variance_of_laplacian,
    wavelet_sum,
)
from tests.conftest import BaseTester

NAMES = list(FOCUS_NAMES)  # psmini's seven names and the 28 operator codes of Pertuz et al. (2013)
assert set(FOCUS_MEASURES) < set(NAMES) and len(NAMES) == 35
# Operators divided by a brightness (a contrast ratio by design): inverting a frame whose mean changes changes them.
BRIGHTNESS_RATIOS = {"variance", "glvn", "wavr", "dcte", "dctr", "helm"}
# Operators that read one pixel only (no neighbours): a 1-pixel-high frame is enough for them.
POINTWISE = {"variance", "glvn", "acmo", "glva", "hise", "hisr"}


def texture(size: int = 48, seed: int = 0, sigma: float = 0.0) -> np.ndarray:
    """A random texture in [0.2, 0.8], optionally blurred (float64, size × size)."""
    image = np.random.default_rng(seed).uniform(0.2, 0.8, (size, size))
    return ndimage.gaussian_filter(image, sigma, mode="reflect") if sigma > 0 else image


def stripes(size: int = 32, period: int = 6, vertical: bool = True) -> np.ndarray:
    """Square-wave stripes of levels 0.2 and 0.8 with half the pixels at each level (mean 0.5)."""
    wave = np.where((np.arange(size) // (period // 2)) % 2 == 0, 0.2, 0.8)
    image = np.tile(wave, (size, 1))
    return image if vertical else image.T.copy()


# Independent reference implementations (NumPy/SciPy), written from the formulas, not from psmini.
def ref_brenner(g: np.ndarray) -> float:
    c = g[:-2, :-2]
    return float(np.maximum((g[:-2, 2:] - c) ** 2, (g[2:, :-2] - c) ** 2).mean())


def ref_contrast(g: np.ndarray) -> float:
    h, w = g.shape
    total = np.zeros((h - 2, w - 2))
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            total[i - 1, j - 1] = np.abs(g[i, j] - g[i - 1 : i + 2, j - 1 : j + 2]).sum()
    return float(total.mean())


def ref_wavelet(g: np.ndarray) -> float:
    a, b, c, d = g[:-1, :-1], g[:-1, 1:], g[1:, :-1], g[1:, 1:]  # every 2 × 2 window (stationary transform)
    return float((np.abs(a + b - c - d) + np.abs(a - b + c - d) + np.abs(a - b - c + d)).mean() / 2)


def ref_tenengrad(g: np.ndarray) -> float:
    gx, gy = ndimage.sobel(g, axis=1), ndimage.sobel(g, axis=0)
    return float((gx**2 + gy**2)[1:-1, 1:-1].mean())


def ref_laplacian(g: np.ndarray) -> float:
    return float(ndimage.laplace(g)[1:-1, 1:-1].var())


def ref_gaussian(g: np.ndarray, sigma: float) -> float:
    # Gaussian derivative by SciPy, with its own truncation; the sums match psmini's normalisation to ~1e-3.
    r = int(np.ceil(3 * sigma))
    gx = ndimage.gaussian_filter(g, sigma, order=(0, 1), truncate=r / sigma)
    gy = ndimage.gaussian_filter(g, sigma, order=(1, 0), truncate=r / sigma)
    return float((gx**2 + gy**2)[r:-r, r:-r].mean())


def ref_variance(g: np.ndarray) -> float:
    return float(g.var() / g.mean())


REFERENCES = {
    "brenner": ref_brenner,
    "contrast": ref_contrast,
    "wavelet": ref_wavelet,
    "tenengrad": ref_tenengrad,
    "laplacian": ref_laplacian,
    "variance": ref_variance,
}


class TestAgainstReferences(BaseTester):
    @pytest.mark.parametrize("name", list(REFERENCES))
    def test_matches_numpy(self, name, device, dtype):
        images = [texture(21, seed) for seed in range(2)]
        frames = torch.tensor(np.stack(images), device=device, dtype=dtype)
        expected = torch.tensor([REFERENCES[name](g) for g in images], device=device, dtype=dtype)
        self.assert_close(focus_measure(frames, name), expected)

    def test_gaussian_matches_scipy(self, device):
        g = texture(40, 3, sigma=1.0)
        frames = torch.tensor(g[None], device=device, dtype=torch.float64)
        for sigma in (1.0, 1.5):
            actual = float(gaussian_derivative(frames, sigma=sigma))
            # SciPy's derivative kernel is normalised analytically, psmini's to a unit ramp: 1% agreement.
            assert actual == pytest.approx(ref_gaussian(g, sigma), rel=2e-2)

    def test_gaussian_unit_ramp(self, device, dtype):
        ramp = torch.arange(20, device=device, dtype=dtype).repeat(20, 1)
        frames = torch.stack([ramp, ramp.T])
        self.assert_close(gaussian_derivative(frames, sigma=1.3), torch.ones(2, device=device, dtype=dtype))

    def test_brenner_step_edge(self, device, dtype):
        frames = torch.zeros(1, 8, 8, device=device, dtype=dtype)
        frames[..., 4:] = 1.0
        # positions j = 2, 3 of the 6 columns see the edge through g[i, j+2]: 2/6 of the positions score 1.
        self.assert_close(brenner(frames), torch.full((1,), 1 / 3, device=device, dtype=dtype))

    def test_tenengrad_threshold(self, device):
        frames = torch.tensor(texture(16, 1)[None], device=device)
        full = tenengrad(frames)
        assert float(tenengrad(frames, threshold=1e9)) == 0.0
        assert 0 < float(tenengrad(frames, threshold=float(full))) < float(full)


class TestIntegerInput(BaseTester):
    @pytest.mark.parametrize("name", NAMES)
    def test_uint8_scaled(self, name, device):
        raw = torch.randint(0, 256, (3, 37, 41), dtype=torch.uint8, device=device)
        expected = focus_measure(raw.double() / 255.0, name)
        actual = focus_measure(raw, name)
        assert actual.dtype == torch.float32
        self.assert_close(actual.double(), expected, rtol=1e-5, atol=1e-7)

    @pytest.mark.parametrize("name", NAMES)
    def test_uint16_scaled(self, name, device):
        raw = torch.randint(0, 65536, (2, 20, 24), dtype=torch.int32, device=device).to(torch.uint16)
        expected = focus_measure(raw.to(torch.int32).double() / 65535.0, name)
        self.assert_close(focus_measure(raw, name).double(), expected, rtol=1e-5, atol=1e-7)

    def test_uint8_brenner_exact_on_large_frame(self):
        raw = torch.randint(0, 256, (2, 480, 640), dtype=torch.uint8)
        g = raw.numpy().astype(np.float64) / 255.0
        expected = torch.tensor([ref_brenner(x) for x in g], dtype=torch.float64)
        self.assert_close(brenner(raw).double(), expected, rtol=1e-6, atol=0)

    def test_uint8_brenner_non_contiguous(self):
        raw = torch.randint(0, 256, (4, 30, 40), dtype=torch.uint8)
        expected = brenner(raw.double() / 255)
        self.assert_close(brenner(raw[::2]).double(), expected[::2], rtol=1e-6, atol=1e-8)
        transposed = raw.transpose(-1, -2)  # strides the fast path cannot view: it copies
        self.assert_close(brenner(transposed).double(), brenner(transposed.double() / 255), rtol=1e-6, atol=1e-8)


class TestSymmetry(BaseTester):
    """FIELD_NOTES: signed maxima score one polarity 0; 1-D ports see one orientation. Every measure here must not."""

    @pytest.mark.parametrize("name", NAMES)
    def test_orientation(self, name, device):
        for period in (4, 6, 10):
            vertical = torch.tensor(stripes(32, period, vertical=True)[None], device=device)
            horizontal = torch.tensor(stripes(32, period, vertical=False)[None], device=device)
            score_v, score_h = focus_measure(vertical, name), focus_measure(horizontal, name)
            # 2-pixel stripes put every pixel on an edge: the variance of a response (TENV, GLLV) is then 0
            assert period == 4 or float(score_v) > 1e-3
            self.assert_close(score_v, score_h)

    @pytest.mark.parametrize("name", NAMES)
    def test_transpose_texture(self, name, device):
        g = torch.tensor(texture(33, 5)[None], device=device)
        self.assert_close(focus_measure(g, name), focus_measure(g.transpose(-1, -2), name))

    @pytest.mark.parametrize("name", NAMES)
    def test_polarity(self, name, device):
        # Inversion keeps the mean of these images (0.5), so even the normalised variance must agree.
        edge = torch.full((1, 24, 24), 0.2, device=device, dtype=torch.float64)
        edge[..., 12:] = 0.8
        for image in (edge, edge.transpose(-1, -2), torch.tensor(stripes(24, 6)[None], device=device)):
            self.assert_close(focus_measure(image, name), focus_measure(1.0 - image, name))

    @pytest.mark.parametrize("name", [n for n in NAMES if n not in BRIGHTNESS_RATIOS])
    def test_polarity_texture_uint8(self, name, device):
        raw = torch.randint(0, 256, (2, 31, 29), dtype=torch.uint8, device=device)
        self.assert_close(focus_measure(raw, name), focus_measure(255 - raw, name))


class TestBehaviour(BaseTester):
    @pytest.mark.parametrize("name", [n for n in NAMES if n != "vola"])
    def test_blur_lowers_score(self, name, device):
        stack = np.stack([texture(64, 7, sigma) for sigma in (0.0, 0.7, 1.5, 3.0)])
        scores = focus_measure(torch.tensor(stack, device=device), name)
        assert bool((scores[:-1] > scores[1:]).all()), scores

    @pytest.mark.parametrize("name", NAMES)
    def test_shapes_and_batch(self, name, device, dtype):
        frames = torch.rand(3, 1, 20, 22, device=device, dtype=dtype)
        scores = focus_measure(frames, name)
        assert scores.shape == (3,) and scores.dtype == dtype and scores.device.type == device.type
        self.assert_close(focus_measure(frames[:, 0], name), scores)
        self.assert_close(focus_measure(frames[1:2], name), scores[1:2])

    @pytest.mark.parametrize("name", NAMES)
    def test_roi_is_crop(self, name, device):
        frames = torch.rand(2, 30, 40, device=device, dtype=torch.float64)
        self.assert_close(focus_measure(frames, name, roi=(5, 3, 21, 17)), focus_measure(frames[:, 3:20, 5:26], name))
        self.assert_close(focus_measure(frames, name, roi="5,3,21,17"), focus_measure(frames[:, 3:20, 5:26], name))

    def test_roi_uint8_brenner(self):
        raw = torch.randint(0, 256, (2, 30, 40), dtype=torch.uint8)
        self.assert_close(brenner(raw, roi=(7, 2, 13, 11)), brenner(raw[:, 2:13, 7:20].contiguous()))

    def test_module(self, device):
        frames = torch.rand(2, 24, 24, device=device)
        module = FocusMeasure("gaussian", roi=(2, 2, 20, 20), sigma=1.2)
        self.assert_close(module(frames), gaussian_derivative(frames[:, 2:22, 2:22], sigma=1.2))
        assert "gaussian" in repr(module)

    def test_gradcheck_module(self):
        frames = (torch.rand(2, 9, 10, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
        self.gradcheck(FocusMeasure("gaussian", roi=(1, 1, 8, 7), sigma=0.6), (frames,))

    def test_vollath_blur_lowers_score_of_band_limited_texture(self, device):
        # Vollath's F4 is lag-1 minus lag-2 autocorrelation: on white noise both are ~0 and a little blur raises
        # the lag-1 term first; on a texture with a finite correlation length (any real image) blur lowers it.
        stack = np.stack([texture(64, 7, sigma) for sigma in (1.0, 1.5, 2.2, 3.0)])
        scores = focus_measure(torch.tensor(stack, device=device), "vola")
        assert bool((scores[:-1] > scores[1:]).all()), scores

    def test_constant_frames_score_zero(self, device):
        frames = torch.full((2, 16, 16), 0.4, device=device)
        for name in NAMES:
            self.assert_close(focus_measure(frames, name), torch.zeros(2, device=device), atol=1e-6, rtol=0)
        assert float(normalized_variance(torch.zeros(1, 4, 4))) == 0.0


class TestGradcheck(BaseTester):
    @pytest.mark.parametrize("name", NAMES)
    def test_gradcheck(self, name):
        frames = torch.rand(2, 9, 10, dtype=torch.float64, requires_grad=True)
        kwargs = {"sigma": 0.6} if name == "gaussian" else {}
        self.gradcheck(lambda x: focus_measure(x, name, **kwargs), (frames,))


class TestErrors:
    def test_roi_errors(self):
        frames = torch.rand(1, 20, 30)
        with pytest.raises(InputError, match="outside"):
            brenner(frames, roi=(20, 0, 20, 10))
        with pytest.raises(InputError, match="outside"):
            brenner(frames, roi=(-1, 0, 5, 5))
        with pytest.raises(InputError, match="at least 3"):
            brenner(frames, roi=(0, 0, 2, 10))
        with pytest.raises(InputError, match="four integers"):
            brenner(frames, roi=(0, 0, 5))
        with pytest.raises(InputError, match="four integers"):
            brenner(frames, roi="a,b,c,d")
        with pytest.raises(InputError, match="four integers"):
            brenner(frames, roi=(0.5, 0, 5, 5))
        assert parse_roi(None, 10, 10) is None

    @pytest.mark.parametrize("name", NAMES)
    def test_bad_frames(self, name):
        with pytest.raises(InputError, match="uint8, uint16 or floating"):
            focus_measure(torch.zeros(1, 8, 8, dtype=torch.int32), name)
        with pytest.raises(InputError, match="torch.Tensor"):
            focus_measure(np.zeros((1, 8, 8)), name)
        with pytest.raises(ShapeError, match=r"\(B, H, W\)"):
            focus_measure(torch.zeros(8, 8), name)
        with pytest.raises(ShapeError, match=r"\(B, H, W\)"):
            focus_measure(torch.zeros(1, 3, 8, 8), name)
        with pytest.raises(ShapeError, match="at least"):
            focus_measure(torch.zeros(1, 0, 40), name)
        if name not in POINTWISE:  # every other measure needs neighbours
            with pytest.raises(ShapeError, match="at least"):
                focus_measure(torch.zeros(1, 1, 40), name)
        bad = torch.rand(1, 8, 8)
        bad[0, 3, 3] = float("nan")
        with pytest.raises(InputError, match="finite"):
            focus_measure(bad, name)

    def test_bad_parameters(self):
        frames = torch.rand(1, 16, 16)
        with pytest.raises(InputError, match="unknown focus measure 'sharpness'"):
            focus_measure(frames, "sharpness")
        with pytest.raises(InputError, match="unknown focus measure"):
            FocusMeasure("sharpness")
        with pytest.raises(InputError, match="sigma"):
            gaussian_derivative(frames, sigma=0.0)
        with pytest.raises(InputError, match="threshold"):
            tenengrad(frames, threshold=-1.0)
        with pytest.raises(InputError, match="eps"):
            normalized_variance(frames, eps=0.0)

    def test_every_function_guards(self):
        for func in (brenner, image_contrast, wavelet_sum, gaussian_derivative, tenengrad, variance_of_laplacian,
                     normalized_variance):
            with pytest.raises(ShapeError):
                func(torch.zeros(2, 2, 2, 2))


class TestFocusCommand:
    """``psmini focus DIR``: frames in name order or from a focus capture manifest."""

    @staticmethod
    def write_sweep(folder, sigmas=(3.0, 1.5, 0.0, 1.0, 2.5), dtype=np.uint8):
        import cv2

        folder.mkdir(parents=True, exist_ok=True)
        scale = np.iinfo(dtype).max
        for i, sigma in enumerate(sigmas):
            image = texture(40, 11, sigma)
            cv2.imwrite(str(folder / f"frame_{i:02d}.png"), (image * scale).round().astype(dtype))
        return [f"frame_{i:02d}.png" for i in range(len(sigmas))]

    def run(self, capsys, *argv):
        from psmini.cli import main

        status = main(["focus", *map(str, argv)])
        out, err = capsys.readouterr()
        return status, out, err

    def test_name_order_json(self, tmp_path, capsys):
        self.write_sweep(tmp_path / "sweep")
        status, out, _ = self.run(capsys, tmp_path / "sweep", "--json")
        assert status == 0
        import json

        payload = json.loads(out.strip().splitlines()[-1])
        assert payload["best_index"] == 2 and len(payload["scores"]) == 5
        assert 1.5 <= payload["best_position"] <= 2.5 and payload["positions_are_indices"]
        assert "best index 2" in out

    def test_manifest_positions_roi_metric(self, tmp_path, capsys):
        import json

        folder = tmp_path / "sweep16"
        names = self.write_sweep(folder, dtype=np.uint16)
        positions = [0.0, 0.5, 1.0, 1.5, 2.0]
        (folder / "capture.json").write_text(json.dumps({
            "format": "psmini-capture", "version": 1, "kind": "focus", "images": names, "dark": None, "mask": None,
            "bit_depth": 16, "pixel_pitch_mm": 0.025, "lights": None, "positions_mm": positions,
        }))
        (folder / "notes.txt").write_text("not an image")
        status, out, _ = self.run(capsys, folder, "--metric", "tenengrad", "--roi", "4,4,30,30", "--json")
        assert status == 0
        payload = json.loads(out.strip().splitlines()[-1])
        assert payload["best_index"] == 2 and payload["metric"] == "tenengrad" and payload["roi"] == [4, 4, 30, 30]
        assert 0.5 <= payload["best_position"] <= 1.5 and payload["positions"] == positions

    def test_errors(self, tmp_path, capsys):
        import cv2

        (tmp_path / "empty").mkdir()
        status, _, err = self.run(capsys, tmp_path / "empty")
        assert status == 1 and "no image files" in err
        mixed = tmp_path / "mixed"
        self.write_sweep(mixed, sigmas=(0.0, 1.0))
        cv2.imwrite(str(mixed / "frame_99.png"), np.zeros((20, 30), np.uint8))
        status, _, err = self.run(capsys, mixed)
        assert status == 1 and "different sizes" in err
        self.write_sweep(tmp_path / "ok", sigmas=(0.0, 1.0))
        status, _, err = self.run(capsys, tmp_path / "ok", "--roi", "30,30,20,20")
        assert status == 1 and "outside the 40×40 frame" in err
        status, _, err = self.run(capsys, tmp_path / "missing")
        assert status == 1 and "not a folder" in err


def test_docstring_examples():
    import doctest

    import psmini.focus

    assert doctest.testmod(psmini.focus, raise_on_error=False).failed == 0
