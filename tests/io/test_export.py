"""Exports: PNG encodings read back, depth preview decoding, PLY read back with plyfile, atomic write_outputs."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest
import torch
from plyfile import PlyData

from psmini import DataFormatError, InputError, ShapeError
from psmini.geometry import depth_to_points
from psmini.io import export as export_module
from psmini.io.export import (
    read_normal_png,
    robust_max,
    save_albedo_png,
    save_depth,
    save_mesh_ply,
    save_normal_png,
    save_normal_std,
    save_ply,
    write_outputs,
)
from psmini.io.images import read_image, read_image_raw

H, W = 6, 8


def sphere_normals() -> torch.Tensor:
    y, x = torch.meshgrid(torch.linspace(0.7, -0.7, H), torch.linspace(-0.7, 0.7, W), indexing="ij")
    z = (1 - x**2 - y**2).clamp_min(0.01).sqrt()
    n = torch.stack([x, y, z])
    return n / n.norm(dim=0, keepdim=True)


class TestAlbedo:
    def test_scaled_by_robust_max(self, tmp_path):
        albedo = torch.linspace(0, 1, H * W).reshape(1, 1, H, W)
        albedo[0, 0, 0, 0] = 50.0  # one outlier must not darken the picture
        scale = save_albedo_png(tmp_path / "a.png", albedo)
        expected_scale = float(np.percentile(albedo.numpy(), 99.5))
        assert scale == pytest.approx(expected_scale)
        raw, bits = read_image_raw(tmp_path / "a.png")
        assert bits == 8 and raw.shape == (H, W)
        np.testing.assert_array_equal(raw, np.rint(np.clip(albedo[0, 0].numpy() / scale, 0, 1) * 255).astype(np.uint8))

    def test_mask_blacks_out_and_ignores_nan_outside(self, tmp_path):
        albedo = torch.full((1, H, W), 0.4)
        albedo[0, :, 0] = float("nan")
        mask = torch.ones(1, 1, H, W, dtype=torch.bool)
        mask[..., 0] = False
        save_albedo_png(tmp_path / "a.png", albedo, mask)
        raw, _ = read_image_raw(tmp_path / "a.png")
        assert (raw[:, 0] == 0).all() and (raw[:, 1:] == 255).all()

    def test_nan_inside_mask_raises(self, tmp_path):
        albedo = torch.full((H, W), 0.4)
        albedo[2, 2] = float("nan")
        with pytest.raises(InputError, match="1 NaN or infinite value"):
            save_albedo_png(tmp_path / "a.png", albedo)

    def test_bad_shape(self, tmp_path):
        with pytest.raises(ShapeError, match=r"albedo must have shape \(1, 1, H, W\)"):
            save_albedo_png(tmp_path / "a.png", torch.rand(2, 1, H, W))

    def test_robust_max(self):
        assert robust_max(np.arange(1001.0)) == pytest.approx(995.0)
        assert robust_max(np.zeros(5)) == 1.0
        with pytest.raises(InputError, match="percentile"):
            robust_max(np.ones(3), percentile=0)


class TestNormals:
    @pytest.mark.parametrize("bits", [8, 16])
    def test_encoding_read_back(self, tmp_path, bits):
        normals = sphere_normals()
        save_normal_png(tmp_path / "n.png", normals[None], bit_depth=bits)
        image, read_bits = read_image(tmp_path / "n.png")  # RGB order
        assert read_bits == bits
        decoded = torch.from_numpy(image.transpose(2, 0, 1)).double() * 2 - 1
        torch.testing.assert_close(decoded, normals.double(), rtol=0, atol=1.0 / (2**bits - 1) + 1e-6)

    def test_flat_surface_is_the_usual_blue_and_stored_bgr(self, tmp_path):
        flat = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, H, W)
        save_normal_png(tmp_path / "n.png", flat)
        bgr = cv2.imread(str(tmp_path / "n.png"), cv2.IMREAD_UNCHANGED)
        # B = n_z on disk in OpenCV's order: viewers show RGB (128,128,255)
        assert bgr[0, 0].tolist() == [255, 128, 128]

    def test_right_facing_is_red(self, tmp_path):
        right = torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1).expand(3, H, W)
        save_normal_png(tmp_path / "n.png", right)
        raw, _ = read_image_raw(tmp_path / "n.png")
        assert raw[0, 0].tolist() == [255, 128, 128]

    def test_outside_mask_is_black(self, tmp_path):
        mask = torch.zeros(H, W, dtype=torch.bool)
        save_normal_png(tmp_path / "n.png", sphere_normals(), mask)
        assert (read_image_raw(tmp_path / "n.png")[0] == 0).all()

    @pytest.mark.parametrize("bits", [8, 16])
    def test_read_normal_png_round_trip(self, tmp_path, bits):
        """read_normal_png inverts save_normal_png to the file's rounding (0.3 deg at 8 bits), NaN outside the mask."""
        normals = sphere_normals()
        mask = torch.ones(H, W, dtype=torch.bool)
        mask[:3] = False
        save_normal_png(tmp_path / "n.png", normals, mask, bit_depth=bits)
        read = torch.from_numpy(read_normal_png(tmp_path / "n.png")).double()
        assert read.shape == (3, H, W) and torch.isnan(read[:, :3]).all()
        sine = torch.linalg.cross(read[:, 3:], normals[:, 3:].double(), dim=0).norm(dim=0)  # exact near 0, unlike acos
        limit = 0.3 if bits == 8 else 0.002
        assert float(torch.rad2deg(torch.asin(sine)).max()) < limit
        torch.testing.assert_close(read[:, 3:].norm(dim=0), torch.ones(H - 3, W, dtype=torch.float64))

    def test_read_normal_png_errors(self, tmp_path):
        with pytest.raises(DataFormatError, match="does not exist"):
            read_normal_png(tmp_path / "missing.png")
        cv2.imwrite(str(tmp_path / "gray.png"), np.zeros((4, 4), np.uint8))
        with pytest.raises(DataFormatError, match=r"normals must be an RGB image, got shape \(4, 4\)"):
            read_normal_png(tmp_path / "gray.png")
        (tmp_path / "bad.png").write_bytes(b"not a png")
        with pytest.raises(DataFormatError, match="cannot decode"):
            read_normal_png(tmp_path / "bad.png")

    def test_errors(self, tmp_path):
        with pytest.raises(InputError, match="bit_depth must be 8 or 16"):
            save_normal_png(tmp_path / "n.png", sphere_normals(), bit_depth=12)
        with pytest.raises(ShapeError, match=r"normals must have shape \(1, 3, H, W\) or \(3, H, W\)"):
            save_normal_png(tmp_path / "n.png", torch.rand(H, W))
        with pytest.raises(ShapeError, match="mask must be"):
            save_normal_png(tmp_path / "n.png", sphere_normals(), torch.ones(H + 1, W))


