import pytest
import torch

from data_synth.rig import RigConfig, render_card
from psmini.calibration import card_reference, polynomial_surface
from psmini.errors import DataFormatError, InputError, ShapeError
from psmini.io import read_capture, write_flatfield_capture
from psmini.lights import DirectionalLights, ring_lights

CONFIG = RigConfig(size=96, pixel_pitch_mm=0.1)  # the rig's 10 mm field at a coarser pitch


@pytest.fixture(scope="module")
def cards():
    clean = render_card(CONFIG.replace(noise=False), albedo=0.8)
    frames = [render_card(CONFIG, albedo=0.8, seed=seed) for seed in range(4)]
    return clean, frames


def _rms(x):
    return float(x.square().mean().sqrt())


@pytest.mark.parametrize("method", ["polynomial", "gaussian"])
def test_smoothing_removes_the_noise(cards, method):
    clean, frames = cards
    truth = clean.images - clean.dark
    # sigma 2 px here is 0.2 mm on the card, the default 8 px at the rig's 0.025 mm pitch
    card = card_reference(torch.stack([f.images for f in frames]), torch.stack([f.dark for f in frames]), method=method,
                          sigma_px=2.0)
    single = frames[0].images - frames[0].dark
    # the card saturates near the LEDs (not trusted there); the Gaussian's border is less certain
    interior = torch.zeros_like(card.valid)
    interior[:, 8:-8, 8:-8] = True
    interior &= card.valid
    relative_single = _rms(((single - truth) / truth)[interior])
    relative_reference = _rms(((card.reference - truth) / truth)[interior])
    assert relative_reference < relative_single / 4
    assert relative_reference < 0.004
    assert card.frames == 4 and float(card.valid.float().mean()) > 0.8


def test_polynomial_recovers_a_polynomial():
    y, x = torch.meshgrid(
        torch.linspace(-1, 1, 30, dtype=torch.float64), torch.linspace(-1, 1, 40, dtype=torch.float64), indexing="ij"
    )
    surface = (1 + 0.3 * x - 0.2 * y + 0.1 * x * y - 0.05 * x**3)[None]
    weights = torch.ones_like(surface)
    weights[..., :10, :10] = 0  # untrusted pixels do not matter
    noisy = surface.clone()
    noisy[..., :10, :10] = 50.0
    assert torch.allclose(polynomial_surface(noisy, weights, 3), surface, atol=1e-9)


@pytest.mark.parametrize("method", ["polynomial", "gaussian", "mean"])
def test_gradcheck(method):
    """The reference is differentiable in the frames and the dark frame (the trusted pixels are a fixed choice)."""
    gen = torch.Generator().manual_seed(0)
    frames = (torch.rand(2, 3, 6, 6, generator=gen, dtype=torch.float64) * 0.3 + 0.3).requires_grad_()
    dark = torch.full((6, 6), 0.01, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda f, d: card_reference(f, d, method=method, degree=2, sigma_px=1.5).reference, (frames, dark))


def test_dark_pixels_are_not_trusted():
    frames = torch.full((2, 3, 20, 20), 0.5)
    frames[:, 1, :, :5] = 0.001
    card = card_reference(frames, method="mean")
    assert not bool(card.valid[1, :, :5].any()) and bool(card.valid[0].all())
    assert float(card.reference[1, :, :5].abs().max()) == 0.0


def test_saturated_pixels_are_not_trusted():
    frames = torch.full((3, 20, 20), 0.5)
    frames[0, 4, 4] = 1.0
    assert not bool(card_reference(frames, method="mean").valid[0, 4, 4])


def test_errors():
    with pytest.raises(ShapeError):
        card_reference(torch.rand(20, 20))
    with pytest.raises(ShapeError, match="dark"):
        card_reference(torch.rand(3, 20, 20), torch.rand(19, 20))
    with pytest.raises(InputError, match="method"):
        card_reference(torch.rand(3, 20, 20), method="median")
    with pytest.raises(InputError, match="no trusted"):
        card_reference(torch.zeros(3, 20, 20))
    with pytest.raises(InputError, match="degree"):
        polynomial_surface(torch.rand(1, 5, 5), torch.ones(1, 5, 5), 11)


def test_written_capture_gives_back_the_reference(tmp_path, cards):
    _, frames = cards
    card = card_reference(torch.stack([f.images for f in frames]), torch.stack([f.dark for f in frames]))
    folder = write_flatfield_capture(tmp_path / "card", card, DirectionalLights(ring_lights(8, 58.0)),
                                     card_albedo=0.8, pixel_pitch_mm=0.1)
    capture = read_capture(folder)
    assert capture.kind == "flatfield" and capture.card_albedo == 0.8
    assert torch.allclose(capture.images - capture.dark, card.reference, atol=2 / 65535)


def test_write_flatfield_capture_misuse_raise(tmp_path):
    from psmini.calibration.reference import CardReference

    lights = DirectionalLights(ring_lights(8, 58.0))
    reference = torch.rand(8, 6, 7) * 0.5
    # the reference tensor alone failed as a bare AttributeError ('Tensor' object has no attribute 'dark')
    with pytest.raises(InputError, match="card must be a CardReference .* got Tensor"):
        write_flatfield_capture(tmp_path / "a", reference, lights, card_albedo=0.8, pixel_pitch_mm=0.1)
    card = CardReference(reference, None, torch.ones(8, 6, 7, dtype=torch.bool), 4, torch.zeros(8))
    # a list of metadata failed as a bare TypeError ('list' object is not a mapping)
    with pytest.raises(InputError, match="metadata must be a dict or None, got list"):
        write_flatfield_capture(tmp_path / "b", card, lights, card_albedo=0.8, pixel_pitch_mm=0.1, metadata=["x"])
    with pytest.raises(InputError, match="card_albedo"):
        write_flatfield_capture(tmp_path / "c", card, lights, card_albedo=-1.0, pixel_pitch_mm=0.1)
    with pytest.raises(InputError, match="8 images but 6 lights"):
        write_flatfield_capture(tmp_path / "d", card, DirectionalLights(ring_lights(6, 58.0)), card_albedo=0.8,
                                pixel_pitch_mm=0.1)
    write_flatfield_capture(tmp_path / "e", card, lights, card_albedo=0.8, pixel_pitch_mm=0.1)
    with pytest.raises(DataFormatError, match="already exists"):
        write_flatfield_capture(tmp_path / "e", card, lights, card_albedo=0.8, pixel_pitch_mm=0.1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e"]  # nothing written by the refused calls
