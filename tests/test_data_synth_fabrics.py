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


# --------------------------------------------------------------------------------------------------------------
# The weave family (data_synth.weaves) and the shifted capture conditions (data_synth.shift)
# --------------------------------------------------------------------------------------------------------------


def test_pattern_repeats_of_the_family():
    from data_synth.weaves import WEAVE_PATTERNS, pattern_repeats

    expected = {"plain": (2, 2), "basket": (4, 4), "twill_2_1": (3, 3), "twill_3_1": (4, 4), "satin_5": (5, 5),
                "rib": (2, 4)}
    assert {name: pattern_repeats(p) for name, p in WEAVE_PATTERNS.items()} == expected
    for pattern in WEAVE_PATTERNS.values():  # every end and every pick goes both over and under: it is woven
        assert all(0 < sum(row) < len(row) for row in pattern)
        assert all(0 < sum(col) < len(col) for col in zip(*pattern, strict=True))


@pytest.mark.parametrize("orientation", [0.0, 90.0])
def test_weave_yarn_spacing_and_truth(orientation):
    """A straight plain weave at 0 deg: the warp runs along y, so the height averaged down the columns repeats
    every warp spacing along x; at 90 deg the same along y. The truth lists the denser system first."""
    from data_synth.weaves import WeaveParams, make_weave, weave_truth

    params = WeaveParams("plain", 20.0, 12.5, orientation, crimp_ratio=0.3, randomness=0.0)
    fabric = make_weave(params, size=400, seed=1)
    height = fabric.height_mm[0, 0].double()
    profile = height.mean(dim=0) if orientation == 0.0 else height.mean(dim=1)
    spectrum = torch.fft.rfft(profile - profile.mean()).abs()
    frequencies = torch.fft.rfftfreq(400, d=0.025)
    assert float(frequencies[int(spectrum.argmax())]) == pytest.approx(2.0, rel=0.03)  # 20 ends per cm
    truth = weave_truth(params)
    assert truth.threads_per_cm == (20.0, 12.5)
    assert truth.thread_angles_deg == ((orientation + 90.0) % 180.0, orientation % 180.0)
    assert truth.repeat_threads == (2, 2) and not truth.knit
    assert fabric.params["truth"]["threads_per_cm"] == (20.0, 12.5)


def test_weave_family_draws_are_reproducible_and_in_range():
    from data_synth.weaves import WEAVES, FamilyOptions, draw_weave, draw_weave_params

    options = FamilyOptions()
    drawn = [draw_weave_params(seed) for seed in range(60)]
    assert {p.weave for p in drawn} == set(WEAVES)
    for p in drawn:
        assert 10 <= p.warp_per_cm <= 40 and 10 <= p.weft_per_cm <= 40 and 0 <= p.orientation_deg < 180
        assert options.crimp_ratio[0] <= p.crimp_ratio <= options.crimp_ratio[1]
    assert draw_weave_params(5, weave="rib").weave == "rib"
    a, truth = draw_weave(11, size=64)
    b, _ = draw_weave(11, size=64)
    assert torch.equal(a.height_mm, b.height_mm) and a.name in WEAVES
    assert float(a.height_mm.min()) >= 0.0 and len(truth.repeat_threads) == 2


def test_jersey_is_a_knit_with_repeat_one():
    from data_synth.weaves import WeaveParams, make_weave

    fabric = make_weave(WeaveParams("jersey", 30.0, 38.0, 10.0), size=64, seed=2)
    assert fabric.name == "jersey" and fabric.params["truth"]["knit"]
    assert fabric.params["truth"]["repeat_threads"] == (1, 1)
    assert fabric.params["truth"]["threads_per_cm"] == (38.0, 30.0)  # courses, then wales: the denser first