class TestDepth:
    def test_npy_preview_and_sidecar(self, tmp_path):
        depth = torch.linspace(-1.0, 3.0, H * W, dtype=torch.float64).reshape(1, 1, H, W)
        mask = torch.ones(1, 1, H, W, dtype=torch.bool)
        mask[..., 0, :] = False
        paths = save_depth(tmp_path / "depth.npy", depth, mask, pixel_pitch_mm=0.025)
        assert [p.name for p in paths] == ["depth.npy", "depth.png", "depth.json"]
        exact = np.load(tmp_path / "depth.npy")
        assert exact.dtype == np.float32 and np.isnan(exact[0]).all()
        np.testing.assert_array_equal(exact[1:], depth[0, 0, 1:].numpy().astype(np.float32))
        sidecar = json.loads((tmp_path / "depth.json").read_text())
        assert sidecar["units"] == "mm" and sidecar["min"] == pytest.approx(float(depth[0, 0, 1, 0]))
        inside = depth[0, 0, 1:].numpy()
        assert sidecar["preview_limits"] == pytest.approx(np.percentile(inside, [1, 99]).tolist())
        preview, bits = read_image_raw(tmp_path / "depth.png")
        assert bits == 8 and preview.ndim == 3 and preview.shape[1] >= 320  # RGB, enlarged to be seen

    def test_preview_colours_unsolved_pixels_and_outliers(self, tmp_path):
        """Height reads as viridis (dark low, yellow high); unsolved pixels are hatched, not black; 1% of far
        outliers does not set the colour scale."""
        size = 100
        rows = np.arange(size, dtype=np.float64)[:, None].repeat(size, 1)
        depth = 0.5 * rows / (size - 1)  # a ramp from 0 (top) to 0.5 mm (bottom)
        depth[0, :50] = -2.5  # 50 outliers, 0.5% of the pixels
        mask = np.ones((size, size), bool)
        mask[40:60, 40:60] = False  # an unsolved hole
        save_depth(tmp_path / "d.npy", depth, mask, pixel_pitch_mm=0.025)
        limits = json.loads((tmp_path / "d.json").read_text())["preview_limits"]
        assert limits[0] > -0.01 and limits[1] == pytest.approx(0.5, abs=0.01)
        picture = cv2.imread(str(tmp_path / "d.png"))[..., ::-1]
        scale = picture.shape[1] // size
        relief = picture[: size * scale].reshape(size, scale, size, scale, 3).mean(axis=(1, 3))
        low_row, high_row = relief[5:15, 70:95].mean(axis=(0, 1)), relief[85:92, 70:95].mean(axis=(0, 1))
        assert low_row[2] > low_row[1] and high_row[1] > high_row[2] and high_row[0] > 2 * low_row[0] - 60
        hole = picture[45 * scale : 55 * scale, 45 * scale : 55 * scale].reshape(-1, 3)
        gray = np.abs(hole.astype(int) - hole[:, :1]).max(axis=1) <= 2  # no hue: gray or white
        assert gray.all() and hole.min() >= 190  # light, never black

    def test_flat_depth(self, tmp_path):
        save_depth(tmp_path / "d.npy", torch.full((H, W), 2.0))
        sidecar = json.loads((tmp_path / "d.json").read_text())
        assert (
            sidecar["min"] == sidecar["max"] == 2.0
            and sidecar["preview_limits"][0] < 2.0 < sidecar["preview_limits"][1]
        )

    def test_errors(self, tmp_path):
        with pytest.raises(InputError, match="mask is empty"):
            save_depth(tmp_path / "d.npy", torch.zeros(H, W), torch.zeros(H, W))
        with pytest.raises(InputError, match="NaN"):
            save_depth(tmp_path / "d.npy", torch.full((H, W), float("inf")))
        with pytest.raises(DataFormatError, match="cannot write"):
            save_depth(tmp_path / "none" / "d.npy", torch.zeros(H, W))


