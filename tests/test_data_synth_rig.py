import math

import pytest
import torch

from data_synth import CARD_ALBEDO, FABRICS, make_fabric
from data_synth.rig import (
    RigConfig,
    defocus,
    distant_lights,
    focus_stack,
    render_capture,
    render_card,
    render_sphere,
    rig_lights,
    write_synthetic_capture,
)
from psmini.config import ReconstructionConfig
from psmini.errors import DataFormatError, InputError
from psmini.metrics import angular_error_deg, mean_angular_error
from psmini.pipeline import PhotometricStereo

IDEAL = dict(noise=False, bit_depth=16, vignetting=0.0, ambient=0.0)


def test_rig_geometry():
    leds = rig_lights()
    assert leds.count == 8
    positions = leds.positions_mm.double()
    assert torch.allclose(positions[:, :2].norm(dim=-1), torch.full((8,), 15.8, dtype=torch.float64), atol=1e-5)
    assert torch.allclose(positions[:, 2], torch.full((8,), 10.0, dtype=torch.float64))
    # every LED points at the field centre
    axes = leds.principal_directions.double()
    assert torch.allclose(axes, -positions / positions.norm(dim=-1, keepdim=True), atol=1e-6)
    zenith = math.degrees(math.acos(float(distant_lights().directions[0, 2])))
    assert zenith == pytest.approx(math.degrees(math.atan2(15.8, 10.0)), abs=1e-4)


@pytest.mark.parametrize("name", list(FABRICS))
def test_ideal_directional_render_is_recovered_where_no_led_is_shadowed(name):
    config = RigConfig(size=96, **IDEAL)
    fabric = make_fabric(name, size=96, seed=1)
    capture = render_capture(fabric, config, lights=distant_lights(config))
    result = PhotometricStereo(capture.lights, pixel_pitch_mm=config.pixel_pitch_mm)(capture.images[None],
                                                                                         dark=capture.dark[None])
    errors = angular_error_deg(result.normals, capture.normals[None])
    unshadowed = capture.lit.all(dim=0, keepdim=True)[None] & (fabric.specular == 0)
    assert float(unshadowed.float().mean()) > 0.2
    assert float(errors[unshadowed].mean()) < 0.05
    assert float(errors[unshadowed].max()) < 0.05


def test_card_follows_the_led_model_analytically():
    config = RigConfig(size=33, pixel_pitch_mm=0.3, **IDEAL)
    card = render_card(config, albedo=0.5)
    leds = rig_lights(config, dtype=torch.float64)
    # pixel (row 0, col 32): x = 4.8, y = 4.8, on the card plane
    point = torch.tensor([4.8, 4.8, 0.0], dtype=torch.float64)

    def level(k: int, x: torch.Tensor) -> float:
        offset = leds.positions_mm[k] - x
        r = offset.norm()
        cos_axis = float(-(offset / r) @ leds.principal_directions[k])
        return float(cos_axis / r**2 * offset[2] / r)

    gain = config.exposure / (sum(level(k, torch.zeros(3, dtype=torch.float64)) for k in range(8)) / 8)
    for k in (0, 3):
        expected = 0.5 * gain * level(k, point) + config.black_level
        assert float(card.images[k, 0, 32]) == pytest.approx(expected, abs=2e-5)


def test_sensor_noise_quantisation_and_saturation():
    fabric = make_fabric("lurex", size=64)
    config = RigConfig(size=64, bit_depth=8, exposure=0.9)
    capture = render_capture(fabric, config, seed=5)
    codes = capture.images * 255
    assert torch.allclose(codes, codes.round(), atol=1e-4)  # 8-bit levels
    assert float(capture.images.max()) == 1.0  # the metallic highlights saturate
    again = render_capture(fabric, config, seed=5)
    assert torch.equal(capture.images, again.images)
    assert not torch.equal(capture.images, render_capture(fabric, config, seed=6).images)
    quiet = render_capture(fabric, config.replace(noise=False), seed=5)
    noise = (capture.images - quiet.images).std()
    assert 0.001 < float(noise) < 0.02
    assert float(capture.dark.mean()) == pytest.approx(config.ambient + config.black_level, abs=3 / 255)


