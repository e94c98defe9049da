"""How far cloth captures alone pin the LEDs down: self-calibration through the near-light reconstruction.

The experiment of section 5 of ``notebooks/04_near_light.ipynb``, measured further than a notebook can afford.
Three flat-fielded captures of the rig at 64² over the 10 mm field (jute on the card, twill 1 mm above it, knit at
0.5 mm; the cloths' mean heights known), LED positions pushed 0.5 mm in a random direction each, fitted through
:func:`psmini.solve_near_light` by minimising the re-rendering error of each reconstruction (each reading weighted
by the solver's own robust weight, the readings predicted within three noise levels of zero left out: the sensor
clips their noise at 0 and the solver's max is smoothed there, so their mean is not the model's; with them in, the
fit on the means of 16 frames ended 0.78 mm off, its minimum pulled by them, and without them 0.12 mm).

1. Adam (learning rate 0.05) on the noisy renders, three perturbations: the mean and largest position error after
   30, 60 and 120 steps, and the loss there against the loss at the true positions.
2. Gauss–Newton with Levenberg damping (the exact gradient through the solve, the curvature with each pixel's
   albedo-normal projected out), on the noisy renders from the same three perturbations and on noise-free renders
   without cast shadows: where the loss's minimum lies, the LEDs' common shift there, and its loss against the true
   positions'. Adam's figures after a given number of steps are where a slow descent along a flat valley has got to;
   these are where it ends.
3. What moves that minimum: Gauss–Newton again with the ring's common height held at the true LEDs' mean (the gauge
   that cloth captures pin least, taken from the rig's drawing), with the card's noise alone (noise-free cloths) and
   the cloths' alone (a noise-free card), and on the same three cloths at 128² (four times the pixels), noisy and
   noise-free.
4. Cloths of lower relief (cotton, twill, taffeta) at 128²: noise-free (where the minimum lies when near light's
   normals are unbiased), noisy, and with each noise alone (how far the noise moves it).
5. ``--projection`` (a section of its own): no reconstruction at all, a textbook variable projection at the cloths'
   true heights with fixed inverse-variance weights (:func:`projection_fit`), noise-free, with three noise
   realisations and on the means of 16 and 64 frames: whether the captures themselves measure the LEDs to 0.1 mm.
6. ``--frames`` (a section of its own): Gauss–Newton through the reconstruction on the means of 16 and 64 frames
   per capture (what averaging frames, which a webcam affords, buys) of the cloths of lower relief, from three
   pushes in each of two noise realisations.

Run:  python benchmarks/selfcalibration.py [--steps 120] [--projection | --frames] [--no-record]
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import append_results, table  # noqa: E402

SIZE = 64
CLOTHS = (("jute", 0.0), ("twill", 1.0), ("knit", 0.5))
# cloths of lower relief (no holes, no walls of a jute's or a knit's yarns), whose normals near light recovers unbiased
SMOOTH_CLOTHS = (("cotton", 0.0), ("twill", 1.0), ("taffeta", 0.5))
SMOOTH_NAMES = ", ".join(name for name, _ in SMOOTH_CLOTHS)
PUSH_MM = 0.5
# readings predicted within this many noise levels of zero stay out of the loss (as in near light's own reliability)
LIT_SIGMAS = 3.0


def captures(size: int = SIZE, noisy_card: bool = True, noisy_cloths: bool = True, cloths=CLOTHS,
             noise_seed: int = 0, truth: bool = False, **render_options) -> tuple[object, list[dict]]:
    """The true LEDs and flat-fielded captures (float64) of ``cloths`` (name, lift in mm) at ``size``² over the
    10 mm field; a noise-free card or cloths are rendered at 16 bits; ``noise_seed`` offsets the cloths' noise. With
    ``truth``, each capture also keeps its true height (``depth``, mm), its noise-free flat-fielded images (``clean``,
    a second render) and the sensor it was rendered with (``config``)."""
    import psmini
    from data_synth import CARD_ALBEDO, make_fabric
    from data_synth.rig import RigConfig, render_capture, render_card, rig_lights

    config = RigConfig(size=size, pixel_pitch_mm=10.0 / size, **render_options)
    noise_free = config.replace(noise=False, bit_depth=16)
    card = render_card(config if noisy_card else noise_free, CARD_ALBEDO, seed=1)

    def flatten(shot):
        return psmini.flatfield(shot.images[None], card.images[None], shot.dark[None], card.dark[None], CARD_ALBEDO,
                                saturation_level=1.0, card_smoothing_px=3.0)

    flat_cloths = []
    for index, (name, lift) in enumerate(cloths):
        fabric = make_fabric(name, size=size, pixel_pitch_mm=config.pixel_pitch_mm, seed=index)
        shot = render_capture(fabric, config if noisy_cloths else noise_free, seed=index + noise_seed,
                              height_offset_mm=lift)
        flat = flatten(shot)
        flat_cloths.append({"images": flat.images.double(), "valid": flat.valid, "gain": flat.gain.double(),
                            "height": float(shot.depth_mm.mean()), "pitch": config.pixel_pitch_mm})
        if truth:
            clean = render_capture(fabric, noise_free, seed=index, height_offset_mm=lift)
            flat_cloths[-1] |= {"depth": shot.depth_mm[None].double(), "clean": flatten(clean).images.double(),
                                "config": config if noisy_cloths else noise_free}
    return rig_lights(config), flat_cloths


def averaged(frames: int) -> dict:
    """Render options of the mean of ``frames`` captures of the rig's default 10-bit sensor: read and shot noise
    variance divided by ``frames``, the quantisation, dithered by the noise, that of a 16-bit render."""
    from data_synth.rig import RigConfig

    sensor = RigConfig()
    return {"full_well": sensor.full_well * frames, "read_noise": sensor.read_noise / frames**0.5, "bit_depth": 16}


def pushed(rig, seed: int):
    """A learnable copy of the rig's LEDs, each pushed PUSH_MM in a random direction."""
    import psmini

    push = torch.randn(rig.count, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    start = rig.positions_mm.double() + PUSH_MM * push / push.norm(dim=1, keepdim=True)
    return psmini.LEDLights(start, rig.principal_directions.double(), rig.intensities.double(), rig.mu.double(),
                            learnable=True)


def reconstruct(model, cloth):
    import psmini

    options = psmini.NearLightOptions(estimate_offset=False, estimate_tilt=False, estimate_bend=False,
                                      initial_height_mm=cloth["height"])
    return psmini.solve_near_light(cloth["images"], model, cloth["pitch"], 0.0, valid=cloth["valid"],
                                   options=options, gain=cloth["gain"])


def shading(model, result):
    """m · L per reading (B, K, H, W) before the clamp at 0, and the light vectors."""
    import psmini

    vectors = psmini.near_light_vectors(model, result.depth, 10.0 / result.depth.shape[-1], card_height_mm=0.0)
    return (vectors * (result.albedo * result.normals).unsqueeze(1)).sum(2), vectors


def reading_std(result, gain: torch.Tensor, predicted: torch.Tensor) -> torch.Tensor:
    """Each reading's noise standard deviation under the noise model the solver fitted, at its predicted value."""
    read, shot, model = (part.view(-1, 1, 1, 1) for part in result.noise.unbind(1))
    reading = predicted.clamp_min(0)
    return (gain.square() * read + gain * shot * reading + model * reading.square()).sqrt()


def loss_of(model, cloths, curvature: bool = False):
    """The summed re-rendering loss (and, with ``curvature``, its Gauss–Newton curvature in the positions with each
    pixel's m projected out: variable projection). A reading predicted within :data:`LIT_SIGMAS` noise levels of
    zero is left out: the sensor clips its noise at 0 and the solver's max is smoothed there, so its mean is not
    the model's."""
    total, hessian = 0.0, torch.zeros(3 * model.count, 3 * model.count, dtype=torch.float64)
    for cloth in cloths:
        result = reconstruct(model, cloth)
        predicted, vectors = shading(model, result)
        lit = predicted > LIT_SIGMAS * reading_std(result, cloth["gain"], predicted.detach())
        weight = (result.weights * cloth["valid"] * result.mask * lit).detach()
        residual = torch.where(weight > 0, cloth["images"] - predicted.clamp_min(0), 0)
        total = total + (weight * residual.square()).sum() / weight.sum()
        if curvature:
            hessian = hessian + _curvature(model, result, vectors.detach(), weight)
    return total, hessian


@contextlib.contextmanager
def positions_swapped(model, flat: torch.Tensor):
    """The model's learnable positions swapped for the plain tensor ``flat`` (3K,) inside the block (a forward-mode
    Jacobian differentiates through it), put back after."""
    positions = model.positions_mm
    del model.positions_mm
    model.positions_mm = flat.view(-1, 3)
    try:
        yield model
    finally:
        del model.positions_mm
        model.positions_mm = positions


def _curvature(model, result, vectors, weight):
    frozen = type(result)(*(t.detach() for t in (result.albedo, result.normals, result.p, result.q, result.depth,
                                                 result.mask)))

    def readings(flat):
        with positions_swapped(model, flat):
            return shading(model, frozen)[0]

    jacobian = torch.func.jacfwd(readings)(model.positions_mm.detach().flatten())  # (B, K, H, W, 3K)
    weighted = weight.unsqueeze(2) * vectors
    gram = torch.einsum("bkihw,bkjhw->bhwij", weighted, vectors) + 1e-12 * torch.eye(3, dtype=torch.float64)
    projection = torch.linalg.solve(gram, torch.einsum("bkihw,bkhwp->bhwip", weighted, jacobian))
    projected = jacobian - torch.einsum("bkihw,bhwip->bkhwp", vectors, projection)
    return 2 * torch.einsum("bkhw,bkhwp,bkhwq->pq", weight, projected, projected) / weight.sum()


def position_error(model, rig) -> torch.Tensor:
    return (model.positions_mm.detach() - rig.positions_mm.double()).norm(dim=1)


def precise_loss(model, cloths) -> float:
    """The loss as a number, its solves as precise as a differentiated loss's: the model's parameters require
    gradients (under ``no_grad`` the weighted integration stops at a relative residual of 1e-2, whose error would
    decide comparisons near the minimum)."""
    return float(loss_of(model, cloths)[0].detach())


def at_truth(model, rig, cloths) -> float:
    saved = model.positions_mm.detach().clone()
    with torch.no_grad():
        model.positions_mm.copy_(rig.positions_mm.double())
    loss = precise_loss(model, cloths)
    with torch.no_grad():
        model.positions_mm.copy_(saved)
    return loss


def adam(rig, cloths, seed: int, steps: int) -> list[object]:
    model = pushed(rig, seed)
    optimizer = torch.optim.Adam([model.positions_mm], lr=0.05)
    row: list[object] = [f"Adam, noisy, seed {seed}"]
    for step in range(1, steps + 1):
        optimizer.zero_grad()
        loss = loss_of(model, cloths)[0]
        loss.backward()
        optimizer.step()
        if step in (30, 60, 120) or step == steps:
            error = position_error(model, rig)
            row.append(f"{float(error.mean()):.3f} / {float(error.max()):.3f}")
    return [*row, "", f"{precise_loss(model, cloths) / at_truth(model, rig, cloths):.4f}"]


def gauss_newton(rig, cloths, seed: int, label: str, iterations: int = 8,
                 ring_height_fixed: bool = False) -> list[object]:
    """Levenberg-damped Gauss–Newton from the pushed LEDs; with ``ring_height_fixed`` the LEDs' mean height is set to
    the true one and every step keeps it (the step projected off the common height, a gauge constraint)."""
    model = pushed(rig, seed)
    free = torch.eye(3 * model.count, dtype=torch.float64)
    if ring_height_fixed:
        with torch.no_grad():
            model.positions_mm[:, 2] += rig.positions_mm.double()[:, 2].mean() - model.positions_mm[:, 2].mean()
        common = torch.zeros(3 * model.count, dtype=torch.float64)
        common[2::3] = model.count**-0.5
        free = free - torch.outer(common, common)
    damping = 1e-3
    for _ in range(iterations):
        model.positions_mm.grad = None
        loss, hessian = loss_of(model, cloths, curvature=True)
        loss.backward()
        gradient = free @ model.positions_mm.grad.flatten()
        # the fixed direction keeps its own curvature, so that the system stays regular; the step has no part in it
        hessian = free @ hessian @ free + (torch.eye(len(free), dtype=hessian.dtype) - free) * hessian.diagonal().mean()
        saved = model.positions_mm.detach().clone()
        while damping < 1e6:
            step = -free @ torch.linalg.solve(hessian + damping * torch.diag(hessian.diagonal()), gradient)
            with torch.no_grad():
                model.positions_mm.copy_(saved + step.view(-1, 3))
            if precise_loss(model, cloths) < float(loss.detach()):
                damping = max(damping / 3, 1e-6)
                break
            with torch.no_grad():
                model.positions_mm.copy_(saved)
            damping *= 10
        else:  # no step lowers the loss: at its minimum (later iterations would only evaluate it again)
            break
    error = position_error(model, rig)
    shift = (model.positions_mm.detach() - rig.positions_mm.double()).mean(0)
    final = precise_loss(model, cloths)
    return [f"Gauss–Newton, {label}, seed {seed}", "", "", f"{float(error.mean()):.3f} / "
            f"{float(error.max()):.3f}", ", ".join(f"{v:+.3f}" for v in shift.tolist()),
            f"{final / at_truth(model, rig, cloths):.4f}"]


def projection_fit(rig, cloths, seed: int, label: str, steps: int = 12) -> list[object]:
    """Textbook variable projection, no reconstruction: at each cloth's true height, each pixel's m by weighted least
    squares, the weights each reading's inverse variance under the rig's sensor model at its noise-free value (read
    noise, shot noise, quantisation, times the flat-field's gain squared; readings under 0.02 left out), fixed; then
    Levenberg–Marquardt steps on the whitened residuals with m projected out (the Jacobian column by column, forward
    mode). Where its minimum lies says how well the captures themselves measure the LEDs."""
    import psmini

    model = pushed(rig, seed)
    for cloth in cloths:
        sensor, clean, gain = cloth["config"], cloth["clean"].clamp_min(0), cloth["gain"]
        step = 1 / (2**sensor.bit_depth - 1)
        raw = clean / gain.clamp_min(1e-12)
        noise = (sensor.read_noise**2 + raw / sensor.full_well) if sensor.noise else torch.zeros_like(raw)
        variance = gain.square() * (noise + step**2 / 12)
        cloth["weight"] = torch.where(cloth["valid"] & (gain > 0) & (clean > 0.02), 1 / variance, 0)
    largest = max(float(cloth["weight"].amax()) for cloth in cloths)
    for cloth in cloths:  # relative weights (the minimum is the same), so that the ridge below is relative too
        cloth["weight"] = cloth["weight"] / largest

    def whitened(flat):
        residuals = []
        with positions_swapped(model, flat):
            for cloth in cloths:
                lights = psmini.near_light_vectors(model, cloth["depth"], cloth["pitch"], card_height_mm=0.0)
                weighted = cloth["weight"].unsqueeze(2) * lights
                gram = torch.einsum("bkihw,bkjhw->bhwij", weighted, lights) + 1e-9 * torch.eye(3, dtype=lights.dtype)
                m = torch.linalg.solve(gram, torch.einsum("bkihw,bkhw->bhwi", weighted, cloth["images"]))
                predicted = torch.einsum("bkihw,bhwi->bkhw", lights, m)
                residuals.append((cloth["weight"].sqrt() * (cloth["images"] - predicted)).flatten())
        return torch.cat(residuals)

    x, damping = model.positions_mm.detach().flatten().clone(), 1e-3
    basis = torch.eye(len(x), dtype=x.dtype)
    for _ in range(steps):
        with torch.no_grad():  # the model's other parameters are learnable: no graph is wanted here
            residual = whitened(x)
        # each column copied out: a forward-mode tangent left as returned holds on to the solve's dual buffers
        jacobian = torch.stack([torch.func.jvp(whitened, (x,), (basis[i],))[1].detach().clone()
                                for i in range(len(x))], 1)
        hessian, gradient = jacobian.T @ jacobian, jacobian.T @ residual
        while damping < 1e8:
            trial = x - torch.linalg.solve(hessian + damping * torch.diag(hessian.diagonal()), gradient)
            with torch.no_grad():
                better = float(whitened(trial).square().sum()) < float(residual.square().sum())
            if better:
                x, damping = trial, max(damping / 3, 1e-7)
                break
            damping *= 10
    offset = x.view(-1, 3) - rig.positions_mm.double()
    error = offset.norm(dim=1)
    return [f"variable projection at the true height, {label}, seed {seed}",
            f"{float(error.mean()):.3f} / {float(error.max()):.3f}", ", ".join(f"{v:+.3f}" for v in offset.mean(0))]


def projection_only(args: argparse.Namespace) -> int:
    """``--projection``: where the minimum of a textbook fit on the captures themselves lies, without noise, with
    three noise realisations and on the means of 16 and 64 frames."""
    rows = []
    for label, options in (("noise-free", {"noisy_card": False, "noisy_cloths": False}), ("noisy", {}),
                           ("noisy, another realisation", {"noise_seed": 100}),
                           ("noisy, a third realisation", {"noise_seed": 200}),
                           ("means of 16 frames", averaged(16)),
                           ("means of 16 frames, another realisation", {"noise_seed": 100, **averaged(16)}),
                           ("means of 64 frames", averaged(64))):
        rig, cloths = captures(size=2 * SIZE, cloths=SMOOTH_CLOTHS, truth=True, **options)
        rows.append(projection_fit(rig, cloths, 6, f"{label}, {2 * SIZE}², {SMOOTH_NAMES}"))
    report = table(["fit", "at the end: mean / largest (mm)", "mean shift of the LEDs x, y, z (mm)"], rows)
    note = (f"LEDs pushed {PUSH_MM} mm each (seed 6); cotton on the card, twill 1 mm and taffeta 0.5 mm above it, at "
            f"{2 * SIZE}² over 10 mm, 10-bit with noise (the card too), noise-free at 16 bits, or the means of 16 "
            "or 64 frames (1/N of the noise variance, 16 bits), flat-fielded by the card smoothed by 3 px. "
            "No reconstruction: each pixel's albedo-normal by weighted least squares at the "
            "true height, weights the sensor model's inverse variance at the noise-free reading (fixed), 12 "
            "Levenberg–Marquardt steps on the whitened residuals. One torch thread.")
    print(report)
    print(note)
    if not args.no_record:
        append_results("Self-calibration: textbook variable projection at the true heights "
                       "(benchmarks/selfcalibration.py --projection)", report + "\n\n" + note)
    return 0


def averaged_frames(args: argparse.Namespace) -> int:
    """``--frames``: Gauss–Newton through the reconstruction on the means of 16 and 64 frames of the cloths of lower
    relief, from three pushes and in two noise realisations."""
    rows = []
    for frames in (16, 64):
        for realisation, noise_seed in enumerate((0, 100), 1):
            rig, cloths = captures(size=2 * SIZE, cloths=SMOOTH_CLOTHS, noise_seed=noise_seed, **averaged(frames))
            for seed in (5, 6, 7):
                row = gauss_newton(rig, cloths, seed, f"means of {frames} frames, realisation {realisation}, "
                                                      f"{2 * SIZE}², {SMOOTH_NAMES}")
                rows.append([row[0], *row[3:]])
    report = table(["fit", "at the end: mean / largest (mm)", "mean shift of the LEDs x, y, z (mm)",
                    "loss / loss at the true positions"], rows)
    note = (f"LEDs pushed {PUSH_MM} mm each (the seed names the push); {SMOOTH_NAMES} at 0, 1 and 0.5 mm above "
            f"the card, {2 * SIZE}² over 10 mm, mean heights known; every capture (the card's too) the mean of 16 "
            "or 64 frames of the rig's default 10-bit sensor (1/N of its noise variance, 16 bits), two noise "
            "realisations; flat-fielded by the card smoothed by 3 px. Gauss–Newton with Levenberg damping to the "
            "minimum of the re-rendering loss through the near-light reconstruction (the readings predicted within "
            f"{LIT_SIGMAS:g} noise levels of zero left out). One torch thread.")
    print(report)
    print(note)
    if not args.no_record:
        append_results("Self-calibration on averaged frames (benchmarks/selfcalibration.py --frames)",
                       report + "\n\n" + note)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=120, help="Adam steps per perturbation")
    parser.add_argument("--no-record", action="store_true", help="print only; do not append to results.md")
    parser.add_argument("--projection", action="store_true",
                        help="only the textbook variable projection at the true heights (section 5 of the docstring)")
    parser.add_argument("--frames", action="store_true",
                        help="only Gauss–Newton on the means of 16 and 64 frames (section 6 of the docstring)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.projection:
        return projection_only(args)
    if args.frames:
        return averaged_frames(args)
    rig, noisy = captures()
    rows = [adam(rig, noisy, seed, args.steps) for seed in (5, 6, 7)]
    rows += [gauss_newton(rig, noisy, seed, "noisy") for seed in (5, 6, 7)]
    rows += [gauss_newton(rig, noisy, seed, "noisy, the ring's height fixed", ring_height_fixed=True)
             for seed in (5, 6, 7)]
    rig, clean = captures(noise=False, shadows=False)
    rows.append(gauss_newton(rig, clean, 6, "noise-free, no cast shadows"))
    rig, cloths = captures(noisy_cloths=False)
    rows.append(gauss_newton(rig, cloths, 6, "the card's noise alone"))
    rig, cloths = captures(noisy_card=False)
    rows.append(gauss_newton(rig, cloths, 6, "the cloths' noise alone"))
    rig, cloths = captures(size=2 * SIZE)
    rows += [gauss_newton(rig, cloths, seed, f"noisy, {2 * SIZE}²") for seed in (5, 6)]
    rig, cloths = captures(size=2 * SIZE, noisy_card=False, noisy_cloths=False)
    rows.append(gauss_newton(rig, cloths, 6, f"noise-free, {2 * SIZE}²"))
    for label, noise in (("noise-free", {"noisy_card": False, "noisy_cloths": False}), ("noisy", {}),
                         ("the card's noise alone", {"noisy_cloths": False}),
                         ("the cloths' noise alone", {"noisy_card": False})):
        rig, cloths = captures(size=2 * SIZE, cloths=SMOOTH_CLOTHS, **noise)
        rows.append(gauss_newton(rig, cloths, 6, f"{label}, {2 * SIZE}², {SMOOTH_NAMES}"))
    report = table(["fit", "after 30 steps: mean / largest (mm)", "after 60", f"after {args.steps} (or the end)",
                    "mean shift of the LEDs x, y, z (mm)", "loss / loss at the true positions"], rows)
    note = (f"LEDs pushed {PUSH_MM} mm each; {len(CLOTHS)} captures at {SIZE}² (unless the row says otherwise) over "
            "10 mm (jute 0, twill 1, knit 0.5 mm above the card, mean heights known; rows naming cotton, twill, "
            "taffeta: those at 0, 1 and 0.5 mm), 10-bit with noise (the rig's default), flat-fielded "
            "by a card at 0 mm smoothed by 3 px; a noise-free card or noise-free cloths are 16-bit renders; "
            "\"means of N frames\": every capture (the card's too) with 1/N of the sensor's noise variance, at 16 "
            "bits. "
            "\"The ring's height fixed\": the LEDs' mean height set to the true one and held. Loss: the re-rendering "
            "error of each near-light reconstruction weighted by the solver's robust weights, the readings predicted "
            f"within {LIT_SIGMAS:g} noise levels of zero left out. One torch thread.")
    print(report)
    print(note)
    if not args.no_record:
        append_results("Self-calibration from cloth captures (benchmarks/selfcalibration.py)", report + "\n\n" + note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
