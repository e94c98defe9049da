import math

import pytest
import torch

from psmini.errors import InputError, ShapeError
from psmini.geometry import depth_to_points
from psmini.lights import DirectionalLights, LEDLights, PointLights, ring_lights
from psmini.render import Renderer, cast_shadows, normals_from_height, render, render_lambertian
from tests._analytic import analytic_sphere
from tests._analytic import render as reference_render
from tests.conftest import BaseTester


def _plane(a: float, b: float, size: int, pitch: float, device, dtype) -> torch.Tensor:
    """Height z = a·x + b·y on the orthographic pixel grid, (1, 1, size, size)."""
    index = (torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2) * pitch
    y, x = torch.meshgrid(-index, index, indexing="ij")
    return (a * x + b * y)[None, None]


def _flat_normals(size: int, device, dtype) -> torch.Tensor:
    return torch.tensor([0.0, 0.0, 1.0], device=device, dtype=dtype).view(1, 3, 1, 1).expand(1, 3, size, size)


class TestNormalsFromHeight(BaseTester):
    def test_tilted_plane_everywhere(self, device, dtype):
        height = _plane(0.3, -0.7, 9, 0.25, device, dtype)
        normals = normals_from_height(height, 0.25)
        expected = torch.tensor([-0.3, 0.7, 1.0], device=device, dtype=dtype)
        expected = (expected / expected.norm()).view(1, 3, 1, 1).expand_as(normals)
        self.assert_close(normals, expected)

    def test_y_is_up(self, device, dtype):
        rows = torch.arange(5, device=device, dtype=dtype).view(1, 1, 5, 1).expand(1, 1, 5, 5)
        normals = normals_from_height(rows.clone(), 1.0)  # height grows downward in the image: -y
        assert bool((normals[:, 1] > 0).all())  # the surface faces up (+y)

    def test_paraboloid_interior(self, device):
        # central differences are exact on a quadratic: p = 2 c x
        height = _plane(0.0, 0.0, 11, 0.1, device, torch.float64)
        index = (torch.arange(11, device=device, dtype=torch.float64) - 5) * 0.1
        height = (0.5 * index.square()).view(1, 1, 1, 11).expand(1, 1, 11, 11).contiguous()
        normals = normals_from_height(height, 0.1)
        p = -normals[:, 0] / normals[:, 2]
        torch.testing.assert_close(p[0, :, 1:-1], index[1:-1].expand(11, 9), rtol=1e-12, atol=1e-12)

    def test_gradcheck(self):
        height = torch.rand(1, 1, 4, 5, dtype=torch.float64, requires_grad=True)
        self.gradcheck(lambda h: normals_from_height(h, 0.5), (height,))

    def test_errors(self):
        with pytest.raises(ShapeError):
            normals_from_height(torch.rand(1, 2, 4, 4), 0.1)
        with pytest.raises(ShapeError, match="2x2"):
            normals_from_height(torch.rand(1, 1, 1, 4), 0.1)
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            normals_from_height(torch.rand(1, 1, 4, 4), 0.0)
        with pytest.raises(InputError, match="finite"):
            normals_from_height(torch.full((1, 1, 4, 4), math.nan), 0.1)


