"""load_sample for both folder kinds (with the flat-field capture wired in) and find_samples."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from psmini import DataFormatError, DirectionalLights, ring_lights
from psmini.io.capture import write_capture
from psmini.io.load import find_samples, load_sample
from psmini.io.sample import Sample
from tests.conftest import shared_data

H, W, K = 5, 6, 8


def lights() -> DirectionalLights:
    return DirectionalLights(ring_lights(K, 55.0))


def images(seed: int, count: int = K) -> np.ndarray:
    return np.random.default_rng(seed).random((count, H, W))


@pytest.fixture
def rig(tmp_path):
    """A card capture and a sample referencing it, as the rig writes them."""
    write_capture(tmp_path / "card", images(1), lights(), pixel_pitch_mm=0.025, kind="flatfield", card_albedo=0.8,
                  dark=images(2, 1)[0] * 0.01, bit_depth=12)  # fmt: skip
    gt = {"normals": np.tile(np.array([0, 0, 1.0])[:, None, None], (1, H, W)), "depth": np.zeros((H, W)),
          "albedo": np.full((H, W), 0.5), "mask": np.ones((H, W), bool), "lights": lights()}  # fmt: skip
    write_capture(tmp_path / "denim", images(3), lights(), pixel_pitch_mm=0.025, flatfield={"path": "../card"},
                  dark=images(4, 1)[0] * 0.01, mask=np.ones((H, W)), gt=gt, metadata={"fabric": "denim"})  # fmt: skip
    return tmp_path


class TestLoadCapture:
    def test_sample_with_flatfield(self, rig):
        sample = load_sample(rig / "denim")
        assert isinstance(sample, Sample) and sample.name == "denim" and sample.count == K
        assert sample.images.shape == (K, H, W) and sample.images.dtype == torch.float32
        torch.testing.assert_close(sample.images.double(), torch.from_numpy(images(3)), rtol=0, atol=0.5 / 65535 + 1e-7)
        torch.testing.assert_close(
            sample.reference.double(), torch.from_numpy(images(1)), rtol=0, atol=0.5 / 4095 + 1e-7
        )
        assert sample.reference_dark.shape == (1, H, W) and sample.dark.shape == (1, H, W)
        assert sample.card_albedo == 0.8 and sample.pixel_pitch_mm == 0.025 and sample.saturation_level == 1.0
        assert sample.mask.dtype == torch.bool and bool(sample.mask.all())
        assert sample.normals_gt.shape == (3, H, W) and sample.depth_gt.shape == (1, H, W)
        assert sample.albedo_gt.shape == (1, H, W) and sample.gt_mask.shape == (1, H, W)
        assert isinstance(sample.meta["gt_lights"], DirectionalLights)
        assert sample.meta["source"] == "capture" and sample.meta["metadata"] == {"fabric": "denim"}

    def test_card_left_to_the_caller(self, rig, monkeypatch):
        """with_flatfield=False: the card's images are not decoded; its path and albedo stay for the caller."""
        import psmini.io.load as load_module

        decoded = []
        real_read_capture = load_module.read_capture
        monkeypatch.setattr(
            load_module,
            "read_capture",
            lambda path, **kw: decoded.append(Path(path).name) or real_read_capture(path, **kw),
        )
        sample = load_sample(rig / "denim", with_flatfield=False)
        assert decoded == ["denim"]
        assert sample.reference is None and sample.reference_dark is None and sample.card_albedo == 0.8
        assert Path(sample.meta["flatfield"]).resolve() == (rig / "card").resolve()
        load_sample(rig / "denim")
        assert decoded == ["denim", "denim", "card"]

    def test_sample_without_flatfield(self, tmp_path):
        write_capture(tmp_path / "s", images(0), lights(), pixel_pitch_mm=0.025)
        sample = load_sample(tmp_path / "s")
        assert (
            sample.reference is None and sample.card_albedo == 1.0 and sample.mask is None and sample.normals_gt is None
        )

    def test_flatfield_with_other_image_count(self, tmp_path):
        other = DirectionalLights(ring_lights(4, 55.0))
        write_capture(tmp_path / "card", images(1, 4), other, pixel_pitch_mm=0.025, kind="flatfield", card_albedo=0.8)
        write_capture(tmp_path / "s", images(0), lights(), pixel_pitch_mm=0.025, flatfield={"path": "../card"})
        with pytest.raises(DataFormatError, match=r"\(4, 5, 6\) .* \(8, 5, 6\); the card must be imaged under the same "
                                                  r"LEDs"):
            load_sample(tmp_path / "s")

    def test_focus_capture_is_refused(self, tmp_path):
        write_capture(tmp_path / "f", images(0, 2), None, pixel_pitch_mm=0.025, kind="focus", positions_mm=[0, 1])
        with pytest.raises(DataFormatError, match="'focus' capture without lights"):
            load_sample(tmp_path / "f")


