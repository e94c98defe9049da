import pytest
import torch

from psmini.calibration.highlights import locate_highlights
from psmini.errors import CalibrationError, ShapeError

SIZE = 96
CENTRE = torch.tensor([48.0, 46.0], dtype=torch.float64)
RADIUS = 30.0
GRID_V, GRID_U = torch.meshgrid(torch.arange(SIZE, dtype=torch.float64), torch.arange(SIZE, dtype=torch.float64),
                                indexing="ij")


def _spot(u: float, v: float, peak: float = 0.9, sigma: float = 1.5) -> torch.Tensor:
    return peak * torch.exp(-((GRID_U - u).square() + (GRID_V - v).square()) / (2 * sigma**2))


def _noise(seed: int, level: float = 0.002) -> torch.Tensor:
    return 0.02 + level * torch.randn(SIZE, SIZE, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_subpixel_gaussian_spots():
    truth = torch.tensor([[40.3, 37.7], [55.85, 50.2], [47.5, 60.1]], dtype=torch.float64)
    images = torch.stack([_spot(u, v) + _noise(i) for i, (u, v) in enumerate(truth.tolist())])
    found = locate_highlights(images, CENTRE, RADIUS)
    assert float((found.positions_px - truth).norm(dim=-1).max()) < 0.03
    assert not bool(found.saturated.any())


def test_saturated_core_with_blooming_and_stray_reflection():
    # a clipped core, a symmetric blooming halo, and a bright reflection off the sphere (ignored)
    image = (_spot(41.4, 52.6, peak=3.0, sigma=2.0) + _spot(41.4, 52.6, peak=0.2, sigma=6.0) + _noise(3)).clamp(max=1.0)
    image = image + _spot(90.0, 10.0, peak=0.9)
    found = locate_highlights(image[None], CENTRE, RADIUS)
    assert bool(found.saturated[0])
    assert float((found.positions_px[0] - torch.tensor([41.4, 52.6], dtype=torch.float64)).norm()) < 0.05


def test_dim_led_found_relative_to_its_own_image():
    images = torch.stack([_spot(40.0, 40.0) + _noise(0), _spot(52.25, 44.6, peak=0.05) + _noise(1, 0.0005)])
    found = locate_highlights(images, CENTRE, RADIUS)
    assert float((found.positions_px[1] - torch.tensor([52.25, 44.6], dtype=torch.float64)).norm()) < 0.05


def test_dark_frame_is_subtracted():
    dark = 0.06 * (GRID_U / SIZE)  # a gradient that would pull the centroid
    found = locate_highlights((_spot(45.2, 47.9) + dark + _noise(2))[None], CENTRE, RADIUS, dark=dark[None])
    assert float((found.positions_px[0] - torch.tensor([45.2, 47.9], dtype=torch.float64)).norm()) < 0.03


def test_no_highlight_names_the_led():
    images = torch.stack([_spot(40.0, 40.0) + _noise(0), _noise(1)])
    with pytest.raises(CalibrationError, match=r"LED 1 \(led_01.png\): no highlight"):
        locate_highlights(images, CENTRE, RADIUS, names=["led_00.png", "led_01.png"])


def test_two_highlights():
    images = (_spot(40.0, 40.0) + _spot(56.0, 52.0, peak=0.7) + _noise(0))[None]
    with pytest.raises(CalibrationError, match="LED 0: two highlights"):
        locate_highlights(images, CENTRE, RADIUS)


def test_highlight_outside_the_sphere():
    images = (_spot(88.0, 90.0) + _noise(0))[None]
    with pytest.raises(CalibrationError, match="LED 0: highlight outside the sphere"):
        locate_highlights(images, CENTRE, RADIUS)


def test_shapes():
    with pytest.raises(ShapeError):
        locate_highlights(torch.rand(SIZE, SIZE), CENTRE, RADIUS)
    with pytest.raises(ShapeError, match="dark"):
        locate_highlights(torch.rand(2, SIZE, SIZE), CENTRE, RADIUS, dark=torch.rand(2, SIZE, SIZE))
    with pytest.raises(ShapeError, match="names"):
        locate_highlights(torch.rand(2, SIZE, SIZE), CENTRE, RADIUS, names=["a"])