class TestRenderLambertian(BaseTester):
    def test_matches_independent_render(self, device, dtype):
        normals, mask, albedo = analytic_sphere(16, device=device, dtype=dtype)
        lights = ring_lights(8, 55.0, device=device, dtype=dtype) * 0.7
        self.assert_close(render_lambertian(normals, albedo, lights), reference_render(normals, albedo, lights))

    def test_attached_shadows_are_zero(self, device, dtype):
        normals = torch.tensor([1.0, 0.0, 0.0], device=device, dtype=dtype).view(1, 3, 1, 1).expand(1, 3, 2, 2)
        lights = torch.tensor([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], device=device, dtype=dtype)
        images = render_lambertian(normals, torch.ones(1, 1, 2, 2, device=device, dtype=dtype), lights)
        assert images[:, 0].abs().max() == 0 and bool((images[:, 1] == 1).all())

    def test_batched_lights(self, device, dtype):
        normals, _, albedo = analytic_sphere(8, device=device, dtype=dtype)
        lights = torch.stack(
            [ring_lights(4, 30.0, device=device, dtype=dtype), ring_lights(4, 60.0, device=device, dtype=dtype)]
        )
        images = render_lambertian(normals.expand(2, -1, -1, -1), albedo.expand(2, -1, -1, -1), lights)
        self.assert_close(images[1:], render_lambertian(normals, albedo, lights[1]))

    def test_gradcheck(self):
        normals, _, albedo = analytic_sphere(4, dtype=torch.float64, radius_fraction=2.0)
        lights = ring_lights(8, 40.0, dtype=torch.float64)
        self.gradcheck(render_lambertian, (normals.requires_grad_(), albedo.requires_grad_(), lights.requires_grad_()))

    def test_errors(self):
        with pytest.raises(ShapeError):
            render_lambertian(torch.rand(1, 2, 4, 4), torch.rand(1, 1, 4, 4), ring_lights(8, 55.0))
        with pytest.raises(ShapeError, match="albedo"):
            render_lambertian(torch.rand(1, 3, 4, 4), torch.rand(1, 1, 4, 5), ring_lights(8, 55.0))
        with pytest.raises(ShapeError, match="lights"):
            render_lambertian(torch.rand(1, 3, 4, 4), torch.rand(1, 1, 4, 4), torch.rand(8, 2))
        with pytest.raises(InputError):
            render_lambertian(torch.ones(1, 3, 4, 4, dtype=torch.int64), torch.rand(1, 1, 4, 4), ring_lights(8, 55.0))


