"""Shape from focus on synthetic stacks of known depth (data_synth.focus_stacks), its command, and the stacks."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from data_synth.focus_stacks import SHAPES, focus_stack_of, render_focus_stack, shape_height, texture_image
from psmini.errors import InputError, ShapeError
from psmini.sff import SFFConfig, depth_from_focus


def rms_steps(result, stack) -> float:
    return float((result.depth - stack.best_position_mm).square().mean().sqrt()) / stack.step_mm


@pytest.fixture(scope="module")
def stacks():
    return {shape: focus_stack_of(shape, size=64, frames=13, seed=3) for shape in ("tilted_plane", "sphere_cap")}


class TestDepth:
    @pytest.mark.parametrize("shape", ["tilted_plane", "sphere_cap"])
    @pytest.mark.parametrize("measure", ["LAPM", "TENG", "GLVA"])
    def test_within_one_step_rms(self, stacks, shape, measure):
        stack = stacks[shape]
        result = depth_from_focus(stack.frames, stack.positions_mm, measure, window=9)
        assert rms_steps(result, stack) < 1.0
        # heights back from positions: focal plane - position
        height = result.surface_height(stack.focal_plane_mm)
        assert float((height - stack.height_mm).square().mean().sqrt()) < stack.step_mm

    def test_interpolation_beats_sampling(self, stacks):
        stack = stacks["sphere_cap"]
        errors = {m: rms_steps(depth_from_focus(stack.frames, stack.positions_mm, "LAPM", 9, SFFConfig(m)), stack)
                  for m in ("gaussian", "parabola", "none")}
        assert errors["gaussian"] < 0.7 * errors["none"] and errors["parabola"] < 0.7 * errors["none"], errors
        assert 0.2 < errors["none"] < 0.6  # sampling alone: about a uniform error over a step, 1/√12

    def test_uint8_stack_and_descending_positions(self, stacks):
        stack = stacks["tilted_plane"]
        raw = (stack.frames * 255).round().to(torch.uint8)
        result = depth_from_focus(raw.flip(0), stack.positions_mm.flip(0), "LAPM", 9)
        assert rms_steps(result, stack) < 1.0 and result.depth.dtype == torch.float64

    def test_reliability_marks_textureless_regions(self):
        size = 64
        u = torch.linspace(-1, 1, size)
        flat = (u[None].square() + u[:, None].square()) < 0.35**2  # a textureless disc in the middle
        height = shape_height("tilted_plane", size, 1.0)
        positions = torch.linspace(-0.2, 1.2, 15)
        stack = render_focus_stack(texture_image(size, 4), height, positions, focal_plane_mm=1.0, blur_per_mm=6.0,
                                   noise=0.005, seed=4, flat=flat)
        result = depth_from_focus(stack.frames, stack.positions_mm, "LAPM", 9)
        inside = result.reliability[flat]
        core = (u[None].square() + u[:, None].square()) < 0.2**2  # away from the disc's textured rim
        far = (u[None].square() + u[:, None].square()) > 0.6**2
        assert float(result.reliability[core].median()) < 0.35 < 0.6 < float(result.reliability[far].median())
        assert float(inside.mean()) < float(result.reliability[far].mean())
        # noise-free and textureless: flat focus curves, reliability 0
        clean = render_focus_stack(torch.full((16, 16), 0.5), torch.zeros(16, 16), [0.0, 0.1, 0.2, 0.3])
        assert float(depth_from_focus(clean.frames, clean.positions_mm, "TENG", 5).reliability.max()) == 0.0

    def test_aggregation_removes_outliers(self):
        stack = focus_stack_of("sphere_cap", size=64, frames=13, seed=5, noise=0.03)
        plain = depth_from_focus(stack.frames, stack.positions_mm, "LAPM", 5)
        median = depth_from_focus(stack.frames, stack.positions_mm, "LAPM", 5, SFFConfig(aggregation=5))
        assert rms_steps(median, stack) < rms_steps(plain, stack)

    def test_operator_parameters(self, stacks):
        stack = stacks["tilted_plane"]
        result = depth_from_focus(stack.frames, stack.positions_mm, "GDER", 9, SFFConfig(params=(("sigma", 1.5),)))
        assert rms_steps(result, stack) < 1.0


class TestErrors:
    def test_errors(self):
        frames = torch.rand(5, 16, 16)
        with pytest.raises(InputError, match="same length"):
            depth_from_focus(frames, [0, 1, 2], "TENG")
        with pytest.raises(InputError, match="monotonic"):
            depth_from_focus(frames, [0, 1, 1, 2, 3], "TENG")
        with pytest.raises(ShapeError, match="N ≥ 3"):
            depth_from_focus(frames[:2], [0, 1], "TENG")
        with pytest.raises(InputError, match="interpolation"):
            depth_from_focus(frames, range(5), "TENG", 5, SFFConfig(interpolation="cubic"))
        with pytest.raises(InputError, match="aggregation"):
            depth_from_focus(frames, range(5), "TENG", 5, SFFConfig(aggregation=4))
        with pytest.raises(InputError, match="larger than"):
            depth_from_focus(frames, range(5), "TENG", 5, SFFConfig(aggregation=17))
        with pytest.raises(InputError, match="torch.Tensor"):
            depth_from_focus(frames.numpy(), range(5), "TENG")
        with pytest.raises(InputError, match="unknown focus measure"):
            depth_from_focus(frames, range(5), "sharpness")

    def test_positions_not_numbers_raise(self):
        frames = torch.rand(5, 16, 16)
        # None failed as a bare TypeError of torch ("must be real number, not NoneType")
        with pytest.raises(InputError, match="positions must be a sequence or a 1-D tensor of the 5 frames' positions "
                                             "\\(numbers\\), got NoneType"):
            depth_from_focus(frames, None)
        with pytest.raises(InputError, match="got list"):
            depth_from_focus(frames, ["0", "a", "2", "3", "4"])

    def test_stack_errors(self):
        with pytest.raises(InputError, match="shape must be one of"):
            shape_height("torus", 8)
        with pytest.raises(InputError, match="surface must be one of"):
            focus_stack_of("torus")
        with pytest.raises(InputError, match="one size"):
            render_focus_stack(torch.rand(8, 8), torch.zeros(9, 9), [0.0])
        with pytest.raises(InputError, match="contrast"):
            render_focus_stack(torch.rand(8, 8), torch.zeros(8, 8), [0.0], contrast=0.0)
        with pytest.raises(InputError, match="scale_px"):
            texture_image(8, scale_px=0)


class TestStacks:
    @pytest.mark.parametrize("shape", SHAPES)
    def test_shapes(self, shape):
        height = shape_height(shape, 33, 2.0)
        assert float(height.min()) >= 0 and float(height.max()) == pytest.approx(2.0 if shape != "plane" else 1.0)
        assert torch.allclose(height, height.flip(-1).flip(-2)) or shape == "tilted_plane"

    def test_conditions(self):
        base = focus_stack_of("plane", size=32, frames=5)
        dim = focus_stack_of("plane", size=32, frames=5, contrast=0.5)
        assert float(dim.frames.std()) == pytest.approx(0.5 * float(base.frames.std()), rel=0.02)
        saturated = focus_stack_of("plane", size=32, frames=5, gain=1.8)
        assert float((saturated.frames == 1).double().mean()) > 0.05
        noisy = focus_stack_of("plane", size=32, frames=5, noise=0.05)
        assert float((noisy.frames - base.frames).std()) == pytest.approx(0.05, rel=0.1)

    def test_fabric_stack(self):
        stack = focus_stack_of("twill", size=48, frames=9)
        assert stack.frames.shape == (9, 48, 48) and stack.height_mm.shape == (48, 48)
        assert torch.allclose(stack.best_position_mm, stack.focal_plane_mm - stack.height_mm)


class TestCommand:
    def run(self, capsys, *argv):
        from psmini.cli import main

        status = main([*map(str, argv)])
        out, err = capsys.readouterr()
        return status, out, err

    def write_folder(self, folder, stack):
        import cv2

        folder.mkdir()
        names = []
        for i, frame in enumerate(stack.frames.numpy()):
            names.append(f"z{i:02d}.png")
            cv2.imwrite(str(folder / names[-1]), (frame * 255).round().astype(np.uint8))
        (folder / "capture.json").write_text(json.dumps({
            "format": "psmini-capture", "version": 1, "kind": "focus", "images": names, "dark": None, "mask": None,
            "bit_depth": 8, "pixel_pitch_mm": 0.025, "lights": None, "positions_mm": stack.positions_mm.tolist()}))

    def test_folder_with_manifest(self, tmp_path, capsys):
        stack = focus_stack_of("tilted_plane", size=48, frames=11, seed=1)
        self.write_folder(tmp_path / "sweep", stack)
        status, out, _ = self.run(capsys, "sff", tmp_path / "sweep", "--out", tmp_path / "h.npy", "--focal-plane",
                                  stack.focal_plane_mm, "--reliability", tmp_path / "r.npy", "--json")
        assert status == 0, out
        height = np.load(tmp_path / "h.npy")
        assert height.shape == (48, 48) and np.load(tmp_path / "r.npy").shape == (48, 48)
        assert np.sqrt(((height - stack.height_mm.numpy()) ** 2).mean()) < stack.step_mm
        assert json.loads(out.strip().splitlines()[-1])["kind"] == "height"

    def test_npy_positions_and_errors(self, tmp_path, capsys):
        stack = focus_stack_of("sphere_cap", size=32, frames=7)
        np.save(tmp_path / "s.npy", stack.frames.numpy())
        status, out, _ = self.run(capsys, "sff", tmp_path / "s.npy", "--out", tmp_path / "d.npy", "--positions", "0:1",
                                  "--metric", "teng", "--median", "3")
        assert status == 0 and "7 frames" in out
        depth = np.load(tmp_path / "d.npy")
        assert depth.min() >= 0 and depth.max() <= 6
        status, _, err = self.run(capsys, "sff", tmp_path / "s.npy", "--out", tmp_path / "d.npy", "--positions", "1,2")
        assert status == 1 and "2 positions for 7 frames" in err
        status, _, err = self.run(capsys, "sff", tmp_path / "missing.npy", "--out", tmp_path / "d.npy")
        assert status == 1 and "does not exist" in err
        np.save(tmp_path / "flat.npy", np.zeros((4, 4)))
        status, _, err = self.run(capsys, "sff", tmp_path / "flat.npy", "--out", tmp_path / "d.npy")
        assert status == 1 and "(N, H, W)" in err

    def test_focus_metric_all(self, tmp_path, capsys):
        stack = focus_stack_of("plane", size=48, frames=7, margin_steps=2, seed=2)
        self.write_folder(tmp_path / "sweep", stack)
        status, out, _ = self.run(capsys, "focus", tmp_path / "sweep", "--metric", "all", "--json")
        assert status == 0
        payload = json.loads(out.strip().splitlines()[-1])
        assert len(payload["operators"]) == 28 and payload["consensus_index"] == stack.sharpest_frame
        assert "LAPD" in out and "operators pick index" in out
        status, out, _ = self.run(capsys, "focus", tmp_path / "sweep", "--metric", "LAPM")
        assert status == 0 and f"best index {stack.sharpest_frame}" in out


def test_docstring_examples():
    import doctest

    import data_synth.focus_stacks
    import psmini.sff

    for module in (psmini.sff, data_synth.focus_stacks):
        assert doctest.testmod(module, raise_on_error=False).failed == 0, module.__name__


def test_rig_full_sweep_keeps_every_frame_for_sff(tmp_path, capsys):
    """The rig's focus sweep with full_sweep=True writes every position's frame; psmini sff reads that folder."""
    from data_synth.rig import RigConfig
    from data_synth.simulated_rig import SimulatedRig
    from psmini.cli import main
    from psmini.io import read_capture
    from psmini.rig import CaptureSession
    from tests.rig.test_session import open_rig

    with SimulatedRig("jute", 0, 32, pixel_pitch_mm=0.1, config=RigConfig(shadows=False)) as rig:
        leds, camera = open_rig(rig)
        with leds, camera:
            session = CaptureSession(leds, camera, rig.lights, pixel_pitch_mm=0.1)
            positions = [round(-1.2 + 0.2 * i, 2) for i in range(11)]
            result = session.focus_sweep(rig.move_to, positions, folder=tmp_path / "focus", full_sweep=True)
    assert result.positions == positions and not result.stopped_by_rule
    assert read_capture(tmp_path / "focus").positions_mm == positions
    assert main(["sff", str(tmp_path / "focus"), "--out", str(tmp_path / "d.npy"), "--window", "5"]) == 0
    depth = np.load(tmp_path / "d.npy")
    assert depth.shape == (32, 32) and depth.min() >= -1.2 and depth.max() <= 0.8
    assert "position of best focus" in capsys.readouterr().out