def test_flatfielding_cancels_near_light_for_a_flat_fabric():
    # a flat patch of known albedo at the card's height: dividing by the card leaves albedo x cos exactly
    config = RigConfig(size=48, **IDEAL)
    card = render_card(config, albedo=CARD_ALBEDO)
    patch = render_card(config, albedo=0.4, seed=3)
    result = PhotometricStereo(rig_lights(config), config.pixel_pitch_mm, ReconstructionConfig(solver="distant"))(
        patch.images[None], reference=card.images[None], dark=patch.dark[None], reference_dark=card.dark[None],
        card_albedo=CARD_ALBEDO)
    assert float(mean_angular_error(result.normals, patch.normals[None])) < 0.01
    assert torch.allclose(result.albedo, torch.full_like(result.albedo, 0.4), atol=1e-3)


def test_sphere_highlight_reflects_toward_each_led():
    config = RigConfig(size=120, pixel_pitch_mm=0.05, noise=False)
    sphere = render_sphere(config, radius_mm=1.5)
    assert sphere.mask.shape == (1, 120, 120)
    index = (torch.arange(120, dtype=torch.float64) - 59.5) * 0.05
    for k in range(8):
        flat = int(sphere.images[k].argmax())
        row, col = divmod(flat, 120)
        assert bool(sphere.mask[0, row, col])
        # trace the brightest pixel's ray and reflect it: it must point at LED k
        camera = sphere.camera_centre_mm.double()
        ray = torch.tensor([float(index[col]), -float(index[row]), 0.0], dtype=torch.float64) - camera
        ray = ray / ray.norm()
        centre = sphere.centre_mm.double()
        b = float(ray @ (camera - centre))
        t = -b - math.sqrt(b * b - float((camera - centre).square().sum()) + 1.5**2)
        hit = camera + t * ray
        normal = (hit - centre) / 1.5
        reflected = ray - 2 * float(ray @ normal) * normal
        to_led = sphere.lights.positions_mm[k].double() - hit
        angle = math.degrees(math.acos(float(reflected @ to_led / to_led.norm())))
        assert angle < 3.0


def test_focus_stack_is_sharpest_near_the_focal_plane():
    fabric = make_fabric("jute", size=96)
    positions = [-2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 1.0]
    frames = focus_stack(fabric, positions, focal_plane_mm=-0.3, depth_of_field_mm=0.5, noise=0.0,
                         config=RigConfig(size=96))
    assert frames.shape == (7, 96, 96)
    g = frames
    brenner = torch.maximum((g[:, :-2, 2:] - g[:, :-2, :-2]).square(), (g[:, 2:, :-2] - g[:, :-2, :-2]).square())
    score = brenner.mean(dim=(1, 2))
    best = positions[int(score.argmax())]
    expected = -0.3 - float(fabric.height_mm.mean())
    assert abs(best - expected) <= 0.5
    assert float(score[0]) < float(score.max()) / 2 and float(score[-1]) < float(score.max()) / 2


def test_defocus():
    image = torch.rand(1, 1, 32, 32)
    assert torch.equal(defocus(image, torch.zeros(1, 1, 32, 32)), image)
    flat = torch.full((1, 1, 32, 32), 0.3)
    assert torch.allclose(defocus(flat, torch.rand(1, 1, 32, 32) * 5), flat, atol=1e-6)
    blurred = defocus(image, torch.full((1, 1, 32, 32), 3.0))
    assert float(blurred.std()) < float(image.std()) / 2


def test_capture_defocus_blurs_away_from_the_focal_plane():
    fabric = make_fabric("cotton", size=64)
    sharp = render_capture(fabric, RigConfig(size=64, noise=False)).images
    blurred = render_capture(fabric, RigConfig(size=64, noise=False, depth_of_field_mm=0.5, focal_plane_mm=3.0)).images
    assert float(blurred.std()) < float(sharp.std())


