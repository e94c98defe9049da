"""End to end on data_synth's perspective renders of a mirror sphere at the rig's geometry."""

import pytest
import torch

from data_synth.rig import RigConfig, render_sphere
from psmini.calibration import calibrate_sphere, card_distance_from_spheres, triangulate_leds
from psmini.calibration.mirror import SphereCalibration
from psmini.errors import CalibrationError, InputError
from tests.calibration._helpers import angle_deg, rig_intrinsics, specular_points

CONFIG = RigConfig()  # 400x400, 0.025 mm/px, 40 mm working distance, noise and 10-bit quantisation
PLACES = [(0.0, 0.0), (3.0, 3.0), (-3.0, 3.0)]
RADIUS_MM = 1.5


@pytest.fixture(scope="module")
def placements():
    renders = [render_sphere(CONFIG, RADIUS_MM, (x, y, RADIUS_MM), seed=i) for i, (x, y) in enumerate(PLACES)]
    intrinsics = rig_intrinsics(CONFIG)
    # the first placement's sphere is found automatically, the others from their masks
    calibrations = [
        calibrate_sphere(r.images, dark=r.dark, mask=r.mask if i else None, intrinsics=intrinsics, radius_mm=RADIUS_MM)
        for i, r in enumerate(renders)
    ]
    return renders, calibrations


def _true_directions(render):
    leds = render.lights.positions_mm.double()
    points = specular_points(render.camera_centre_mm, render.centre_mm, render.radius_mm, leds)
    return leds - points


def test_perspective_directions_within_0_2_deg(placements):
    for render, calibration in zip(*placements, strict=True):
        assert calibration.model == "perspective"
        assert float(angle_deg(calibration.directions, _true_directions(render)).max()) < 0.2


def test_orthographic_directions_are_degrees_off(placements):
    render = placements[0][0]
    orthographic = calibrate_sphere(render.images, dark=render.dark, mask=render.mask)
    error = angle_deg(orthographic.directions, _true_directions(render))
    assert orthographic.model == "orthographic" and float(error.min()) > 0.8


def test_sphere_centre_in_space(placements):
    for render, calibration in zip(*placements, strict=True):
        truth = render.centre_mm.double() - render.camera_centre_mm.double()
        assert float((calibration.centre_mm.double() - truth).norm()) < 0.05


def test_positions_within_0_2_mm(placements):
    renders, calibrations = placements
    positions, residuals = triangulate_leds(calibrations)
    distance = card_distance_from_spheres(calibrations)
    assert abs(distance - CONFIG.working_distance_mm) < 0.05
    positions = positions.double() + torch.tensor([0.0, 0.0, distance], dtype=torch.float64)
    error = (positions - renders[0].lights.positions_mm.double()).norm(dim=-1)
    assert float(error.max()) < 0.2
    assert float(residuals.max()) < 0.1


def test_bad_input(placements):
    render = placements[0][0]
    with pytest.raises(InputError, match="radius"):
        calibrate_sphere(render.images, intrinsics=rig_intrinsics(CONFIG))
    with pytest.raises(CalibrationError, match="at least 2"):
        triangulate_leds(placements[1][:1])
    with pytest.raises(CalibrationError, match="perspective"):
        triangulate_leds([calibrate_sphere(render.images[:3], dark=render.dark, mask=render.mask)] * 2)
    images = render.images.clone()
    images[2] = render.dark[0]  # LED 2 did not light
    with pytest.raises(CalibrationError, match="LED 2.*no highlight"):
        calibrate_sphere(images, dark=render.dark, mask=render.mask)


def test_triangulate_leds_wrong_types_raise():
    # a list of tensors (the directions or points) failed as a bare AttributeError ('Tensor' has no 'points_mm')
    with pytest.raises(InputError, match="each be a SphereCalibration .* got Tensor at index 0"):
        triangulate_leds([torch.zeros(8, 3), torch.zeros(8, 3)])
    with pytest.raises(InputError, match="sequence of SphereCalibration .* got Tensor"):
        triangulate_leds(torch.zeros(2, 8, 3))
    with pytest.raises(InputError, match="sequence of SphereCalibration .* got NoneType"):
        triangulate_leds(None)


def test_card_distance_from_spheres_wrong_types_raise():
    # a list of tensors (the sphere centres) failed as a bare AttributeError ('Tensor' has no 'centre_mm')
    with pytest.raises(InputError, match="each be a SphereCalibration .* got Tensor at index 0"):
        card_distance_from_spheres([torch.zeros(3), torch.zeros(3)])
    with pytest.raises(InputError, match="sequence of SphereCalibration .* got NoneType"):
        card_distance_from_spheres(None)
    with pytest.raises(CalibrationError, match="perspective"):
        card_distance_from_spheres([])


def test_triangulate_leds_gradcheck():
    """Gradients reach each placement's reflection points and directions (through :func:`triangulate_rays`)."""
    gen = torch.Generator().manual_seed(0)
    down = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    points = [torch.randn(3, 3, generator=gen, dtype=torch.float64).requires_grad_() for _ in range(2)]
    directions = [(torch.randn(3, 3, generator=gen, dtype=torch.float64) + down).requires_grad_() for _ in range(2)]

    def positions(p0, p1, d0, d1):
        # only directions and points_mm enter the triangulation; the highlights and silhouette are not read
        placements = [SphereCalibration(d, None, None, "perspective", points_mm=p)  # type: ignore[arg-type]
                      for p, d in ((p0, d0), (p1, d1))]
        return triangulate_leds(placements)

    assert torch.autograd.gradcheck(positions, (*points, *directions))
