"""psmini.viz: pictures checked against analytic values and independent implementations written here."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from psmini import viz
from psmini.errors import DataFormatError, InputError, ShapeError
from psmini.result import Reconstruction


class TestArrays:
    def test_normals_to_rgb(self):
        n = torch.nn.functional.normalize(torch.randn(1, 3, 5, 6, dtype=torch.float64), dim=1)
        mask = torch.ones(1, 1, 5, 6, dtype=torch.bool)
        mask[..., 0, 0] = False
        rgb = viz.normals_to_rgb(n, mask, background=0.25)
        expected = (n[0].permute(1, 2, 0).numpy() + 1) / 2
        np.testing.assert_allclose(rgb[1:], expected[1:])
        assert rgb[0, 0].tolist() == [0.25, 0.25, 0.25]
        with pytest.raises(ShapeError, match="normals"):
            viz.normals_to_rgb(torch.zeros(2, 5, 6))
        with pytest.raises(ShapeError, match="mask"):
            viz.normals_to_rgb(n, torch.ones(4, 4))

    @pytest.mark.parametrize("slope", [0.0, 0.5, -1.2])
    def test_hillshade_of_a_tilted_plane(self, slope):
        """z = slope · x: normal (-slope, 0, 1)/√(1 + slope²); light from azimuth 315°, altitude 45°."""
        pitch = 0.1
        cols = np.arange(12) * pitch
        depth = np.tile(slope * cols, (9, 1))
        light = np.array([math.sin(math.radians(315)) * math.cos(math.radians(45)),
                          math.cos(math.radians(315)) * math.cos(math.radians(45)), math.sin(math.radians(45))])
        normal = np.array([-slope, 0.0, 1.0]) / math.sqrt(1 + slope**2)
        np.testing.assert_allclose(viz.hillshade(depth, pitch), max(0.0, normal @ light), atol=1e-12)

    def test_hillshade_lights_the_upper_left_slope(self):
        rows = np.arange(10.0)[:, None] * np.ones((1, 10))
        facing_up = viz.hillshade(rows)  # height grows down the image: the slope's normal leans toward the top
        facing_down = viz.hillshade(-rows)
        assert facing_up.mean() > facing_down.mean()
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            viz.hillshade(rows, 0.0)
        with pytest.raises(InputError, match="altitude"):
            viz.hillshade(rows, altitude_deg=0.0)

    def test_colormap_is_viridis(self):
        matplotlib = pytest.importorskip("matplotlib")
        values = np.linspace(-1.0, 3.0, 300)[None]
        ours = viz.apply_colormap(values, (-1.0, 3.0))[0]
        theirs = matplotlib.colormaps["viridis"](np.linspace(0, 1, 300))[:, :3]
        assert np.abs(ours - theirs).max() < 0.01
        np.testing.assert_allclose(
            viz.apply_colormap(np.array([[-5.0, 9.0]]), (-1.0, 3.0))[0], theirs[[0, -1]], atol=1e-3
        )
        with pytest.raises(InputError, match="increasing"):
            viz.apply_colormap(values, (1.0, 1.0))

    def test_robust_limits_ignore_outliers_and_masked_pixels(self):
        values = np.r_[np.linspace(0.0, 0.5, 990), np.full(5, -2.5), np.full(5, 40.0)]
        low, high = viz.robust_limits(values)
        assert -0.01 < low < 0.02 and 0.48 < high < 0.51
        mask = np.r_[np.zeros(990, bool), np.ones(10, bool)]
        assert viz.robust_limits(values, mask, (0, 100)) == (-2.5, 40.0)
        assert viz.robust_limits(np.full(4, 2.0)) == (1.0, 3.0)
        with pytest.raises(InputError, match="percentiles"):
            viz.robust_limits(values, percentiles=(50, 10))
        with pytest.raises(InputError, match="no finite"):
            viz.robust_limits(np.full(3, np.nan))
        with pytest.raises(ShapeError, match="mask"):
            viz.robust_limits(values, np.ones(3))

    def test_scale_bar_length(self):
        assert [viz.scale_bar_length(w) for w in (10.0, 1.0, 4.9, 0.26, 250.0)] == [2.0, 0.2, 0.5, 0.05, 50.0]
        with pytest.raises(InputError, match="field_width"):
            viz.scale_bar_length(0.0)

    def test_shaded_depth_hatches_unsolved_pixels(self):
        depth = np.linspace(0, 1, 64).reshape(8, 8)
        mask = np.ones((8, 8), bool)
        mask[2:4, 2:4] = False
        rgb, limits = viz.shaded_depth(depth, mask, 0.1)
        hole = rgb[2:4, 2:4].reshape(-1, 3)
        assert np.ptp(hole, axis=1).max() == 0 and hole.min() >= 0.8  # light, colourless
        assert np.ptp(rgb[mask], axis=1).min() > 0.05  # every solved pixel has a hue
        with pytest.raises(InputError, match="no solved pixel"):
            viz.shaded_depth(depth, np.zeros((8, 8)))
        with pytest.raises(InputError, match="ambient"):
            viz.shaded_depth(depth, ambient=2.0)

    def test_float32_depth_is_shaded_as_float64_within_a_level(self):
        """A float32 map (what save_depth writes) is coloured and shaded in float32: the picture is the float64
        one within a quarter of an 8-bit level."""
        rows, cols = np.mgrid[0:64, 0:64]
        depth = 0.1 * np.sin(rows / 5.0) * np.cos(cols / 7.0) + 0.002 * cols
        mask = np.ones((64, 64), bool)
        mask[10:20, 30:40] = False
        rgb64, limits = viz.shaded_depth(depth, mask, 0.025)
        rgb32, limits32 = viz.shaded_depth(depth.astype(np.float32), mask, 0.025, limits=limits)
        assert rgb64.dtype == np.float64 and rgb32.dtype == np.float32 and limits32 == limits
        assert np.abs(rgb32 - rgb64).max() < 0.25 / 255
        np.testing.assert_array_equal(rgb32[~mask], rgb64[~mask].astype(np.float32))  # the same hatching

        picture = viz.depth_preview(np.random.default_rng(1).random((30, 40)), pixel_pitch_mm=0.025)
        assert picture.dtype == np.uint8 and picture.shape[1] == 320 and picture.shape[0] > 30 * 8
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            viz.depth_preview(np.zeros((4, 4)), pixel_pitch_mm=-1.0)


class TestTriangulation:
    def test_against_a_loop_over_cells(self):
        rng = np.random.default_rng(3)
        mask = rng.random((9, 11)) > 0.3
        index, faces = viz.triangulate_grid(mask)
        np.testing.assert_array_equal(index, np.flatnonzero(mask))
        expected = 0
        for r in range(8):
            for c in range(10):
                corners = int(mask[r, c]) + int(mask[r, c + 1]) + int(mask[r + 1, c]) + int(mask[r + 1, c + 1])
                expected += 2 if corners == 4 else 1 if corners == 3 else 0
        assert faces.shape == (expected, 3)
        rows, cols = np.divmod(index[faces], 11)
        x, y = cols.astype(float), -rows.astype(float)
        # every triangle lies in one cell and turns counter-clockwise seen from +z
        cross = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (y[:, 1] - y[:, 0]) * (x[:, 2] - x[:, 0])
        assert (cross > 0).all() and (np.ptp(rows, axis=1) == 1).all() and (np.ptp(cols, axis=1) == 1).all()

    def test_errors(self):
        with pytest.raises(ShapeError, match="mask"):
            viz.triangulate_grid(np.ones((2, 2, 2)))
        assert viz.triangulate_grid(np.ones((1, 5)))[1].shape == (0, 3)


class TestMatplotlib:
    @pytest.fixture(autouse=True)
    def _agg(self):
        matplotlib = pytest.importorskip("matplotlib")
        matplotlib.use("Agg")

    def test_colour_bars_have_units_and_overlap_nothing(self):
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 3, figsize=(12, 4), dpi=100, constrained_layout=True)
        depth = np.outer(np.linspace(0, 0.3, 40), np.ones(50))
        viz.plot_normals(axes[0], torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 40, 50))
        error_bar = viz.plot_angular_error(axes[1], np.abs(np.random.default_rng(0).normal(2, 1, (40, 50))))
        depth_bar = viz.plot_depth(axes[2], depth, None, 0.025, limits=(0.0, 0.3))
        assert error_bar.ax.get_ylabel() == "angular error (°)" and depth_bar.ax.get_ylabel() == "height (µm)"
        assert depth_bar.mappable.norm.vmin == 0.0 and depth_bar.mappable.norm.vmax == pytest.approx(300.0)
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        boxes = [ax.get_tightbbox(renderer) for ax in fig.axes]
        for i, first in enumerate(boxes):
            for second in boxes[i + 1 :]:
                apart = first.x1 <= second.x0 + 1 or second.x1 <= first.x0 + 1 or first.y1 <= second.y0 + 1 \
                    or second.y1 <= first.y0 + 1
                assert apart, f"{first} overlaps {second}"
        plt.close(fig)

    def test_errors(self):
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots()
        with pytest.raises(InputError, match="no finite"):
            viz.plot_angular_error(ax, np.full((3, 3), np.nan))
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            viz.plot_depth(ax, np.zeros((3, 3)), pixel_pitch_mm=0.0)
        plt.close(fig)


class TestSurface:
    @pytest.fixture(autouse=True)
    def _plotly(self):
        pytest.importorskip("plotly")

    def test_mesh_in_mm_with_albedo(self):
        depth = np.zeros((10, 12))
        depth[3, 4] = np.nan
        fig = viz.surface_figure(depth, np.ones((10, 12)), pixel_pitch_mm=0.5)
        mesh = fig.data[0]
        assert len(mesh.x) == 10 * 12 - 1 and len(mesh.i) == 2 * 9 * 11 - 4 * 2 + 4
        assert max(mesh.x) == pytest.approx(11 * 0.5) and min(mesh.y) == pytest.approx(-9 * 0.5)
        assert "true proportions" in fig.layout.title.text and fig.layout.scene.aspectmode == "data"
        big = viz.surface_figure(np.zeros((400, 400)), max_size=200, exaggeration=3.0)
        assert len(big.data[0].x) == 200 * 200 and "exaggerated 3" in big.layout.title.text

    def test_errors(self):
        with pytest.raises(InputError, match="no solved pixel"):
            viz.surface_figure(np.full((3, 3), np.nan))
        with pytest.raises(ShapeError, match="albedo"):
            viz.surface_figure(np.zeros((3, 3)), np.zeros((4, 4)))
        with pytest.raises(InputError, match="exaggeration"):
            viz.surface_figure(np.zeros((3, 3)), exaggeration=0.0)

    def test_reconstruction_show(self):
        depth = torch.zeros(2, 1, 6, 6)
        rec = Reconstruction(torch.ones(2, 1, 6, 6), torch.zeros(2, 3, 6, 6), depth, depth, depth,
                             torch.ones(2, 1, 6, 6, dtype=torch.bool))
        fig = rec.show(0.025, index=1)
        assert len(fig.data[0].x) == 36 and "mm" in fig.layout.title.text
        with pytest.raises(InputError, match="outside the batch"):
            rec.show(index=2)

    def test_write_html_interrupted_leaves_nothing(self, tmp_path):
        class Interrupted:  # a write that fails half-way (a full disk): the page was left looking complete
            def write_html(self, path, **_):
                Path(path).write_text("<html><body>half")
                raise OSError("No space left on device")

        (tmp_path / "s.html").write_text("the earlier page")
        with pytest.raises(DataFormatError, match="cannot write .*s.html: No space left"):
            viz.write_html(Interrupted(), tmp_path / "s.html")
        assert [p.name for p in tmp_path.iterdir()] == ["s.html"]
        assert (tmp_path / "s.html").read_text() == "the earlier page"

    def test_write_html_is_offline(self, tmp_path):
        path = viz.write_html(viz.surface_figure(np.zeros((4, 4))), tmp_path / "s.html")
        text = path.read_text(encoding="utf-8")
        assert "<script src=" not in text.replace('<script src="data:', "") and len(text) > 1_000_000
