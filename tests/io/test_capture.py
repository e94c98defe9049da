"""Capture folders: write/read round trips (bit-exact codes, lights, ground truth), validation, atomicity."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from psmini import DataFormatError, DirectionalLights, InputError, LEDLights, PointLights, ring_lights
from psmini.io import capture as capture_module
from psmini.io.capture import lights_from_dict, lights_to_dict, read_capture, read_manifest, write_capture
from psmini.io.images import write_image
from psmini.io.load import load_sample

H, W, K = 6, 7, 8


def directional() -> DirectionalLights:
    return DirectionalLights(ring_lights(K, 55.0), torch.linspace(0.5, 1.5, K))


def leds() -> LEDLights:
    positions = torch.cat([ring_lights(K, 55.0)[:, :2] * 15.8, torch.full((K, 1), 10.0)], dim=1)
    return LEDLights(positions, -ring_lights(K, 20.0), torch.linspace(1.0, 2.0, K), torch.linspace(0.5, 2.0, K))


def points() -> PointLights:
    return PointLights(leds().positions_mm, torch.full((K,), 3.0))


def codes(bits: int, seed: int = 0, count: int = K) -> np.ndarray:
    return (
        np.random.default_rng(seed).integers(0, 2**bits, size=(count, H, W)).astype(np.uint16 if bits > 8 else np.uint8)
    )


def assert_same_lights(actual, expected) -> None:
    """Same model and parameters; unit vectors are renormalised on construction, so allow an ulp or two."""
    assert type(actual) is type(expected)
    for name in ("directions", "positions_mm", "principal_directions", "intensities", "mu"):
        if hasattr(expected, name):
            torch.testing.assert_close(getattr(actual, name), getattr(expected, name), rtol=0, atol=1e-7)


class TestLightsDict:
    @pytest.mark.parametrize("factory", [directional, points, leds], ids=["directional", "point", "led"])
    def test_round_trip_through_json(self, factory):
        lights = factory()
        data = json.loads(json.dumps(lights_to_dict(lights)))
        assert_same_lights(lights_from_dict(data), lights)

    def test_optional_keys_default_to_ones(self):
        back = lights_from_dict(
            {"model": "led", "positions_mm": [[0, 0, 10]] * 3, "principal_directions": [[0, 0, -1]] * 3}
        )
        torch.testing.assert_close(back.mu, torch.ones(3))
        torch.testing.assert_close(back.intensities, torch.ones(3))

    def test_dtype(self):
        assert lights_from_dict(lights_to_dict(directional()), dtype=torch.float64).directions.dtype == torch.float64

    @pytest.mark.parametrize(
        ("data", "message"),
        [
            ([1, 2], "JSON object"),
            ({"model": "spot"}, "one of"),
            ({"model": "point"}, "lacks 'positions_mm'"),
            ({"model": "directional", "directions": [[1, 2]]}, r"\[x, y, z\] triples"),
            ({"model": "directional", "directions": [["a", "b", "c"]]}, "must hold numbers"),
            ({"model": "directional", "directions": [[0, 0, 1]], "intensities": [[1]]}, "list of numbers"),
        ],
    )
    def test_bad_dicts(self, data, message):
        with pytest.raises(DataFormatError, match=message):
            lights_from_dict(data)

    def test_to_dict_refuses_other_objects(self):
        with pytest.raises(InputError, match="LightModel .DirectionalLights, PointLights, LEDLights or a subclass"):
            lights_to_dict(torch.nn.Linear(2, 2))


class TestRoundTrip:
    @pytest.mark.parametrize("bits", [8, 10, 12, 16])
    def test_codes_survive_bit_exact(self, tmp_path, bits):
        raw = codes(bits)
        write_capture(tmp_path / "s", raw, directional(), pixel_pitch_mm=0.025, bit_depth=bits)
        capture = read_capture(tmp_path / "s")
        assert capture.bit_depth == bits and capture.images.dtype == torch.float32
        back = np.rint(capture.images.double().numpy() * (2**bits - 1)).astype(np.int64)
        np.testing.assert_array_equal(back, raw.astype(np.int64))

    def test_floats_are_rounded_to_codes(self, tmp_path):
        images = torch.rand(K, H, W, dtype=torch.float64)
        write_capture(tmp_path / "s", images, directional(), pixel_pitch_mm=0.025, bit_depth=16)
        torch.testing.assert_close(
            read_capture(tmp_path / "s").images.double(), images, rtol=0, atol=0.5 / 65535 + 1e-7
        )

    def test_everything_round_trips(self, tmp_path):
        rng = np.random.default_rng(3)
        normals = rng.normal(size=(3, H, W)).astype(np.float32)
        normals /= np.linalg.norm(normals, axis=0)
        depth = rng.random((H, W)).astype(np.float32)
        depth[0, 0] = np.nan
        gt = {
            "normals": normals,
            "depth": depth,
            "albedo": rng.random((H, W)),
            "mask": depth == depth,
            "lights": leds(),
        }
        dark, mask = codes(16, seed=5, count=1)[0], rng.random((H, W)) > 0.5
        write_capture(
            tmp_path / "card", codes(16, seed=9), directional(), pixel_pitch_mm=0.025, kind="flatfield", card_albedo=0.8
        )
        write_capture(
            tmp_path / "s", codes(16), directional(), pixel_pitch_mm=0.03, dark=dark, mask=mask,
            flatfield={"path": str(tmp_path / "card")}, gt=gt, crop=[120, 40, 400, 400],
            camera={"exposure": -6}, metadata={"fabric": "denim", "threads_per_cm": 24},
        )  # fmt: skip
        capture = read_capture(tmp_path / "s")
        assert capture.kind == "sample" and capture.pixel_pitch_mm == 0.03
        np.testing.assert_array_equal(np.rint(capture.dark[0].numpy() * 65535).astype(np.uint16), dark)
        np.testing.assert_array_equal(capture.mask[0].numpy(), mask)
        assert capture.flatfield_path == (tmp_path / "card").resolve() and capture.card_albedo == 0.8
        assert capture.manifest["flatfield"] == {"path": "../card"}  # stored relative
        np.testing.assert_array_equal(capture.gt["normals"].numpy(), normals)
        np.testing.assert_array_equal(capture.gt["depth"][0].numpy(), depth)  # NaN where NaN
        np.testing.assert_array_equal(capture.gt["mask"][0].numpy(), depth == depth)
        assert capture.gt["albedo"].shape == (1, H, W)
        assert_same_lights(capture.gt["lights"], leds())
        assert_same_lights(capture.lights, directional())
        assert capture.crop == [120, 40, 400, 400] and capture.camera == {"exposure": -6}
        assert capture.metadata == {"fabric": "denim", "threads_per_cm": 24}
        assert capture.manifest["software"].startswith("psmini ")
        # without ground truth nothing of it is read: a broken ground-truth file does not matter then
        (tmp_path / "s" / capture.manifest["gt"]["normals"]).write_bytes(b"not an npy file")
        bare = read_capture(tmp_path / "s", ground_truth=False)
        assert bare.gt == {} and torch.equal(bare.images, capture.images)
        sample = load_sample(tmp_path / "s", with_ground_truth=False)
        assert sample.normals_gt is None and sample.depth_gt is None and sample.meta["gt_lights"] is None
        with pytest.raises(DataFormatError, match="ground truth"):
            read_capture(tmp_path / "s")

    def test_focus_capture(self, tmp_path):
        write_capture(
            tmp_path / "f",
            codes(8, count=3),
            None,
            pixel_pitch_mm=0.025,
            kind="focus",
            bit_depth=8,
            positions_mm=[0, 0.1, 0.2],
        )
        capture = read_capture(tmp_path / "f")
        assert capture.lights is None and capture.positions_mm == [0.0, 0.1, 0.2]

    def test_rgb_images_read_as_gray(self, tmp_path):
        write_capture(tmp_path / "s", codes(16), directional(), pixel_pitch_mm=0.025)
        rgb = np.zeros((H, W, 3), np.uint16)
        rgb[..., 1] = 65535
        for index in range(K):
            write_image(tmp_path / "s" / f"led_{index:02d}.png", rgb)
        np.testing.assert_allclose(read_capture(tmp_path / "s").images.numpy(), 0.587, rtol=1e-6)

    def test_many_leds_get_wider_names(self, tmp_path):
        lights = DirectionalLights(ring_lights(101, 55.0))
        write_capture(tmp_path / "s", np.zeros((101, 2, 2), np.uint8), lights, pixel_pitch_mm=1.0, bit_depth=8)
        assert read_manifest(tmp_path / "s")["images"][100] == "led_100.png"


class TestWriteErrors:
    def test_existing_folder_refused_then_overwritten(self, tmp_path):
        write_capture(tmp_path / "s", codes(16), directional(), pixel_pitch_mm=0.025)
        with pytest.raises(DataFormatError, match="already exists"):
            write_capture(tmp_path / "s", codes(16, seed=1), directional(), pixel_pitch_mm=0.025)
        write_capture(tmp_path / "s", codes(16, seed=1), directional(), pixel_pitch_mm=0.025, overwrite=True)
        back = np.rint(read_capture(tmp_path / "s").images.numpy() * 65535).astype(np.uint16)
        np.testing.assert_array_equal(back, codes(16, seed=1))
        assert sorted(os.listdir(tmp_path)) == ["s"]  # no temporary or old folder left

    @pytest.mark.parametrize(
        ("kwargs", "message"),
        [
            ({"images": np.zeros((K, H)), "lights": None}, r"shape \(K, H, W\)"),
            ({"images": np.full((K, H, W), 1.5)}, r"floats in \[0, 1\]"),
            ({"images": np.full((K, H, W), np.nan)}, "NaN"),
            ({"images": np.full((K, H, W), 4096, np.uint16), "bit_depth": 12}, "outside 0..4095"),
            ({"images": np.zeros((K, H, W), bool)}, "floats in"),
            ({"images": [[0.0]]}, "torch.Tensor or numpy"),
            ({"lights": DirectionalLights(ring_lights(4, 55.0))}, "8 images but 4 lights"),
            ({"lights": None}, "lights are required"),
            # a tensor of directions is not a light model: an argument error, not a file format one
            ({"lights": ring_lights(K, 55.0)}, "DirectionalLights, PointLights, LEDLights or a subclass"),
            ({"gt": {"lights": ring_lights(K, 55.0)}}, "DirectionalLights, PointLights, LEDLights or a subclass"),
            ({"kind": "calibration"}, "kind must be one of"),
            ({"bit_depth": 14}, "bit_depth must be one of"),
            ({"pixel_pitch_mm": 0}, "pixel_pitch_mm"),
            ({"kind": "flatfield"}, "card_albedo"),
            ({"kind": "focus"}, "positions_mm"),
            ({"dark": np.zeros((H + 1, W))}, "dark must be"),
            ({"mask": np.zeros((H, W + 1))}, "mask must be"),
            ({"gt": {"normals": np.zeros((H, W))}}, r"gt\['normals'\] must have shape"),
            ({"gt": {"height": np.zeros((H, W))}}, "unknown ground-truth"),
            ({"flatfield": {"albedo": 0.5}}, "flatfield must be"),
            ({"metadata": {"when": object()}}, "serialise to JSON"),
        ],
    )
    def test_bad_arguments(self, tmp_path, kwargs, message):
        arguments = {"images": codes(16), "lights": directional(), "pixel_pitch_mm": 0.025} | kwargs
        images, lights = arguments.pop("images"), arguments.pop("lights")
        with pytest.raises(InputError, match=message):
            write_capture(tmp_path / "s", images, lights, **arguments)
        assert not (tmp_path / "s").exists()
        assert os.listdir(tmp_path) == []

    def test_failure_mid_write_leaves_nothing(self, tmp_path, monkeypatch):
        calls = []

        def failing_write(path, pixels):
            calls.append(path)
            if len(calls) == 3:
                raise DataFormatError("disk full (simulated)")
            from psmini.io.images import write_image as real

            real(path, pixels)

        monkeypatch.setattr(capture_module, "write_image", failing_write)
        with pytest.raises(DataFormatError, match="simulated"):
            write_capture(tmp_path / "s", codes(16), directional(), pixel_pitch_mm=0.025)
        assert len(calls) == 3 and (tmp_path / ".s.tmp-") != calls[0].parent
        assert calls[0].parent.name.startswith(".s.tmp-")
        assert os.listdir(tmp_path) == []

    def test_failure_during_overwrite_keeps_the_old_folder(self, tmp_path, monkeypatch):
        write_capture(tmp_path / "s", codes(16), directional(), pixel_pitch_mm=0.025)
        monkeypatch.setattr(capture_module, "write_image", lambda path, pixels: (_ for _ in ()).throw(OSError("boom")))
        with pytest.raises(OSError, match="boom"):
            write_capture(tmp_path / "s", codes(16, seed=1), directional(), pixel_pitch_mm=0.025, overwrite=True)
        assert os.listdir(tmp_path) == ["s"]
        back = np.rint(read_capture(tmp_path / "s").images.numpy() * 65535).astype(np.uint16)
        np.testing.assert_array_equal(back, codes(16))


    def test_failed_rename_during_overwrite_puts_the_old_folder_back(self, tmp_path, monkeypatch):
        """The old folder was moved into a hidden .s.old-* sibling before the new one was renamed in; when that
        rename failed, the capture was left there, hidden, and s was gone."""
        write_capture(tmp_path / "s", codes(16), directional(), pixel_pitch_mm=0.025)
        real_replace = os.replace

        def failing_replace(source, target):
            if Path(target) == tmp_path / "s" and Path(source).name.startswith(".s.tmp-"):
                raise OSError(28, "No space left on device")
            return real_replace(source, target)

        monkeypatch.setattr(os, "replace", failing_replace)
        with pytest.raises(OSError, match="No space left"):
            write_capture(tmp_path / "s", codes(16, seed=1), directional(), pixel_pitch_mm=0.025, overwrite=True)
        assert os.listdir(tmp_path) == ["s"]
        back = np.rint(read_capture(tmp_path / "s").images.numpy() * 65535).astype(np.uint16)
        np.testing.assert_array_equal(back, codes(16))

@pytest.fixture
def sample_folder(tmp_path):
    write_capture(
        tmp_path / "s", codes(16), directional(), pixel_pitch_mm=0.025, dark=codes(16, 1, 1)[0], mask=np.ones((H, W))
    )
    return tmp_path / "s"


def _edit(folder, **changes):
    path = folder / "capture.json"
    manifest = json.loads(path.read_text())
    for key, value in changes.items():
        if value is _DELETE:
            del manifest[key]
        else:
            manifest[key] = value
    path.write_text(json.dumps(manifest))


_DELETE = object()


class TestReadErrors:
    def test_not_a_capture(self, tmp_path):
        with pytest.raises(DataFormatError, match="capture.json is missing"):
            read_capture(tmp_path)

    @pytest.mark.parametrize("text", ["{", '{"format": "psmini-capture",}', "", "[1, 2"])
    def test_corrupt_json_names_path_and_reason(self, sample_folder, text):
        (sample_folder / "capture.json").write_text(text)
        with pytest.raises(DataFormatError, match=r"capture\.json is not valid JSON: .*line 1 column"):
            read_capture(sample_folder)

    def test_not_utf8(self, sample_folder):
        (sample_folder / "capture.json").write_bytes(b"\xff\xfe{")
        with pytest.raises(DataFormatError, match="not UTF-8"):
            read_capture(sample_folder)

    def test_not_an_object(self, sample_folder):
        (sample_folder / "capture.json").write_text("[]")
        with pytest.raises(DataFormatError, match="JSON object, got list"):
            read_capture(sample_folder)

    @pytest.mark.parametrize(
        ("changes", "message"),
        [
            ({"format": "other"}, "format must be 'psmini-capture'"),
            ({"version": 2}, "version 2 is newer than this psmini reads"),
            ({"version": "1"}, "version must be a positive integer"),
            ({"version": 0}, "version must be a positive integer"),
            ({"kind": "video"}, "kind must be one of"),
            ({"images": []}, "non-empty list"),
            ({"images": ["/abs/led.png"] * K}, "relative to the folder"),
            ({"images": ["led_00.png"] * (K - 1)}, "7 images but the light model has 8 lights"),
            ({"lights": None}, "lights must be a light model"),
            ({"lights": {"model": "spot", "directions": [[0, 0, 1]] * K}}, "light model must be one of"),
            ({"lights": {"model": ["directional"], "directions": [[0, 0, 1]] * K}}, "light model must be one of"),
            ({"bit_depth": 14}, "bit_depth must be one of"),
            ({"pixel_pitch_mm": -1}, "pixel_pitch_mm must be a positive number"),
            ({"pixel_pitch_mm": _DELETE}, "pixel_pitch_mm must be a positive number"),
            ({"crop": [1, 2, 3]}, "crop must be"),
            ({"metadata": []}, "metadata must be a JSON object"),
            ({"kind": "flatfield"}, "card_albedo"),
            ({"kind": "focus", "lights": None}, "positions_mm"),
            ({"flatfield": "../card"}, "flatfield must be null or"),
            ({"flatfield": {"path": "../card", "albedo": -1}}, "albedo must be a positive"),
            ({"gt": {"height": "gt/h.npy"}}, "unknown ground-truth entry"),
            ({"gt": {"normals": "gt/normals.npy"}}, "ground truth normals file 'gt/normals.npy' does not exist"),
            ({"dark": "none.png"}, "dark frame file 'none.png' does not exist"),
            ({"mask": "none.png"}, "mask file 'none.png' does not exist"),
        ],
    )
    def test_bad_manifest(self, sample_folder, changes, message):
        _edit(sample_folder, **changes)
        with pytest.raises(DataFormatError, match=message) as error:
            read_capture(sample_folder)
        assert "capture.json" in str(error.value) or "does not exist" in str(error.value)

    def test_missing_image(self, sample_folder):
        (sample_folder / "led_05.png").unlink()
        with pytest.raises(DataFormatError, match="image file 'led_05.png' does not exist"):
            read_capture(sample_folder)

    def test_image_of_other_size(self, sample_folder):
        write_image(sample_folder / "led_02.png", np.zeros((H, W + 2), np.uint16))
        with pytest.raises(DataFormatError, match=r"led_02\.png is 9x6 \(WxH\) but .*led_00\.png is 7x6"):
            read_capture(sample_folder)

    def test_image_of_other_bit_depth(self, sample_folder):
        write_image(sample_folder / "led_04.png", np.zeros((H, W), np.uint8))
        with pytest.raises(DataFormatError, match=r"led_04\.png is 8-bit but .*led_00\.png is 16-bit"):
            read_capture(sample_folder)

    def test_files_of_wrong_depth_for_the_manifest(self, sample_folder):
        _edit(sample_folder, bit_depth=8)
        with pytest.raises(DataFormatError, match="16-bit; expected 8-bit"):
            read_capture(sample_folder)

    def test_12_bit_codes_out_of_range(self, tmp_path):
        write_capture(tmp_path / "s", codes(12), directional(), pixel_pitch_mm=0.025, bit_depth=12)
        write_image(tmp_path / "s" / "led_01.png", np.full((H, W), 5000, np.uint16))
        with pytest.raises(DataFormatError, match="led_01.png holds values above 4095"):
            read_capture(tmp_path / "s")

    def test_dark_of_other_size_and_depth(self, sample_folder):
        write_image(sample_folder / "dark.png", np.zeros((H + 1, W), np.uint16))
        with pytest.raises(DataFormatError, match="dark frame 'dark.png' is 7x7"):
            read_capture(sample_folder)
        write_image(sample_folder / "dark.png", np.zeros((H, W), np.uint8))
        with pytest.raises(DataFormatError, match="dark frame 'dark.png' is 8-bit but the images are 16-bit"):
            read_capture(sample_folder)

    def test_mask_of_other_size(self, sample_folder):
        write_image(sample_folder / "mask.png", np.zeros((2, 2), np.uint8))
        with pytest.raises(DataFormatError, match="mask 'mask.png' is 2x2"):
            read_capture(sample_folder)

    def test_ground_truth_of_wrong_shape_or_corrupt(self, tmp_path):
        write_capture(tmp_path / "s", codes(16), directional(), pixel_pitch_mm=0.025, gt={"depth": np.zeros((H, W))})
        np.save(tmp_path / "s" / "gt" / "depth.npy", np.zeros((H, W + 1)))
        with pytest.raises(DataFormatError, match=r"must have shape \(6, 7\), got \(6, 8\)"):
            read_capture(tmp_path / "s")
        (tmp_path / "s" / "gt" / "depth.npy").write_bytes(b"garbage")
        with pytest.raises(DataFormatError, match="cannot read ground truth"):
            read_capture(tmp_path / "s")

    def test_empty_ground_truth_file_names_it(self, tmp_path):
        """A zero-byte .npy (a copy cut off) made numpy raise EOFError, which is no psmini error: a traceback from
        the CLI, and a batch run that ended at that sample."""
        write_capture(tmp_path / "s", codes(16), directional(), pixel_pitch_mm=0.025, gt={"depth": np.zeros((H, W))})
        (tmp_path / "s" / "gt" / "depth.npy").write_bytes(b"")
        with pytest.raises(DataFormatError, match=r"capture\.json: cannot read ground truth .*depth\.npy: the file is "
                           "empty or cut short"):
            read_capture(tmp_path / "s")
        assert read_capture(tmp_path / "s", ground_truth=False).gt == {}

    def test_flatfield_reference_missing(self, sample_folder):
        _edit(sample_folder, flatfield={"path": "../card"})
        with pytest.raises(DataFormatError, match="flatfield reference '../card' is not a readable capture"):
            read_capture(sample_folder)

    def test_flatfield_reference_of_wrong_kind(self, tmp_path, sample_folder):
        write_capture(tmp_path / "sphere", codes(16), directional(), pixel_pitch_mm=0.025, kind="sphere")
        _edit(sample_folder, flatfield={"path": "../sphere"})
        with pytest.raises(DataFormatError, match="is a 'sphere' capture, not 'flatfield'"):
            read_capture(sample_folder)

    def test_flatfield_albedo_disagrees(self, tmp_path, sample_folder):
        write_capture(
            tmp_path / "card", codes(16), directional(), pixel_pitch_mm=0.025, kind="flatfield", card_albedo=0.8
        )
        _edit(sample_folder, flatfield={"path": "../card", "albedo": 0.5})
        with pytest.raises(DataFormatError, match="albedo 0.5 disagrees with card_albedo 0.8"):
            read_capture(sample_folder)