class TestPly:
    def test_points_and_albedo_read_back(self, tmp_path):
        points = torch.randn(50, 3, dtype=torch.float64)
        albedo = torch.linspace(0, 1, 50)
        keep = torch.arange(50) % 3 != 0
        count = save_ply(tmp_path / "p.ply", points, albedo, keep)
        ply = PlyData.read(str(tmp_path / "p.ply"))
        assert count == int(keep.sum()) and ply.elements[0].count == count
        assert not ply.text and ply.byte_order == "<"
        vertex = ply["vertex"]
        back = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1)
        assert vertex["x"].dtype == np.float32 and vertex["red"].dtype == np.uint8
        np.testing.assert_array_equal(back, points[keep].numpy().astype(np.float32))
        expected = np.rint(np.clip(albedo[keep].numpy() / robust_max(albedo[keep].numpy()), 0, 1) * 255)
        np.testing.assert_array_equal(vertex["red"], expected.astype(np.uint8))
        np.testing.assert_array_equal(vertex["red"], vertex["blue"])

    def test_point_image_and_rgb(self, tmp_path):
        points = depth_to_points(torch.rand(1, 1, H, W), 0.025)
        colours = torch.randint(0, 256, (H * W, 3), dtype=torch.uint8)
        save_ply(tmp_path / "p.ply", points, colours)
        vertex = PlyData.read(str(tmp_path / "p.ply"))["vertex"]
        np.testing.assert_array_equal(vertex["z"], points[0, 2].reshape(-1).numpy())
        np.testing.assert_array_equal(vertex["y"], points[0, 1].reshape(-1).numpy())  # row-major order
        np.testing.assert_array_equal(np.stack([vertex["red"], vertex["green"], vertex["blue"]], 1), colours.numpy())

    def test_without_colours(self, tmp_path):
        save_ply(tmp_path / "p.ply", np.zeros((3, 3)))
        assert [p.name for p in PlyData.read(str(tmp_path / "p.ply"))["vertex"].properties] == ["x", "y", "z"]

    def test_errors(self, tmp_path):
        with pytest.raises(ShapeError, match="3 coordinates"):
            save_ply(tmp_path / "p.ply", torch.zeros(5, 2))
        with pytest.raises(ShapeError, match="colors must give 5 rows"):
            save_ply(tmp_path / "p.ply", torch.zeros(5, 3), torch.zeros(4))
        with pytest.raises(ShapeError, match="1 \\(albedo\\) or 3 \\(RGB\\)"):
            save_ply(tmp_path / "p.ply", torch.zeros(5, 3), torch.zeros(5, 2))
        points = torch.zeros(5, 3)
        points[1, 2] = float("nan")
        with pytest.raises(InputError, match="points holds 1 NaN"):
            save_ply(tmp_path / "p.ply", points)
        save_ply(tmp_path / "p.ply", points, mask=torch.tensor([1, 0, 1, 1, 1]))  # masked out: fine
        with pytest.raises(InputError, match="torch.Tensor or numpy"):
            save_ply(tmp_path / "p.ply", [[0.0, 0.0, 0.0]])
        with pytest.raises(DataFormatError, match="cannot write"):
            save_ply(tmp_path / "none" / "p.ply", torch.zeros(5, 3))


