"""Mirror-sphere calibration accuracy on data_synth's perspective renders at the rig's geometry.

For each sphere placement: the angular error of the light directions found by psmini's perspective model and
by its orthographic model, and by a plain NumPy baseline (the textbook recipe: brightest pixel, circle from the
mask's area and centroid, orthographic reflection), against the exact reflection points (a fixed-point solve of
the mirror condition, independent of the library). Then the LED positions triangulated from 2, 3 and 5
placements. Synthetic data only: it needs no data root.

Then (recorded as its own section) the LED fit from card images (:func:`psmini.fit_leds`): rendered 400×400 cards
of albedo 0.8 at 0 and 1 mm, the errors of the fitted positions, intensities (relative, mean 1), principal
directions and mu against the simulator's LEDs, the fit's residual and its time, for three cases: the nominal start
on the default sensor's noise at 8 bits (what ``benchmarks/nearlight.py`` calibrates with), a start 1 mm and
mu 0.5 off on the same noise, and the same start on noise-free 16-bit cards with 3x the default vignetting.

    python benchmarks/calibration.py [--no-noise] [--seed N] [--leds-only] [--no-record]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import append_results, table  # noqa: E402
from data_synth.rig import RigConfig, render_card, render_sphere, rig_lights  # noqa: E402
from psmini.calibration import calibrate_sphere, card_distance_from_spheres, triangulate_leds  # noqa: E402
from psmini.ledcal import LightFitOptions, fit_leds, fit_lights  # noqa: E402
from psmini.lights import LEDLights  # noqa: E402
from tests.user_light_models import GaussianBeamLEDs, TabulatedBeamLEDs  # noqa: E402  (models a user writes)

PLACES = [(0.0, 0.0), (3.0, 3.0), (-3.0, 3.0), (-3.0, -3.0), (3.0, -3.0)]
RADIUS_MM = 1.5


def exact_directions(render) -> torch.Tensor:
    """Directions from the exact reflection points to the LEDs (normal bisecting camera and LED)."""
    leds = render.lights.positions_mm.double()
    camera, centre = render.camera_centre_mm.double(), render.centre_mm.double()
    normal = torch.nn.functional.normalize((leds + camera) / 2 - centre, dim=-1)
    for _ in range(200):
        point = centre + render.radius_mm * normal
        normal = torch.nn.functional.normalize(
            torch.nn.functional.normalize(camera - point, dim=-1) + torch.nn.functional.normalize(leds - point, dim=-1),
            dim=-1,
        )
    return leds - (centre + render.radius_mm * normal)


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    a, b = a.double(), b.double()
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))).numpy()


def numpy_baseline(images: np.ndarray, dark: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Textbook recipe: circle from the mask's area and centroid, brightest pixel, orthographic reflection."""
    rows, cols = np.nonzero(mask)
    cu, cv, radius = cols.mean(), rows.mean(), np.sqrt(mask.sum() / np.pi)
    directions = []
    for image in images - dark:
        v, u = np.unravel_index(np.argmax(np.where(mask, image, -np.inf)), image.shape)
        nx, ny = (u - cu) / radius, -(v - cv) / radius
        normal = np.array([nx, ny, np.sqrt(max(0.0, 1 - nx * nx - ny * ny))])
        directions.append(2 * normal[2] * normal - np.array([0.0, 0.0, 1.0]))
    return np.array(directions)


CARD_ALBEDO = 0.8
CARD_HEIGHTS = (0.0, 1.0)
LED_CASES = (
    ("nominal start, 8-bit noisy", RigConfig(noise=True, bit_depth=8, intensity_spread=0.05), False),
    ("1 mm and mu 0.5 off, 8-bit noisy", RigConfig(noise=True, bit_depth=8, intensity_spread=0.1), True),
    ("1 mm and mu 0.5 off, noise-free 16-bit, vignetting 0.45",
     RigConfig(noise=False, bit_depth=16, intensity_spread=0.1, vignetting=0.45), True),
)


