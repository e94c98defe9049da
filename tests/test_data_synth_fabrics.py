import math

import pytest
import torch

from data_synth import CARD_ALBEDO, FABRICS, Fabric, make_fabric
from psmini.errors import InputError


@pytest.mark.parametrize("name", list(FABRICS))
def test_every_fabric_is_well_formed_and_reproducible(name):
    fabric = make_fabric(name, size=96, seed=3)
    assert isinstance(fabric, Fabric) and fabric.name == name
    for field in (fabric.height_mm, fabric.albedo, fabric.specular):
        assert field.shape == (1, 1, 96, 96) and field.dtype == torch.float32
        assert bool(torch.isfinite(field).all())
    assert fabric.mask.dtype == torch.bool and fabric.mask.shape == (1, 1, 96, 96)
    assert float(fabric.height_mm.min()) >= 0.0  # the cloth rests on the card plane
    assert float(fabric.albedo.min()) >= 0.0 and float(fabric.albedo.max()) <= 1.0
    assert float(fabric.height_mm.max()) > 0.0
    assert fabric.params["seed"] == 3 and fabric.pixel_pitch_mm == 0.025
    again = make_fabric(name, size=96, seed=3)
    assert torch.equal(fabric.height_mm, again.height_mm) and torch.equal(fabric.albedo, again.albedo)
    other = make_fabric(name, size=96, seed=4)
    assert not torch.equal(fabric.height_mm, other.height_mm) or not torch.equal(fabric.albedo, other.albedo)


def test_card_shows_through_holes_of_the_net():
    fabric = make_fabric("net", size=200, seed=0, randomness=0.0, orientation_deg=0.0)
    holes = ~fabric.mask
    assert bool((fabric.height_mm[holes] == 0).all())
    assert torch.allclose(fabric.albedo[holes], torch.tensor(CARD_ALBEDO))
    # open area of a square mesh of yarns of width w every s: (1 - w/s)²
    width, spacing = fabric.params["width_mm"], fabric.params["spacing_mm"]
    assert float(holes.float().mean()) == pytest.approx((1 - width / spacing) ** 2, abs=0.03)


def test_yarn_spacing_sets_the_period():
    # a regular plain weave repeats every two yarns: the height's spectrum peaks at 1 / (2 spacing)
    spacing, size, pitch = 0.5, 400, 0.025
    fabric = make_fabric("jute", size=size, seed=0, spacing_mm=spacing, width_mm=0.45, randomness=0.0)
    profile = fabric.height_mm[0, 0].mean(dim=0) - fabric.height_mm.mean()
    spectrum = torch.fft.rfft(profile.double()).abs()
    spectrum[0] = 0
    frequencies = torch.fft.rfftfreq(size, d=pitch)
    peak = float(frequencies[int(spectrum.argmax())])
    assert peak in (pytest.approx(1 / spacing, rel=0.05), pytest.approx(1 / (2 * spacing), rel=0.05))


def test_coarse_jute_is_thicker_than_silk():
    jute, silk = make_fabric("jute", size=128), make_fabric("silk", size=128)
    assert float(jute.height_mm.max()) > 5 * float(silk.height_mm.max())


def test_lurex_has_specular_tapes_only_on_metal():
    fabric = make_fabric("lurex", size=128, metal_specular=0.7, metal_albedo=0.3)
    metal = fabric.specular > 0
    assert 0.05 < float(metal.float().mean()) < 0.5
    assert torch.allclose(fabric.specular[metal], torch.tensor(0.7))
    assert torch.allclose(fabric.albedo[metal], torch.tensor(0.3))


def test_print_adds_a_few_micrometres_of_dark_ink():
    base = make_fabric("cotton", size=128, seed=2, albedo=0.8)
    printed = make_fabric("print", size=128, seed=2, ink_thickness_mm=0.004, ink_albedo=0.2)
    lift = printed.height_mm - base.height_mm
    assert float(lift.min()) >= -1e-6 and float(lift.max()) <= 0.004 + 1e-6
    assert float(lift.max()) > 0.003
    inked = lift > 0.0035
    assert float(printed.albedo[inked].mean()) < 0.3


def test_taffeta_wrinkle_is_not_flat():
    fabric = make_fabric("taffeta", size=200, wrinkle_height_mm=0.5)
    assert float(fabric.height_mm.max()) > 0.45


def test_orientation_rotates_the_weave():
    straight = make_fabric("cotton", size=64, randomness=0.0, orientation_deg=0.0)
    turned = make_fabric("cotton", size=64, randomness=0.0, orientation_deg=90.0)
    # a quarter turn maps rows to columns (up to the weave's own phase): compare the row/column spectra

    def spectrum(h, dim):
        return torch.fft.rfft(h[0, 0].mean(dim=dim).double() - h.mean()).abs()

    assert torch.allclose(spectrum(straight.height_mm, 0), spectrum(turned.height_mm, 1), rtol=0.05, atol=1e-3)


def test_fabric_to():
    fabric = make_fabric("silk", size=16).to(dtype=torch.float64)
    assert fabric.height_mm.dtype == torch.float64 and fabric.mask.dtype == torch.bool


def test_errors():
    with pytest.raises(InputError, match="unknown fabric"):
        make_fabric("denim")
    with pytest.raises(InputError, match="no parameter"):
        make_fabric("jute", yarn_colour=3)
    with pytest.raises(InputError, match="size"):
        make_fabric("jute", size=4)
    with pytest.raises(InputError, match="pixel_pitch_mm"):
        make_fabric("jute", pixel_pitch_mm=-math.inf)