def reconstruction(batched: bool = True) -> dict[str, torch.Tensor]:
    depth = torch.rand(1, 1, H, W) * 0.3
    mask = torch.ones(1, 1, H, W, dtype=torch.bool)
    mask[..., 0, 0] = False
    depth[..., 0, 0] = float("nan")
    result = {"albedo": torch.rand(1, 1, H, W), "normals": sphere_normals()[None], "depth": depth, "mask": mask}
    return result if batched else {key: value[0] for key, value in result.items()}


class TestWriteOutputs:
    @pytest.mark.parametrize("batched", [True, False])
    def test_writes_every_file(self, tmp_path, batched):
        result = reconstruction(batched)
        written = write_outputs(tmp_path / "out", result, pixel_pitch_mm=0.025, metadata={"sample": "denim"})
        names = ["albedo.png", "normals.png", "depth.npy", "depth.png", "depth.json", "points.ply", "mesh.ply",
                 "outputs.json"]
        assert [p.name for p in written] == names and all(p.is_file() for p in written)
        assert sorted(os.listdir(tmp_path)) == ["out"]
        summary = json.loads((tmp_path / "out" / "outputs.json").read_text())
        assert summary["vertices"] == H * W - 1 and summary["pixel_pitch_mm"] == 0.025
        assert summary["files"] == names[:-1] and summary["metadata"] == {"sample": "denim"}
        vertex = PlyData.read(str(tmp_path / "out" / "points.ply"))["vertex"]
        depth = result["depth"].reshape(1, 1, H, W).double()
        expected = depth_to_points(depth, 0.025)[0].reshape(3, -1)[:, 1:].T.numpy().astype(np.float32)
        np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), expected)

    def test_reconstruction_object_from_the_pipeline(self, tmp_path):
        from psmini.pipeline import Reconstruction

        result = reconstruction()
        rec = Reconstruction(
            result["albedo"], result["normals"], result["depth"], result["depth"], result["depth"], result["mask"]
        )
        write_outputs(tmp_path / "out", rec)
        assert json.loads((tmp_path / "out" / "depth.json").read_text())["units"] == "pixels"

    def test_near_light_normal_std(self, tmp_path):
        """A result with near light's ``normal_std`` adds normal_std.npy (degrees, NaN outside the mask) and
        normal_std.png (0 at 0° to 255 at 10° or more, 0 outside), and its median in outputs.json."""
        result = reconstruct_result = reconstruction()
        std = torch.full((1, 1, H, W), 1.0)
        std[..., 2, 3], std[..., 4, 5] = 5.0, 20.0
        written = write_outputs(tmp_path / "out", result | {"normal_std": std})
        assert [p.name for p in written][-3:] == ["normal_std.npy", "normal_std.png", "outputs.json"]
        values = np.load(tmp_path / "out" / "normal_std.npy")
        inside = reconstruct_result["mask"][0, 0].numpy()
        assert np.isnan(values[~inside]).all() and values[2, 3] == 5.0 and values[4, 5] == 20.0
        pixels, bits = read_image_raw(tmp_path / "out" / "normal_std.png")
        assert bits == 8 and pixels[2, 3] == 128 and pixels[4, 5] == 255 and pixels[1, 1] == 26
        assert (pixels[~inside] == 0).all()
        summary = json.loads((tmp_path / "out" / "outputs.json").read_text())
        assert summary["normal_std_median_deg"] == 1.0 and summary["normal_std_png_max_deg"] == 10.0
        assert "normal_std.npy" in summary["files"]
        write_outputs(tmp_path / "plain", result)
        plain = json.loads((tmp_path / "plain" / "outputs.json").read_text())
        assert "normal_std_median_deg" not in plain and "normal_std.png" not in plain["files"]

    def test_save_normal_std(self, tmp_path):
        std = torch.tensor([[0.5, 12.0], [3.0, 1.0]])
        summary = save_normal_std(tmp_path / "s.npy", std, torch.tensor([[True, True], [False, True]]))
        assert summary == {"normal_std_median_deg": 1.0, "normal_std_png_max_deg": 10.0}
        np.testing.assert_array_equal(read_image_raw(tmp_path / "s.png")[0], [[13, 255], [0, 26]])
        assert save_normal_std(tmp_path / "e.npy", std, torch.zeros(2, 2, dtype=torch.bool))[
            "normal_std_median_deg"] is None
        with pytest.raises(ShapeError, match="mask must be 2x2"):
            save_normal_std(tmp_path / "h.npy", std, torch.ones(2, 3, dtype=torch.bool))
        with pytest.raises(InputError, match="finite and >= 0"):
            save_normal_std(tmp_path / "n.npy", torch.tensor([[-1.0, 0.0], [0.0, 0.0]]))
        with pytest.raises(DataFormatError, match="cannot write"):
            save_normal_std(tmp_path / "none" / "s.npy", std)

    def test_existing_out_dir(self, tmp_path):
        write_outputs(tmp_path / "out", reconstruction())
        with pytest.raises(DataFormatError, match="already exists"):
            write_outputs(tmp_path / "out", reconstruction())
        write_outputs(tmp_path / "out", reconstruction(), overwrite=True)
        assert sorted(os.listdir(tmp_path)) == ["out"]

    def test_failure_mid_write_leaves_nothing(self, tmp_path, monkeypatch):
        def failing_ply(*args, **kwargs):
            raise DataFormatError("disk full (simulated)")

        monkeypatch.setattr(export_module, "save_ply", failing_ply)
        with pytest.raises(DataFormatError, match="simulated"):
            write_outputs(tmp_path / "out", reconstruction())
        assert os.listdir(tmp_path) == []

    def test_errors(self, tmp_path):
        result = reconstruction()
        with pytest.raises(InputError, match="lacks 'normals'"):
            write_outputs(tmp_path / "out", {"albedo": result["albedo"], "depth": result["depth"]})
        with pytest.raises(ShapeError, match="must share one size"):
            write_outputs(tmp_path / "out", result | {"depth": torch.zeros(1, 1, H, W + 1)})
        with pytest.raises(InputError, match="NaN"):
            write_outputs(tmp_path / "out", result | {"mask": None})
        with pytest.raises(InputError, match="serialise"):
            write_outputs(tmp_path / "out", result, metadata={"x": object()})
        with pytest.raises(InputError, match="bit_depth"):
            write_outputs(tmp_path / "out", result, normal_bit_depth=4)
        with pytest.raises(ShapeError, match="normal_std must be 6x8"):
            write_outputs(tmp_path / "out", result | {"normal_std": torch.zeros(1, 1, H + 1, W)})
        assert os.listdir(tmp_path) == []