class TestLoadDiligent:
    @pytest.mark.slow
    def test_diligent_folder(self):
        sample = load_sample(shared_data("DiLiGenT", "cat"))
        assert sample.images.shape == (96, 512, 612) and sample.normals_gt.shape == (3, 512, 612)
        assert sample.pixel_pitch_mm is None and sample.reference is None and sample.meta["source"] == "diligent"


class TestErrors:
    def test_missing_folder(self, tmp_path):
        with pytest.raises(DataFormatError, match="does not exist"):
            load_sample(tmp_path / "none")

    def test_unknown_folder(self, tmp_path):
        (tmp_path / "readme.txt").write_text("hi")
        with pytest.raises(DataFormatError, match="not a sample folder: expected capture.json .* or filenames.txt"):
            load_sample(tmp_path)


class TestFindSamples:
    def test_lists_samples_only(self, rig, tmp_path, caplog):
        write_capture(tmp_path / "nested" / "sphere", images(5), lights(), pixel_pitch_mm=0.025, kind="sphere")
        write_capture(tmp_path / "nested" / "twill", images(6), lights(), pixel_pitch_mm=0.025)
        write_capture(
            tmp_path / "nested" / "focus", images(6, 2), None, pixel_pitch_mm=0.025, kind="focus", positions_mm=[0, 1]
        )
        (tmp_path / "nested" / "broken").mkdir()
        (tmp_path / "nested" / "broken" / "capture.json").write_text("{")
        (tmp_path / ".hidden.tmp-1234").mkdir()
        (tmp_path / ".hidden.tmp-1234" / "capture.json").write_text(json.dumps({}))
        diligent = tmp_path / "dl" / "obj"
        diligent.mkdir(parents=True)
        (diligent / "filenames.txt").write_text("001.png\n")
        (diligent / "light_directions.txt").write_text("0 0 1\n")
        with caplog.at_level(logging.WARNING, logger="psmini.io.load"):
            found = find_samples(tmp_path)
        assert found == sorted([rig / "denim", diligent, tmp_path / "nested" / "broken", tmp_path / "nested" / "twill"])
        assert "broken" in caplog.text

    def test_does_not_descend_into_samples(self, rig):
        assert find_samples(rig / "denim") == [rig / "denim"]

    def test_shared_diligent(self):
        root = shared_data("DiLiGenT")
        assert find_samples(root) == [root / "ball", root / "cat"]

    def test_root_must_be_a_folder(self, tmp_path):
        with pytest.raises(DataFormatError, match="not a folder"):
            find_samples(tmp_path / "none")


def test_capture_round_trip_through_the_pipeline(tmp_path):
    """A sphere rendered under known lights, written as a 16-bit capture, loads and reconstructs to ~0°."""
    from psmini.metrics import mean_angular_error
    from psmini.pipeline import reconstruct

    size = 48
    y, x = torch.meshgrid(torch.linspace(1, -1, size), torch.linspace(-1, 1, size), indexing="ij")  # y up
    inside = x**2 + y**2 < 0.8
    normals = torch.stack([x, y, (1 - x**2 - y**2).clamp_min(0).sqrt()]) * inside
    directions = ring_lights(K, 40.0)
    shading = torch.einsum("kc,chw->khw", directions, normals).clamp_min(0) * 0.9
    write_capture(tmp_path / "sphere", shading, DirectionalLights(directions), pixel_pitch_mm=0.025,
                  mask=inside, gt={"normals": normals})  # fmt: skip
    sample = load_sample(tmp_path / "sphere")
    result = reconstruct(sample)
    error = mean_angular_error(
        result.normals, sample.normals_gt[None], sample.mask[None] & (shading > 0).all(0)[None, None]
    )
    assert float(error) < 0.1