def perturbed_start(config: RigConfig) -> LEDLights:
    """The nominal rig with every LED moved by 1 mm (a fixed random direction each) and mu 1.5 instead of 1."""
    nominal = rig_lights(config.replace(intensity_spread=0.0), dtype=torch.float64)
    offsets = torch.randn(config.led_count, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    offsets = offsets / offsets.norm(dim=-1, keepdim=True)
    return LEDLights(nominal.positions_mm + offsets, nominal.principal_directions, None,
                     torch.full((config.led_count,), 1.5, dtype=torch.float64))


def led_errors(lights, truth: LEDLights) -> list[float]:
    """Largest and mean position error (mm), largest intensity error (%), largest principal-direction error (°),
    largest mu error."""
    position = (lights.positions_mm.double() - truth.positions_mm.double()).norm(dim=-1)
    relative = truth.intensities.double() / truth.intensities.double().mean()
    intensity = (lights.intensities.double() / relative - 1).abs().max()
    direction = angle_deg(lights.principal_directions, truth.principal_directions).max()
    mu = (lights.mu.double() - truth.mu.double()).abs().max()
    return [float(position.max()), float(position.mean()), 100 * float(intensity), float(direction), float(mu)]


def led_fits() -> str:
    """The LED fit's errors on rendered cards, one row per case."""
    torch.set_num_threads(1)
    rows = []
    for name, config, perturbed in LED_CASES:
        cards = [render_card(config, CARD_ALBEDO, seed=10 + i, height_mm=h) for i, h in enumerate(CARD_HEIGHTS)]
        images, dark = torch.stack([c.images for c in cards]), torch.stack([c.dark for c in cards])
        start = time.perf_counter()
        fit = fit_leds(images, CARD_HEIGHTS, config.pixel_pitch_mm, perturbed_start(config) if perturbed else "nominal",
                       card_albedo=CARD_ALBEDO, dark=dark, saturation_level=1.0)
        seconds = time.perf_counter() - start
        errors = led_errors(fit.lights, rig_lights(config, dtype=torch.float64))
        iterations = "+".join(str(stage["iterations"]) for stage in fit.stages)
        rows.append([name, *errors, fit.residual_rms, iterations, seconds])
        print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in rows[-1]), flush=True)
    header = ["case", "position max mm", "position mean mm", "intensity max %", "principal direction max °",
              "mu max error", "residual rms", "iterations (point+led)", "seconds"]
    return (
        f"data_synth `render_card`: a matte card of albedo {CARD_ALBEDO} at {CARD_HEIGHTS[0]:g} and "
        f"{CARD_HEIGHTS[1]:g} mm under the 8 LEDs of the rig (31.6 mm ring, 10 mm up, mu 1, intensities spread as "
        "named in the config), 400×400 px at 0.025 mm/px, dark frame subtracted, readings at full scale dropped. "
        "`fit_leds` with its default options (L-BFGS, point then LED stage, 32×32 pooled cards, Huber 0.05), from "
        "the nominal ring or from a start with every LED 1 mm off and mu 1.5. Errors against the simulator's LEDs; "
        "intensities relative (mean 1); residual as a fraction of the mean card reading; one torch thread.\n\n"
        + table(header, rows)
    )