def test_write_synthetic_capture_round_trip(tmp_path):
    from psmini.io import load_sample
    from psmini.lights import LEDLights

    sample_dir, card_dir = write_synthetic_capture(tmp_path, "net", size=48, seed=2)
    assert sample_dir == tmp_path / "net" and card_dir == tmp_path / "card"
    sample = load_sample(sample_dir)
    assert isinstance(sample.lights, LEDLights) and sample.count == 8
    assert sample.reference is not None and sample.card_albedo == pytest.approx(CARD_ALBEDO)
    assert sample.normals_gt.shape == (3, 48, 48) and sample.depth_gt.shape == (1, 48, 48)
    fabric = make_fabric("net", size=48, seed=2)
    assert torch.allclose(sample.depth_gt, fabric.height_mm[0])
    assert torch.equal(sample.gt_mask, fabric.mask[0])
    with pytest.raises(DataFormatError):
        write_synthetic_capture(tmp_path, "net", size=48)
    write_synthetic_capture(tmp_path, "net", size=48, light_model="directional", overwrite=True)
    assert type(load_sample(sample_dir).lights).__name__ == "DirectionalLights"


def test_synthetic_captures_share_one_card(tmp_path):
    """A second fabric in the same folder keeps the card of the same rig (as one session's captures share one) and
    records its seed; a card of another rig refuses before anything is written; overwrite replaces it."""
    from psmini.io import load_sample

    write_synthetic_capture(tmp_path, "jute", size=32, seed=4)
    card = (tmp_path / "card" / "led_00.png").read_bytes()
    write_synthetic_capture(tmp_path, "twill", size=32, seed=9)
    assert (tmp_path / "card" / "led_00.png").read_bytes() == card
    assert load_sample(tmp_path / "twill").meta["metadata"]["card_seed"] == 5  # the jute's card (seed 4 + 1)
    alone, _ = write_synthetic_capture(tmp_path / "alone", "twill", size=32, seed=9)
    assert load_sample(alone).meta["metadata"]["card_seed"] == 10
    with pytest.raises(DataFormatError, match="another rig.*size"):
        write_synthetic_capture(tmp_path, "silk", size=48)
    with pytest.raises(DataFormatError, match="another rig.*light_model"):
        write_synthetic_capture(tmp_path, "silk", size=32, light_model="directional")
    assert not (tmp_path / "silk").exists()
    with pytest.raises(DataFormatError, match="twill already exists.*--overwrite"):
        write_synthetic_capture(tmp_path, "twill", size=32)
    write_synthetic_capture(tmp_path, "silk", size=48, overwrite=True)
    assert load_sample(tmp_path / "silk").reference.shape[-1] == 48


def test_output_under_a_file(tmp_path):
    """`psmini synth jute --out afile/x` failed with a FileExistsError traceback after rendering; now a
    DataFormatError naming the file, before any rendering, and nothing written."""
    (tmp_path / "afile").write_text("not a folder")
    for out in (tmp_path / "afile", tmp_path / "afile" / "x"):
        with pytest.raises(DataFormatError, match="afile is a file, not a folder"):
            write_synthetic_capture(out, "jute", size=32)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_errors():
    with pytest.raises(InputError, match="led_count"):
        RigConfig(led_count=2)
    with pytest.raises(InputError, match="bit_depth"):
        RigConfig(bit_depth=9)
    with pytest.raises(InputError, match="vignetting"):
        RigConfig(vignetting=1.5)
    with pytest.raises(InputError, match="pixel pitch|pixels"):
        render_capture(make_fabric("silk", size=32), RigConfig(size=64))
    with pytest.raises(InputError, match="albedo"):
        render_card(albedo=0.0)
    with pytest.raises(InputError, match="radius"):
        render_sphere(radius_mm=-1.0)
    with pytest.raises(InputError, match="position"):
        focus_stack(make_fabric("silk", size=32), [], config=RigConfig(size=32))
    with pytest.raises(InputError, match="lift"):
        render_capture(make_fabric("silk", size=32), RigConfig(size=32), height_offset_mm=float("nan"))
    with pytest.raises(InputError, match="light_model"):
        write_synthetic_capture("unused", "jute", light_model="spot")
    with pytest.raises(InputError, match="unknown fabric"):
        write_synthetic_capture("unused", "denim")