class TestRender(BaseTester):
    def test_plane_under_point_source_inverse_square_and_cosine(self, device, dtype):
        # z = 0.2 x - 0.1 y under an isotropic point source: I = ρ φ (n · (s - x)) / |s - x|³, exactly.
        pitch, size = 0.5, 9
        height = _plane(0.2, -0.1, size, pitch, device, dtype)
        points = depth_to_points(height, pitch)
        normals = normals_from_height(height, pitch)
        source = torch.tensor([1.0, -2.0, 6.0], device=device, dtype=dtype)
        phi, rho = 3.0, 0.6
        lights = PointLights(source[None], torch.tensor([phi], device=device, dtype=dtype))
        images = render(points, normals, torch.full((1, 1, size, size), rho, device=device, dtype=dtype), lights)
        offset = source.view(1, 3, 1, 1) - points
        distance = offset.norm(dim=1, keepdim=True)
        expected = rho * phi * (normals * offset).sum(1, keepdim=True) / distance**3
        torch.testing.assert_close(images, expected, rtol=1e-5, atol=1e-7)
        # and the two laws separately, against numbers worked by hand at the pixel under the source's foot
        n = torch.tensor([-0.2, 0.1, 1.0]) / math.sqrt(1.05)

        def analytic(x: float, y: float) -> float:
            z = 0.2 * x - 0.1 * y
            d = torch.tensor([1.0 - x, -2.0 - y, 6.0 - z])
            return rho * phi * float(n @ d) / float(d.norm()) ** 3

        centre = (size - 1) // 2
        assert float(images[0, 0, centre, centre]) == pytest.approx(analytic(0.0, 0.0), rel=1e-5)
        assert float(images[0, 0, 0, size - 1]) == pytest.approx(analytic(2.0, 2.0), rel=1e-5)

    def test_led_falloff(self, device, dtype):
        size = 5
        points = depth_to_points(torch.zeros(1, 1, size, size, device=device, dtype=dtype), 1.0)
        normals = _flat_normals(size, device, dtype)
        position = torch.tensor([[0.0, 0.0, 4.0]], device=device, dtype=dtype)
        axis = torch.tensor([[0.6, 0.0, -0.8]], device=device, dtype=dtype)
        leds = LEDLights(position, axis, torch.tensor([2.0], device=device, dtype=dtype),
                         torch.tensor([1.0], device=device, dtype=dtype))
        images = render(points, normals, torch.ones(1, 1, size, size, device=device, dtype=dtype), leds)
        # at (x, y) = (2, 0): d = (2, 0, -4)/√20, cos to axis = (1.2 + 3.2)/√20, cos to normal = 4/√20, r² = 20
        expected = 2.0 * (4.4 / math.sqrt(20)) * (4 / math.sqrt(20)) / 20
        assert float(images[0, 0, 2, 4]) == pytest.approx(expected, rel=1e-5)

    def test_directional_matches_render_lambertian(self, device, dtype):
        normals, _, albedo = analytic_sphere(12, device=device, dtype=dtype)
        directions = ring_lights(8, 50.0, device=device, dtype=dtype)
        intensities = torch.linspace(0.5, 1.5, 8, device=device, dtype=dtype)
        lights = DirectionalLights(directions, intensities)
        points = torch.zeros(1, 3, 12, 12, device=device, dtype=dtype)
        self.assert_close(render(points, normals, albedo, lights),
                          render_lambertian(normals, albedo, directions * intensities[:, None]))

    def test_blinn_phong_lobe(self, device, dtype):
        size = 3
        normals = _flat_normals(size, device, dtype)
        theta = math.radians(40.0)
        lights = DirectionalLights(torch.tensor([[math.sin(theta), 0.0, math.cos(theta)], [0.0, 0.0, 1.0]],
                                                device=device, dtype=dtype))
        albedo = torch.full((1, 1, size, size), 0.5, device=device, dtype=dtype)
        specular = torch.full((1, 1, size, size), 0.25, device=device, dtype=dtype)
        images = render(torch.zeros(1, 3, size, size, device=device, dtype=dtype), normals, albedo, lights,
                        specular=specular, shininess=20.0)
        # the half vector lies at θ/2 from the normal
        expected = 0.5 * math.cos(theta) + 0.25 * math.cos(theta / 2) ** 20
        assert float(images[0, 0, 1, 1]) == pytest.approx(expected, rel=1e-5)
        assert float(images[0, 1, 1, 1]) == pytest.approx(0.75, rel=1e-5)

    def test_cast_shadows_through_render(self, device):
        height = torch.zeros(1, 1, 6, 12, device=device)
        height[..., 3] = 1.0
        points = depth_to_points(height, 0.25)
        normals = normals_from_height(height, 0.25)
        lights = DirectionalLights(torch.tensor([[-1.0, 0.0, 1.0]], device=device))
        lit = render(points, normals, torch.ones(1, 1, 6, 12, device=device), lights, shadows=True, pixel_pitch_mm=0.25)
        assert bool((lit[0, 0, :, 9:] > 0).all())
        assert bool((lit[0, 0, :, 5:7] == 0).all())

    def test_learnable_lights_get_gradients(self):
        normals, _, albedo = analytic_sphere(6)
        leds = LEDLights(torch.tensor([[3.0, 0.0, 5.0], [-3.0, 0.0, 5.0], [0.0, 3.0, 5.0]]),
                         torch.tensor([[0.0, 0.0, -1.0]]).expand(3, 3), learnable=True)
        renderer = Renderer(leds)
        renderer(torch.zeros(1, 3, 6, 6), normals, albedo).sum().backward()
        assert leds.positions_mm.grad is not None and bool(leds.positions_mm.grad.abs().sum() > 0)

    def test_gradcheck_point_lights(self):
        size = 3
        height = (torch.rand(1, 1, size, size, dtype=torch.float64) * 0.2).requires_grad_()
        albedo = torch.rand(1, 1, size, size, dtype=torch.float64).requires_grad_()
        specular = torch.rand(1, 1, size, size, dtype=torch.float64).requires_grad_()
        lights = PointLights(torch.tensor([[0.5, 0.2, 4.0], [-2.0, 1.0, 5.0]], dtype=torch.float64))

        def func(h, a, s):
            return render(depth_to_points(h, 0.5), normals_from_height(h, 0.5), a, lights, specular=s, shininess=5.0)

        self.gradcheck(func, (height, albedo, specular))

    def test_gradcheck_renderer(self):
        """The module passes gradients to the surface and to its light model's parameters."""
        generator = torch.Generator().manual_seed(0)
        height = (torch.rand(1, 1, 3, 3, generator=generator, dtype=torch.float64) * 0.2).requires_grad_()
        albedo = (torch.rand(1, 1, 3, 3, generator=generator, dtype=torch.float64) + 0.5).requires_grad_()
        directions = ring_lights(4, 40.0, dtype=torch.float64).requires_grad_()
        intensities = torch.linspace(0.5, 2.0, 4, dtype=torch.float64).requires_grad_()

        def func(h, a, d, i):
            renderer = Renderer(DirectionalLights(d, i), shininess=5.0)
            return renderer(depth_to_points(h, 0.5), normals_from_height(h, 0.5), a, 0.3 * a)

        self.gradcheck(func, (height, albedo, directions, intensities))

    def test_errors(self):
        lights = DirectionalLights(ring_lights(8, 55.0))
        points, normals, albedo = (
            torch.zeros(1, 3, 4, 4),
            _flat_normals(4, "cpu", torch.float32),
            torch.ones(1, 1, 4, 4),
        )
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            render(points, normals, albedo, lights, shadows=True)
        with pytest.raises(ShapeError, match="normals"):
            render(points, normals[..., :3], albedo, lights)
        with pytest.raises(ShapeError, match="specular"):
            render(points, normals, albedo, lights, specular=torch.ones(1, 2, 4, 4))
        with pytest.raises(InputError, match="shininess"):
            render(points, normals, albedo, lights, shininess=0.0)
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            Renderer(lights, shadows=True)

    def test_tensor_lights_raise(self):
        # a tensor of directions (what render_lambertian takes) failed as "'Tensor' object is not callable"
        points, normals = torch.zeros(1, 3, 4, 4), _flat_normals(4, "cpu", torch.float32)
        albedo = torch.ones(1, 1, 4, 4)
        with pytest.raises(InputError, match="light_model must be a light model .* got Tensor .*render_lambertian"):
            render(points, normals, albedo, ring_lights(8, 55.0))
        with pytest.raises(InputError, match="light_model must be a light model .* got NoneType"):
            Renderer(None)  # was accepted, to fail at the first call


