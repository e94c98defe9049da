"""Make the documentation's gallery (docs/gallery.md): small PNGs produced by psmini itself, from fixed seeds.

    python scripts/make_gallery.py                     # writes docs/gallery/*.png
    python scripts/make_gallery.py --size 96 --out /tmp/gallery --data-root ../shared/data

Figures:

- ``fabrics.png``: synthetic jute, knit, net and lurex (crops at the rig's 0.025 mm per pixel) captured by the
  simulated rig (one LED image) and reconstructed by near-light photometric stereo: albedo, normal map
  (RGB = (n + 1) / 2), depth as a hill-shaded relief in viridis with its colour bar (µm) and a scale bar
  (``psmini.viz``);
- ``nearlight.png``: angular error of distant lights (raw, then flat-fielded by the card) and near light on jute,
  the whole 10 mm field;
- ``focus.png``: every focus measure over a synthetic focus stack, each normalised to its maximum;
- ``diligent_cat.png``: DiLiGenT cat, ground truth, least squares and robust error maps (only when the data root
  holds ``DiLiGenT/cat``; skipped with a message otherwise).

Every panel is drawn by ``psmini.viz`` (the same pictures as the CLI's previews and the notebooks). Needs
matplotlib (the ``dev`` or ``viz`` extra).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

import psmini  # noqa: E402
from data_synth import CARD_ALBEDO, make_fabric  # noqa: E402
from data_synth.rig import RigConfig, focus_stack, render_capture, render_card, rig_lights  # noqa: E402
from psmini import viz  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PITCH_MM = 0.025  # the rig's pixel pitch: the fabrics are shown at the camera's resolution (a --size crop)
FIELD_MM = 10.0  # the rig's field of view; the near-light figure shows all of it at --size pixels
FABRICS = ("jute", "knit", "net", "lurex")
# PNG metadata would carry matplotlib's version; without it the files depend on the data alone
PNG = {"dpi": 110, "metadata": {"Software": None}, "bbox_inches": "tight"}


def reconstruct(name: str, size: int, pitch: float) -> tuple:
    """Render ``name`` with the simulated rig and reconstruct it with near light: (capture, card, result, pitch)."""
    config = RigConfig(size=size, pixel_pitch_mm=pitch)
    capture = render_capture(make_fabric(name, size=size, pixel_pitch_mm=pitch, seed=0), config, seed=0)
    card = render_card(config, CARD_ALBEDO, seed=1)
    model = psmini.PhotometricStereo(rig_lights(config), pixel_pitch_mm=pitch)
    result = model(capture.images[None], reference=card.images[None], dark=capture.dark[None],
                   reference_dark=card.dark[None], card_albedo=CARD_ALBEDO)
    return capture, card, result, pitch


def fabrics_figure(size: int, out: Path) -> str:
    fig, axes = plt.subplots(len(FABRICS), 4, figsize=(11, 2.6 * len(FABRICS)), constrained_layout=True)
    lines = []
    for row, name in zip(axes, FABRICS, strict=True):
        capture, _, result, pitch = reconstruct(name, size, PITCH_MM)
        error = float(psmini.mean_angular_error(result.normals, capture.normals[None], capture.mask[None])[0])
        row[0].imshow(capture.images[0], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        row[0].set_title(f"{name}: LED 0", fontsize=9)
        row[1].imshow(result.albedo[0, 0], cmap="gray", vmin=0, vmax=float(result.albedo.quantile(0.995)),
                      interpolation="nearest")
        row[1].set_title("albedo", fontsize=9)
        for ax in row[:2]:
            ax.axis("off")
        viz.plot_normals(row[2], result.normals, result.mask, title=f"normals ({error:.1f}° mean error)")
        viz.plot_depth(row[3], result.depth, result.mask, pitch, title="depth, hill-shaded")
        for ax in row[2:]:
            ax.title.set_fontsize(9)
        lines.append(f"{name} {error:.2f} deg")
    fig.suptitle(f"simulated rig, {size * PITCH_MM:.0f} mm crops at {PITCH_MM} mm/px, near-light reconstruction "
                 "(hatched: unsolved)", fontsize=10)
    fig.savefig(out / "fabrics.png", **PNG)
    plt.close(fig)
    return "fabrics.png: mean angular error " + ", ".join(lines)


def nearlight_figure(size: int, out: Path) -> str:
    capture, card, near, pitch = reconstruct("jute", size, FIELD_MM / size)
    leds = rig_lights(RigConfig(size=size, pixel_pitch_mm=pitch))
    distant = psmini.PhotometricStereo(leds, pitch, psmini.ReconstructionConfig(solver="distant"))
    runs = {"distant lights, raw": distant(capture.images[None], dark=capture.dark[None]),
            "distant lights, card": distant(capture.images[None], reference=card.images[None], dark=capture.dark[None],
                                            reference_dark=card.dark[None], card_albedo=CARD_ALBEDO),
            "near light (LED model)": near}
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4), constrained_layout=True)
    lines = []
    for ax, (name, result) in zip(axes, runs.items(), strict=True):
        error = psmini.angular_error_deg(result.normals, capture.normals[None])
        mean = float(psmini.mean_angular_error(result.normals, capture.normals[None], capture.mask[None])[0])
        viz.plot_angular_error(ax, error, capture.mask, limits=(0.0, 30.0), title=f"{name}: {mean:.1f}°")
        ax.title.set_fontsize(9)
        lines.append(f"{name} {mean:.2f} deg")
    fig.savefig(out / "nearlight.png", **PNG)
    plt.close(fig)
    return "nearlight.png: " + ", ".join(lines)


def focus_figure(size: int, out: Path) -> str:
    pitch = PITCH_MM
    config = RigConfig(size=size, pixel_pitch_mm=pitch)
    positions = torch.arange(-2.0, 2.0001, 0.1)
    frames = focus_stack(make_fabric("jute", size=size, pixel_pitch_mm=pitch, seed=0), positions, 0.0, 2.0,
                         noise=0.01, config=config)
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for name in psmini.FOCUS_MEASURES:
        scores = psmini.focus_measure(frames, name)
        ax.plot(positions, scores / scores.max(), label=name)
    best = psmini.best_of_scores(psmini.brenner(frames), positions.tolist())
    ax.axvline(best.best_position, color="k", ls="--", lw=1, label="Brenner, refined peak")
    ax.set_xlabel("stage position, mm")
    ax.set_ylabel("score / max")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title("focus measures on a synthetic focus stack (jute)", fontsize=10)
    fig.savefig(out / "focus.png", **PNG)
    plt.close(fig)
    return f"focus.png: Brenner peak at {best.best_position:+.3f} mm"


def diligent_figure(data_root: Path, out: Path) -> str:
    folder = data_root / "DiLiGenT" / "cat"
    if not (folder / "filenames.txt").is_file():
        return f"diligent_cat.png: skipped, no DiLiGenT/cat under {data_root}"
    from psmini.io import load_sample

    sample = load_sample(folder)
    inside = sample.mask[0]
    rows, cols = inside.any(1).nonzero()[:, 0], inside.any(0).nonzero()[:, 0]
    window = (slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
    truth = sample.normals_gt.nan_to_num()
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.8), constrained_layout=True)
    viz.plot_normals(axes[0], truth[:, window[0], window[1]], inside[window], title="cat: ground-truth normals")
    lines = []
    for ax, method in zip(axes[1:], ("lstsq", "robust"), strict=True):
        result = psmini.reconstruct(sample, psmini.ReconstructionConfig(estimator=method))
        score = psmini.score_reconstruction(result, sample)["mean_angular_error_deg"]
        error = psmini.angular_error_deg(result.normals, truth[None])[0, 0]
        viz.plot_angular_error(ax, error[window], inside[window], limits=(0.0, 30.0),
                               title=f"{method}: {score:.2f}° mean error")
        lines.append(f"{method} {score:.3f} deg")
    for ax in axes:
        ax.title.set_fontsize(9)
    fig.savefig(out / "diligent_cat.png", **PNG)
    plt.close(fig)
    return "diligent_cat.png: DiLiGenT cat " + ", ".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "gallery", help="output folder (docs/gallery)")
    parser.add_argument("--size", type=int, default=200, help="side of the synthetic crops, pixels (default 200)")
    parser.add_argument("--data-root", type=Path, default=ROOT.parent / "shared" / "data",
                        help="folder holding DiLiGenT/ (default: ../shared/data beside the repository)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    for make in (lambda: fabrics_figure(args.size, args.out), lambda: nearlight_figure(args.size, args.out),
                 lambda: focus_figure(args.size, args.out), lambda: diligent_figure(args.data_root, args.out)):
        start = time.perf_counter()
        print(f"{make()}  ({time.perf_counter() - start:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