def test_weave_errors():
    from data_synth.weaves import FamilyOptions, WeaveParams, draw_weave_params, make_weave

    with pytest.raises(InputError, match="unknown weave"):
        WeaveParams("velvet", 20.0, 20.0, 0.0)
    with pytest.raises(InputError, match="warp_per_cm"):
        WeaveParams("plain", -1.0, 20.0, 0.0)
    with pytest.raises(InputError, match="width ratios"):
        WeaveParams("plain", 20.0, 20.0, 0.0, warp_width_ratio=1.2)
    with pytest.raises(InputError, match="unknown weave"):
        draw_weave_params(1, weave="velvet")
    with pytest.raises(InputError, match="size"):
        make_weave(WeaveParams("plain", 20.0, 20.0, 0.0), size=4)
    with pytest.raises(InputError, match="weaves"):
        FamilyOptions(weaves=("velvet",))
    with pytest.raises(InputError, match="density_per_cm"):
        FamilyOptions(density_per_cm=(40.0, 10.0))


def test_shift_regions_are_disjoint_where_they_should_be():
    from data_synth.shift import TEST, TRAIN, draw_shifted

    train = [draw_shifted("plain", seed, TRAIN, size=32) for seed in range(12)]
    test = [draw_shifted("plain", seed, TEST, size=32) for seed in range(40)]
    for draw in train:
        assert 0 <= draw.drawn["orientation_deg"] < 90 and draw.lift_mm <= 0.3 and abs(draw.exposure_stops) <= 0.2
        assert float((draw.led_factors - 1).abs().max()) <= 0.02 and 0.75 <= draw.drawn["dye"] <= 1.0
        assert draw.drawn["print"] in ("none", "blotches")
    for draw in test:
        assert 90 <= draw.drawn["orientation_deg"] < 180 and 0.3 <= draw.lift_mm <= 1.0
        assert not 0.75 < draw.drawn["dye"] < 1.0 and float((draw.led_factors - 1).abs().max()) <= 0.2
    kinds = [d.drawn["print"] for d in test]
    assert kinds.count("imitation") >= 10 and all(d.drawn["imitates"] != "plain" for d in test
                                                  if d.drawn["print"] == "imitation")
    again = draw_shifted("plain", 3, TEST, size=32)
    assert torch.equal(again.fabric.albedo, test[3].fabric.albedo) and again.drawn == test[3].drawn


def test_shifted_capture_keeps_the_nominal_calibration():
    """The capture is lit by drifted LEDs at another exposure; the sample carries the nominal model and card."""
    from dataclasses import replace

    from data_synth.rig import RigConfig, render_card, rig_lights
    from data_synth.shift import TEST, draw_shifted, render_shifted

    rig = RigConfig(size=24, bit_depth=16, noise=False)
    card = render_card(rig)
    draw = draw_shifted("twill_2_1", 2, TEST, size=24)
    sample, capture = render_shifted(draw, rig, card)
    nominal = rig_lights(rig)
    assert torch.equal(sample.lights.intensities, nominal.intensities)
    assert torch.allclose(capture.lights.intensities, nominal.intensities * draw.led_factors.float())
    darker, _ = render_shifted(replace(draw, exposure_stops=draw.exposure_stops - 1.0), rig, card)
    assert float(darker.images.mean()) < 0.6 * float(sample.images.mean())  # a stop less: half the light
    assert torch.equal(sample.reference, card.images)


def test_shift_errors():
    from data_synth.shift import TRAIN, ShiftRegion, draw_shifted

    with pytest.raises(InputError, match="unknown weave"):
        draw_shifted("velvet", 1, TRAIN)
    with pytest.raises(InputError, match="dye"):
        ShiftRegion("x", dye=(), blotch_print=0.1, imitation_print=0.1, orientation_deg=(0, 1), led_drift=0.0,
                    exposure_stops=(0, 0), lift_mm=(0, 0))
    with pytest.raises(InputError, match="add up"):
        ShiftRegion("x", dye=((1.0, 1.0),), blotch_print=0.7, imitation_print=0.7, orientation_deg=(0, 1),
                    led_drift=0.0, exposure_stops=(0, 0), lift_mm=(0, 0))
    with pytest.raises(InputError, match="led_drift"):
        ShiftRegion("x", dye=((1.0, 1.0),), blotch_print=0.0, imitation_print=0.0, orientation_deg=(0, 1),
                    led_drift=1.5, exposure_stops=(0, 0), lift_mm=(0, 0))