class TestCastShadows(BaseTester):
    @pytest.mark.parametrize("elevation_deg", [30.0, 45.0, 60.0])
    def test_shadow_length_of_a_wall(self, device, elevation_deg):
        # a wall of height h casts a shadow h / tan(elevation) long
        pitch, wall_height, wall = 0.1, 1.0, 10
        height = torch.zeros(1, 1, 4, 64, device=device)
        height[..., wall] = wall_height
        e = math.radians(elevation_deg)
        light = torch.tensor([[-math.cos(e), 0.0, math.sin(e)]], device=device)
        visible = cast_shadows(height, light, pitch)[0, 0, 0, 0]
        length = wall_height / math.tan(e) / pitch
        shadowed = torch.nonzero(visible == 0).flatten()
        assert int(shadowed.min()) == wall + 1
        assert abs(int(shadowed.max()) - wall - length) <= 1.0 + 1e-6  # the boundary pixel may go either way
        assert bool((visible[:wall + 1] == 1).all())

    def test_overhead_light_and_flat_field_cast_nothing(self, device):
        height = torch.rand(1, 1, 8, 8, device=device)
        assert bool((cast_shadows(height, torch.tensor([[0.0, 0.0, 1.0]], device=device), 0.1) == 1).all())
        flat = torch.zeros(1, 1, 8, 8, device=device)
        assert bool((cast_shadows(flat, ring_lights(8, 80.0, device=device), 0.1) == 1).all())

    def test_per_pixel_vectors_of_a_point_light(self, device):
        # a point light just beyond a wall: pixels behind the wall are shadowed, those in front are not
        height = torch.zeros(1, 1, 3, 40, device=device)
        height[..., 20] = 2.0
        points = depth_to_points(height, 0.1)
        lights = PointLights(torch.tensor([[-4.0, 0.0, 3.0]], device=device))
        directions, _ = lights(points)
        visible = cast_shadows(height, directions, 0.1)[0, 0, 0, 1]
        assert bool((visible[:20] == 1).all()) and bool((visible[21:30] == 0).all())

    def test_batch_and_shape(self, device):
        height = torch.rand(2, 1, 5, 6, device=device)
        visible = cast_shadows(height, ring_lights(3, 70.0, device=device), 0.05)
        assert visible.shape == (2, 3, 1, 5, 6)

    def test_errors(self):
        with pytest.raises(ShapeError, match="light_vectors"):
            cast_shadows(torch.rand(1, 1, 4, 4), torch.rand(1, 8, 3, 4, 5), 0.1)
        with pytest.raises(ShapeError):
            cast_shadows(torch.rand(1, 2, 4, 4), ring_lights(8, 55.0), 0.1)
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            cast_shadows(torch.rand(1, 1, 4, 4), ring_lights(8, 55.0), -1.0)