def user_model_fits() -> str:
    """fit_lights on models a user writes, each on noisy 8-bit cards rendered with that model, one row each."""
    config = RigConfig(noise=True, bit_depth=8, intensity_spread=0.1)
    leds = rig_lights(config, dtype=torch.float64)
    nominal = rig_lights(config.replace(intensity_spread=0.0), dtype=torch.float64)
    offsets = torch.randn(config.led_count, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    offsets = offsets / offsets.norm(dim=-1, keepdim=True)
    angles = torch.arange(13, dtype=torch.float64) * 2.5
    tabulated = TabulatedBeamLEDs.from_leds(leds)
    tabulated.beam = tabulated.beam * (1 - 0.2 * (angles / 20) ** 2)  # narrower than the LEDs' cos beam
    table_start = TabulatedBeamLEDs.from_leds(nominal, learnable=True)
    with torch.no_grad():
        table_start.positions_mm.add_(0.5 * offsets)
    cases = [
        ("LEDLights, every parameter (1 mm and mu 0.5 off)", leds,
         LEDLights(nominal.positions_mm + offsets, nominal.principal_directions, None,
                   torch.full((8,), 1.5, dtype=torch.float64), learnable=True), None),
        ("Gaussian-beam LEDLights subclass, every parameter (1 mm and width 0.2 off)",
         GaussianBeamLEDs(leds.positions_mm, leds.principal_directions, leds.intensities,
                          torch.full((8,), 0.5, dtype=torch.float64)),
         GaussianBeamLEDs(nominal.positions_mm + offsets, nominal.principal_directions, None,
                          torch.full((8,), 0.7, dtype=torch.float64), learnable=True), None),
        ("tabulated beam, positions and table (0.5 mm off, started from the cos beam)", tabulated, table_start,
         ("positions_mm", "beam")),
    ]
    rows = []
    for name, truth, start, parameters in cases:
        cards = [render_card(config, CARD_ALBEDO, seed=10 + i, height_mm=h, lights=truth)
                 for i, h in enumerate(CARD_HEIGHTS)]
        images, dark = torch.stack([c.images for c in cards]), torch.stack([c.dark for c in cards])
        for optimizer in ("lm", "lbfgs"):
            begin = time.perf_counter()
            fit = fit_lights(start, images, CARD_HEIGHTS, config.pixel_pitch_mm, card_albedo=CARD_ALBEDO, dark=dark,
                             saturation_level=1.0, options=LightFitOptions(parameters=parameters, optimizer=optimizer))
            seconds = time.perf_counter() - begin
            position = (fit.lights.positions_mm.detach() - truth.positions_mm).norm(dim=-1)
            if isinstance(truth, TabulatedBeamLEDs):
                ratio = (fit.lights.beam.detach() / truth.beam)[:, :7]  # the samples the cards see (0-15°)
                other = f"table {100 * float((ratio / ratio.mean() - 1).abs().max()):.3g} %"
            elif isinstance(truth, GaussianBeamLEDs):
                other = f"width {float((fit.lights.width.detach() - truth.width).abs().max()):.2g} rad"
            else:
                relative = fit.lights.intensities.detach() / fit.lights.intensities.detach().mean()
                intensity = (relative / (truth.intensities / truth.intensities.mean()) - 1).abs().max()
                other = (f"intensity {100 * float(intensity):.3g} %, mu "
                         f"{float((fit.lights.mu.detach() - truth.mu).abs().max()):.2g}")
            rows.append([name, optimizer, float(position.max()), float(position.mean()), other, fit.residual_rms,
                         fit.stages[-1]["iterations"], seconds])
            print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in rows[-1]), flush=True)
    header = ["model", "optimizer", "position max mm", "position mean mm", "beam", "residual rms", "iterations",
              "seconds"]
    return ("`fit_lights` with its default options (Levenberg–Marquardt, 50 steps at most) and with L-BFGS "
            "(400 iterations), on the same kind of cards (400×400, 8-bit noise, 0 and 1 mm) rendered with each "
            "model; starts every LED 0.5-1 mm off.\n\n" + table(header, rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-noise", action="store_true", help="render without sensor noise (quantisation stays)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--leds-only", action="store_true", help="only the LED fit from card images")
    parser.add_argument("--no-record", action="store_true", help="print, do not append to benchmarks/results.md")
    args = parser.parse_args()
    if not args.leds_only:
        spheres(args)
    body = led_fits() + "\n\n" + user_model_fits()
    print(body)
    if not args.no_record:
        append_results("LED calibration from card images (benchmarks/calibration.py)", body)


def spheres(args: argparse.Namespace) -> None:
    """The mirror-sphere part: light directions per placement, then LED positions from 2, 3 and 5 placements."""
    config = RigConfig(noise=not args.no_noise)
    focal = config.working_distance_mm / config.pixel_pitch_mm
    centre_px = (config.size - 1) / 2
    intrinsics = torch.tensor([[focal, 0, centre_px], [0, focal, centre_px], [0, 0, 1]], dtype=torch.float64)

    rows, calibrations, renders = [], [], []
    for index, (x, y) in enumerate(PLACES):
        render = render_sphere(config, RADIUS_MM, (x, y, RADIUS_MM), seed=args.seed + index)
        truth = exact_directions(render)
        start = time.perf_counter()
        perspective = calibrate_sphere(render.images, dark=render.dark, intrinsics=intrinsics, radius_mm=RADIUS_MM)
        psmini_s = time.perf_counter() - start
        orthographic = calibrate_sphere(render.images, dark=render.dark, mask=render.mask)
        start = time.perf_counter()
        baseline = numpy_baseline(render.images.numpy(), render.dark.numpy(), render.mask[0].numpy())
        numpy_s = time.perf_counter() - start
        persp_err = angle_deg(perspective.directions, truth)
        ortho_err = angle_deg(orthographic.directions, truth)
        base_err = angle_deg(torch.from_numpy(baseline), truth)
        rows.append([f"({x:+.0f}, {y:+.0f})", float(persp_err.max()), float(persp_err.mean()), float(ortho_err.max()),
                     float(ortho_err.mean()), float(base_err.max()), float(base_err.mean()),
                     float(base_err.mean() / persp_err.mean()), psmini_s, numpy_s])
        calibrations.append(perspective)
        renders.append(render)

    direction_table = table(
        ["sphere centre (mm)", "perspective max °", "perspective mean °", "orthographic max °", "orthographic mean °",
         "numpy baseline max °", "numpy baseline mean °", "baseline / perspective", "psmini s (auto-detect)",
         "numpy s"],
        rows,
    )
    truth_positions = renders[0].lights.positions_mm.double()
    position_rows = []
    for subset in ([1, 3], [0, 1, 2], [0, 1, 2, 3, 4]):
        chosen = [calibrations[i] for i in subset]
        positions, residuals = triangulate_leds(chosen)
        distance = card_distance_from_spheres(chosen)
        positions = positions.double() + torch.tensor([0.0, 0.0, distance], dtype=torch.float64)
        error = (positions - truth_positions).norm(dim=-1).numpy()
        position_rows.append([len(subset), ", ".join(rows[i][0] for i in subset), float(error.max()),
                              float(error.mean()), float(residuals.max()), distance - config.working_distance_mm])
    position_table = table(
        ["placements", "centres (mm)", "max error mm", "mean error mm", "max residual mm", "card distance error mm"],
        position_rows,
    )
    body = (
        f"data_synth `render_sphere`: mirror sphere of radius {RADIUS_MM} mm resting on the card, 8 LEDs on a 31.6 mm "
        f"ring 10 mm up, pinhole camera {config.working_distance_mm} mm above the card ({config.size}×{config.size} "
        "px, "
        f"{config.pixel_pitch_mm} mm/px at the card), {'noise and ' if config.noise else ''}{config.bit_depth}-bit "
        "quantisation, float32 renders. Errors against the exact reflection points. psmini: perspective = "
        "silhouette found automatically + tangent-cone centre + sub-pixel highlight + ray reflection; orthographic = "
        "same highlights, view (0, 0, 1), circle from the mask. NumPy baseline: brightest pixel, circle from the "
        "mask's area and centroid, orthographic reflection.\n\n"
        f"{direction_table}\n\nLED positions (least-squares intersection of the reflected rays; card plane from the "
        f"spheres resting on it):\n\n{position_table}"
    )
    print(body)
    if not args.no_record:
        append_results("Mirror-sphere calibration (benchmarks/calibration.py)", body)


if __name__ == "__main__":
    main()
