import math

import pytest
import torch

from psmini.calibration.sphere import (
    find_sphere,
    fit_circle,
    pixel_rays,
    reflect_orthographic,
    reflect_perspective,
    segment_sphere,
    silhouette_edges,
    sphere_centre_from_silhouette,
)
from psmini.errors import CalibrationError, InputError, ShapeError
from tests.calibration._helpers import angle_deg, project
from tests.conftest import BaseTester

K = torch.tensor([[1600.0, 0.0, 199.5], [0.0, 1600.0, 199.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _disc(size: int, u: float, v: float, radius: float) -> torch.Tensor:
    rows, cols = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64),
                                indexing="ij")
    return (cols - u).square() + (rows - v).square() < radius**2


class TestFitCircle(BaseTester):
    def test_exact_points(self, device, dtype):
        angle = torch.linspace(0, 5.0, 40, device=device, dtype=dtype)
        points = torch.stack([10.25 + 7.5 * angle.cos(), -3.0 + 7.5 * angle.sin()], dim=-1)
        centre, radius, inliers = fit_circle(points)
        self.assert_close(centre, torch.tensor([10.25, -3.0], device=device, dtype=dtype), rtol=1e-4, atol=1e-4)
        self.assert_close(radius, torch.tensor(7.5, device=device, dtype=dtype), rtol=1e-4, atol=1e-4)
        assert bool(inliers.all())

    def test_outliers_are_trimmed(self):
        angle = torch.linspace(0, 6.2, 200, dtype=torch.float64)
        points = torch.stack([50 + 20 * angle.cos(), 40 + 20 * angle.sin()], dim=-1)
        points[:15] += 6.0  # a highlight breaking the outline
        centre, radius, inliers = fit_circle(points)
        assert torch.allclose(centre, torch.tensor([50.0, 40.0], dtype=torch.float64), atol=1e-6)
        assert abs(float(radius) - 20) < 1e-6 and int((~inliers).sum()) == 15

    def test_batched(self):
        angle = torch.linspace(0, 6.0, 30, dtype=torch.float64)
        circle = torch.stack([angle.cos(), angle.sin()], dim=-1)
        points = torch.stack([circle * 2 + 1, circle * 3 - 4])
        centre, radius, _ = fit_circle(points)
        assert torch.allclose(radius, torch.tensor([2.0, 3.0], dtype=torch.float64))
        assert torch.allclose(centre, torch.tensor([[1.0, 1.0], [-4.0, -4.0]], dtype=torch.float64))

    def test_errors(self):
        with pytest.raises(CalibrationError, match="at least 3"):
            fit_circle(torch.rand(2, 2))
        with pytest.raises(ShapeError):
            fit_circle(torch.rand(5, 3))
        with pytest.raises(ShapeError, match="weights"):
            fit_circle(torch.rand(5, 2), weights=torch.ones(4))

    def test_gradcheck(self):
        angle = torch.linspace(0, 6.0, 12, dtype=torch.float64)
        circle = torch.stack([3 + 2 * angle.cos(), 1 + 2 * angle.sin()], -1)
        points = circle + 0.05 * torch.randn(12, 2, dtype=torch.float64)
        self.gradcheck(lambda p: fit_circle(p, trim=False)[:2], (points.requires_grad_(),))


class TestSilhouette:
    def test_edges_of_a_square(self):
        mask = torch.zeros(9, 9, dtype=torch.bool)
        mask[3:6, 3:6] = True
        edges = silhouette_edges(mask)
        assert edges.shape == (12, 2)
        assert set(edges[:, 0].tolist()) == {2.5, 3.0, 4.0, 5.0, 5.5}

    def test_soft_edge_crossing(self):
        # a soft vertical edge at u = 10.3: a linear ramp 2 pixels wide from inside (1) to outside (0)
        u = torch.arange(24, dtype=torch.float64).expand(20, 24)
        image = (0.5 - (u - 10.3) / 2).clamp(0, 1)
        edges = silhouette_edges(image > 0.5, image)
        assert torch.allclose(edges[:, 0], torch.full((20,), 10.3, dtype=torch.float64))
        assert torch.allclose(silhouette_edges(image > 0.5)[:, 0], torch.full((20,), 10.5))

    def test_edges_misuse_raise(self):
        mask = torch.zeros(9, 9, dtype=torch.bool)
        mask[3:6, 3:6] = True
        with pytest.raises(ShapeError, match="mask must be a non-empty 2-D \\(H, W\\) tensor, got .*\\[1, 9, 9\\]"):
            silhouette_edges(mask[None])
        # an empty mask failed as a bare RuntimeError of narrow(); an image as a list as a bare AttributeError
        with pytest.raises(ShapeError, match="non-empty .* got torch.Size\\(\\[0, 0\\]\\)"):
            silhouette_edges(torch.zeros(0, 0, dtype=torch.bool))
        with pytest.raises(InputError, match="image must be a torch.Tensor, got list"):
            silhouette_edges(mask, [[0.0] * 9] * 9)
        with pytest.raises(ShapeError, match="image \\(8, 9\\) and mask \\(9, 9\\) must have the same size"):
            silhouette_edges(mask, torch.rand(8, 9))

    @pytest.mark.parametrize("darker", [True, False])
    def test_segment_and_fit_a_disc(self, darker):
        disc = _disc(160, 77.3, 81.6, 30.2)
        image = torch.where(disc, 0.1, 0.6) if darker else torch.where(disc, 0.7, 0.2)
        image = image + 0.01 * torch.randn(image.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        image[81, 90] = 1.0  # a highlight inside
        sphere = find_sphere(image=image)
        assert torch.allclose(sphere.centre_px, torch.tensor([77.3, 81.6], dtype=torch.float64), atol=0.05)
        assert abs(float(sphere.radius_px) - 30.2) < 0.1

    def test_mask(self):
        sphere = find_sphere(mask=_disc(200, 97.7, 103.2, 41.3))
        assert torch.allclose(sphere.centre_px, torch.tensor([97.7, 103.2]), atol=0.05)
        assert abs(float(sphere.radius_px) - 41.3) < 0.1 and sphere.rms_px < 0.4

    def test_not_found(self):
        with pytest.raises(CalibrationError, match="sphere not found"):
            segment_sphere(torch.full((40, 40), 0.5))
        cut = _disc(100, 5.0, 50.0, 30.0).double()  # cut by the border
        with pytest.raises(CalibrationError, match="sphere not found"):
            find_sphere(image=cut)
        with pytest.raises(CalibrationError, match="empty"):
            find_sphere(mask=torch.zeros(10, 10, dtype=torch.bool))
        with pytest.raises(CalibrationError, match="border"):
            find_sphere(mask=_disc(100, 5.0, 50.0, 30.0))
        with pytest.raises(InputError):
            find_sphere()


def _outline(centre: torch.Tensor, radius: float, count: int = 400) -> torch.Tensor:
    """Exact pixels of a sphere's perspective outline (the tangent cone)."""
    axis = centre / centre.norm()
    alpha = math.asin(radius / float(centre.norm()))
    first = torch.nn.functional.normalize(
        torch.linalg.cross(axis, torch.tensor([0.0, 1.0, 0.0], dtype=axis.dtype)), dim=0
    )
    second = torch.linalg.cross(axis, first)
    theta = torch.linspace(0, 2 * math.pi, count + 1, dtype=axis.dtype)[:-1, None]
    rays = math.cos(alpha) * axis + math.sin(alpha) * (theta.cos() * first + theta.sin() * second)
    return project(rays, K)


class TestPerspective(BaseTester):
    def test_pixel_rays(self):
        rays = pixel_rays(torch.tensor([[199.5, 199.5], [1799.5, 199.5]], dtype=torch.float64), K)
        self.assert_close(rays[0], torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
        self.assert_close(rays[1], torch.tensor([1.0, 0.0, -1.0], dtype=torch.float64) / math.sqrt(2))

    @pytest.mark.parametrize("centre", [(0.0, 0.0, -38.5), (3.0, -2.0, -37.0)])
    def test_centre_from_outline(self, centre):
        centre = torch.tensor(centre, dtype=torch.float64)
        estimate = sphere_centre_from_silhouette(_outline(centre, 1.5), K, 1.5)
        self.assert_close(estimate, centre, rtol=1e-9, atol=1e-9)

    def test_centre_from_outline_misuse_raise(self):
        edges = _outline(torch.tensor([0.0, 0.0, -38.5], dtype=torch.float64), 1.5, 24)
        with pytest.raises(ShapeError, match="edge_px must have shape \\(N, 2\\), got \\(24, 3\\)"):
            sphere_centre_from_silhouette(torch.cat([edges, edges[:, :1]], dim=1), K, 1.5)
        # a NaN edge point was reported as an outline that is not a cone (|w| = nan)
        bad = edges.clone()
        bad[3, 0] = math.nan
        with pytest.raises(InputError, match="edge_px must be finite, got 1 NaN"):
            sphere_centre_from_silhouette(bad, K, 1.5)
        # weights of another length failed as a bare RuntimeError, a list of them as an AttributeError
        with pytest.raises(ShapeError, match="weights must have shape \\(24,\\), one per edge point, got \\(12,\\)"):
            sphere_centre_from_silhouette(edges, K, 1.5, torch.ones(12))
        with pytest.raises(ShapeError, match="weights .* got list"):
            sphere_centre_from_silhouette(edges, K, 1.5, [1.0] * 24)
        with pytest.raises(InputError, match="weights must be finite"):
            sphere_centre_from_silhouette(edges, K, 1.5, torch.full((24,), math.nan))
        with pytest.raises(InputError, match="radius_mm must be a positive finite number, got 0.0"):
            sphere_centre_from_silhouette(edges, K, 0.0)
        with pytest.raises(ShapeError, match="intrinsics must have shape \\(3, 3\\)"):
            sphere_centre_from_silhouette(edges, torch.eye(2, dtype=torch.float64), 1.5)
        # the inliers of find_sphere serve as weights as they are (bool)
        inliers = torch.ones(24, dtype=torch.bool)
        expected = sphere_centre_from_silhouette(edges, K, 1.5)
        self.assert_close(sphere_centre_from_silhouette(edges, K, 1.5, inliers), expected)

    def test_reflection_reaches_the_led(self):
        centre = torch.tensor([2.0, 1.0, -38.0], dtype=torch.float64)
        leds = torch.tensor([[15.8, 0.0, -30.0], [0.0, -15.8, -30.0], [-11.2, 11.2, -30.0]], dtype=torch.float64)
        from tests.calibration._helpers import specular_points

        points = specular_points(torch.zeros(3, dtype=torch.float64), centre, 1.5, leds)
        directions, hits = reflect_perspective(project(points, K), K, centre, 1.5)
        self.assert_close(hits, points, rtol=1e-8, atol=1e-8)
        assert float(angle_deg(directions, leds - points).max()) < 1e-6

    def test_orthographic(self):
        # a normal 30 degrees from the view reflects a light 60 degrees from it
        offset = 20 * math.sin(math.radians(30))
        directions = reflect_orthographic(torch.tensor([[50.0 + offset, 50.0]], dtype=torch.float64),
                                          torch.tensor([50.0, 50.0], dtype=torch.float64), 20.0)
        expected = torch.tensor([[math.sin(math.radians(60)), 0.0, math.cos(math.radians(60))]], dtype=torch.float64)
        self.assert_close(directions, expected)

    def test_outside_raises(self):
        with pytest.raises(CalibrationError, match=r"outside the sphere for LED\(s\) \[1\]"):
            reflect_orthographic(torch.tensor([[50.0, 50.0], [80.0, 50.0]]), torch.tensor([50.0, 50.0]), 20.0)
        with pytest.raises(CalibrationError, match=r"LED\(s\) \[0\]"):
            reflect_perspective(torch.tensor([[10.0, 10.0]], dtype=torch.float64), K,
                                torch.tensor([0.0, 0.0, -38.5], dtype=torch.float64), 1.5)

    def test_bad_intrinsics(self):
        with pytest.raises(CalibrationError, match="focal"):
            pixel_rays(torch.zeros(1, 2, dtype=torch.float64), torch.eye(3, dtype=torch.float64) * -1)

    def test_gradcheck(self):
        highlights = torch.tensor([[215.0, 190.0], [180.0, 205.0]], dtype=torch.float64, requires_grad=True)
        centre = torch.tensor([0.1, -0.1, -38.5], dtype=torch.float64, requires_grad=True)
        self.gradcheck(lambda h, c: reflect_perspective(h, K, c, 1.5), (highlights, centre))
        self.gradcheck(lambda h, c: reflect_orthographic(h, c, 40.0),
                       (highlights, torch.tensor([199.0, 198.0], dtype=torch.float64, requires_grad=True)))
        edges = _outline(torch.tensor([0.3, 0.2, -38.0], dtype=torch.float64), 1.5, 24).requires_grad_()
        self.gradcheck(lambda e: sphere_centre_from_silhouette(e, K, 1.5), (edges,))