class TestMesh:
    def test_faces_cover_the_mask_and_face_the_camera(self, tmp_path):
        """A tilted plane with a hole: every cell with four corners inside gives two triangles, three give one;
        every face's normal is the plane's normal (computed here from its slopes), toward the camera."""
        height, width, pitch = 7, 9, 0.025
        rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
        slope_x, slope_y = 0.3, -0.2  # dz/dx and dz/dy (y up = -row)
        depth = torch.from_numpy(slope_x * cols * pitch + slope_y * (-rows) * pitch)[None, None]
        mask = np.ones((height, width), bool)
        mask[3, 4] = False
        points = depth_to_points(depth, pitch)
        albedo = torch.rand(1, 1, height, width, dtype=torch.float64)
        vertices, faces = save_mesh_ply(tmp_path / "mesh.ply", points, albedo, mask)
        # cells: (height-1)*(width-1) = 48; the 4 cells around the hole have 3 corners each -> 1 triangle
        assert vertices == height * width - 1 and faces == 2 * (48 - 4) + 4
        ply = PlyData.read(str(tmp_path / "mesh.ply"))
        xyz = np.stack([ply["vertex"][k] for k in "xyz"], 1).astype(np.float64)
        tri = np.stack(ply["face"]["vertex_indices"]).astype(int)
        assert tri.shape == (faces, 3) and len({tuple(sorted(t)) for t in tri}) == faces
        normal = np.cross(xyz[tri[:, 1]] - xyz[tri[:, 0]], xyz[tri[:, 2]] - xyz[tri[:, 0]])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        expected = np.array([-slope_x, -slope_y, 1.0]) / np.sqrt(slope_x**2 + slope_y**2 + 1)
        np.testing.assert_allclose(normal, np.broadcast_to(expected, normal.shape), atol=1e-5)
        assert {"red", "green", "blue"} <= {p.name for p in ply["vertex"].properties}

    def test_errors(self, tmp_path):
        with pytest.raises(ShapeError, match="points"):
            save_mesh_ply(tmp_path / "m.ply", torch.zeros(2, 4, 4))
        with pytest.raises(InputError, match="NaN"):
            save_mesh_ply(tmp_path / "m.ply", torch.full((3, 4, 4), float("nan")))
        with pytest.raises(DataFormatError, match="cannot write"):
            save_mesh_ply(tmp_path / "none" / "m.ply", torch.zeros(3, 4, 4))
