"""Structure descriptors and relief amplitude on a randomised family of weaves, and on psmini's own fabrics.

Two questions, on captures of the simulated rig (8-bit, noise, shadows; the cloth lifted 0-1 mm above the card)
reconstructed by psmini's default pipeline (near light for the rig's LED captures):

1. **Descriptors on a family, not one generator.** ``--samples`` members of :mod:`data_synth.weaves` (seeds
   0..N-1: plain, 2/2 basket, 2/1 and 3/1 twill, 5-end satin, 2/2 warp rib, jersey; 10-40 threads/cm per system,
   any orientation, cross-section, crimp 0.15-2 times the yarn height). A sample is right when both thread
   densities are within 3%, both directions within 1.5° and the repeat along each system exact, by
   :func:`psmini.fabric.fabric_structure` on the ground-truth height and on the reconstruction (on its slopes'
   unweighted integration, :func:`psmini.fabric.structure_surface`, where ``describe_reconstruction`` reads the
   structure); the failures are counted by kind.
2. **Relief amplitude.** Sa and Sq of the reconstructed depth against the true height's,
   the reconstruction's over its solved pixels (what ``describe`` reports), the true height's over the whole
   field, two ways: levelled by a plane alone (as issue 46 measured), and on ``describe``'s scale-limited surface (the
   ISO S-filter of the pixel, 80 µm; an L-filter of 2.5 mm). For psmini's own fabrics (``data_synth.FABRICS``,
   seed 0, 0.5 mm above the card) the loss is split: the true normals integrated by the same integration, and the
   reconstruction's slopes with the true slopes put in at the pixels it left unsolved (what near light's unsolved
   crevices cost); for the family, what the true normals give with every slope clipped at a rise of 2 (63 deg:
   what walls steeper than that hold of the relief) and the true height over the reconstruction's solved pixels.
   Both also over the cloth alone: where the card shows through a hole the generator's height is the cloth's base
   (0), which no camera sees, so a hole's pixels are left out of both heights (ISO 25178's non-measured points).

``--cache DIR`` keeps every reconstruction (keyed by a hash of the renderer's and pipeline's code). Prints
tables and appends them to ``benchmarks/results.md``. Usage::

    python benchmarks/fabric_family.py [--samples 200] [--size 400] [--cache .fabric_cache] [--no-ledger]
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._fabric_captures import reconstruct_capture, source_tag  # noqa: E402
from benchmarks._ledger import append_results, table  # noqa: E402
from psmini.config import ReconstructionConfig  # noqa: E402

CONFIG = ReconstructionConfig()
PITCH = 0.025
DENSITY_TOLERANCE = 0.03
ANGLE_TOLERANCE_DEG = 1.5


def angle_difference(a: float, b: float) -> float:
    """Difference of two line directions, degrees in [0, 90]."""
    return abs((a - b + 90.0) % 180.0 - 90.0)


def structure_failures(found, truth) -> list[str]:
    """The ways ``found`` (a FabricStructure) misses ``truth`` (a WeaveTruth); empty when right.

    Each found system is matched to the true system of the nearest direction; kinds: "no structure", "one
    system", "a system twice", "density" (> 3%), "direction" (> 1.5°), "repeat".

    Example:
        >>> from types import SimpleNamespace as N
        >>> truth = N(threads_per_cm=(30.0, 20.0), thread_angles_deg=(90.0, 0.0), repeat_threads=(2, 2))
        >>> structure_failures(N(found=True, threads_per_cm=[30.2, 20.0], thread_angles_deg=[90.3, 0.1],
        ...                      repeat_threads=[2, 2]), truth)
        []
        >>> structure_failures(N(found=True, threads_per_cm=[30.0, 10.0], thread_angles_deg=[90.0, 0.0],
        ...                      repeat_threads=[2, 1]), truth)
        ['density', 'repeat']
    """
    if not found.found:
        return ["no structure"]
    if found.threads_per_cm is None or len(found.threads_per_cm) < 2:
        return ["one system"]
    match = [min((0, 1), key=lambda k: angle_difference(a, truth.thread_angles_deg[k]))
             for a in found.thread_angles_deg]
    if match[0] == match[1]:
        return ["a system twice"]
    kinds = []
    if any(abs(d / truth.threads_per_cm[k] - 1) > DENSITY_TOLERANCE for d, k in zip(found.threads_per_cm, match,
                                                                                  strict=True)):
        kinds.append("density")
    if any(angle_difference(a, truth.thread_angles_deg[k]) > ANGLE_TOLERANCE_DEG
           for a, k in zip(found.thread_angles_deg, match, strict=True)):
        kinds.append("direction")
    repeats = [found.repeat_threads[match.index(k)] for k in (0, 1)] if found.repeat_threads else None
    if repeats is None or tuple(repeats) != tuple(truth.repeat_threads):
        kinds.append("repeat")
    return kinds


def amplitude(height: torch.Tensor, mask: torch.Tensor | None, options) -> tuple[float, float]:
    """(Sa, Sq) in µm of ``height`` over ``mask`` on the scale-limited surface of ``options``."""
    from psmini.fabric import iso25178

    out = iso25178(height.double(), PITCH, mask, options)
    return float(out["Sa"]), float(out["Sq"])


def bias(measured: tuple[float, float], true: tuple[float, float]) -> tuple[float, float]:
    """Relative (Sa, Sq) bias in per cent."""
    return 100 * (measured[0] / true[0] - 1), 100 * (measured[1] / true[1] - 1)


def measure_relief(depth, mask, height, cloth) -> dict[str, tuple[float, float]]:
    """Sa/Sq bias (%), plane-levelled and on describe's ISO surface: the reconstruction over its solved pixels (what
    ``describe`` measures), the true height over the whole field; and on describe's surface over the cloth alone
    (``cloth``: where it covers the card), both heights: in a hole the generator's height is 0, the cloth's base,
    which no camera sees (it sees the card, lifted 0-1 mm lower), so the holes are left out of both as the
    non-measured points of ISO 25178 are."""
    from psmini.fabric import SurfaceOptions, describe_surface_options

    plane = SurfaceOptions(form_degree=1)
    iso = describe_surface_options(PITCH)
    return {"plane": bias(amplitude(depth, mask, plane), amplitude(height, None, plane)),
            "describe": bias(amplitude(depth, mask, iso), amplitude(height, None, iso)),
            "cloth": bias(amplitude(depth, mask & cloth, iso), amplitude(height, cloth, iso))}


#: The steepest facet of the "walls limited" column: a rise of 2 per run, 63.4 deg from the card's plane.
STEEPEST_RISE = 2.0


def true_slopes(height: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The slopes (p, q) of the true normals (psmini's renderer's central differences), float64."""
    from psmini.render import normals_from_height

    normals = normals_from_height(height.double(), PITCH)
    return -normals[:, :1] / normals[:, 2:], -normals[:, 1:2] / normals[:, 2:]


def integrated(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Slopes integrated by the near-light solver's final integration (masked least squares on the rectangle, with
    its restoration of the trapezoidal rule's flattening)."""
    from psmini.integrate import integrate
    from psmini.integrate.least_squares import _undo_edge_averaging

    return _undo_edge_averaging(integrate(p, q, "masked", PITCH))


def slopes_bias(p: torch.Tensor, q: torch.Tensor, true: tuple[float, float],
                limit: float | None = None, region: torch.Tensor | None = None) -> tuple[float, float]:
    """Sa/Sq bias (%) on describe's surface of the slopes :func:`integrated` (over ``region``, all when None), against
    the true height's ``true`` (over the same region); with ``limit``, each slope clipped to +-limit first: what a
    reconstruction would read that measured every facet exactly up to that steepness and none beyond it."""
    from psmini.fabric import describe_surface_options

    if limit is not None:
        p, q = p.clamp(-limit, limit), q.clamp(-limit, limit)
    return bias(amplitude(integrated(p, q), region, describe_surface_options(PITCH)), true)


def steep_share(p: torch.Tensor, q: torch.Tensor, limit: float = STEEPEST_RISE) -> float:
    """The share of pixels (%) whose slope (gradient magnitude) exceeds ``limit``."""
    return 100 * float(((p.square() + q.square()).sqrt() > limit).double().mean())


def without_fill(reconstruct):
    """Run ``reconstruct()`` with near light's fill of unconfident slopes switched off (a diagnostic).

    The energy solver (``psmini.nearlight._integrate``) blends a slope into its neighbourhood's weighted mean by
    ``1 - decided``, ``decided = 1 / (1 + (normal_std / _FILL_ABOVE_DEG)^4 + slope_variance^2 / _FILL_SLOPE_STD^8)``;
    with both thresholds infinite ``decided`` is 1 everywhere (``normal_std`` is at most 180 deg and the slope
    variance finite), so every slope enters the integration as fitted, still weighted by its inverse variance.
    (Before the energy solver this switched off ``_FILL_BELOW``, which no longer exists.)"""
    import math

    from psmini import nearlight

    names = ("_FILL_ABOVE_DEG", "_FILL_SLOPE_STD")
    if not all(hasattr(nearlight, name) for name in names):
        raise SystemExit(f"--fill-diagnostic: this psmini's near-light solver has no {' / '.join(names)} to switch off")
    kept = {name: getattr(nearlight, name) for name in names}
    for name in names:
        setattr(nearlight, name, math.inf)
    try:
        return reconstruct()
    finally:
        for name, value in kept.items():
            setattr(nearlight, name, value)


def capture_maker(fabric, rig, card, seed: int, lift: float):
    """A function rendering ``fabric`` on the rig (``lift`` mm above the card) as a flat-fielded Sample."""
    def make():
        from data_synth import CARD_ALBEDO
        from data_synth.rig import render_capture
        from psmini.io.sample import Sample

        capture = render_capture(fabric, rig, seed=seed, height_offset_mm=lift)
        sample = Sample(name=fabric.name, images=capture.images, lights=capture.lights, dark=capture.dark,
                        reference=card.images, reference_dark=card.dark, card_albedo=CARD_ALBEDO,
                        pixel_pitch_mm=PITCH, saturation_level=1.0)
        return sample, capture
    return make


def lift_of(seed: int) -> float:
    """The cloth's lift above the card for family member ``seed``: uniform 0-1 mm, its own stream."""
    return float(torch.rand((), generator=torch.Generator().manual_seed(104_729 + int(seed)), dtype=torch.float64))


def summary(values: list[float]) -> str:
    """Mean, spread and extremes of a list of biases (per cent)."""
    a = np.asarray(values)
    return f"{a.mean():+.1f} ± {a.std():.1f} ({a.min():+.1f} to {a.max():+.1f})"


def within(values: list[tuple[float, float]], limit: float = 5.0) -> str:
    a = np.asarray(values)
    return f"{int((np.abs(a) <= limit).all(axis=1).sum())}/{len(a)}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=200)
    parser.add_argument("--first-seed", type=int, default=0, help="the family members are seeds FIRST..FIRST+N-1")
    parser.add_argument("--size", type=int, default=400, help="crop side, pixels (0.025 mm each)")
    parser.add_argument("--cache", type=Path, default=None, metavar="DIR")
    parser.add_argument("--no-named", action="store_true", help="skip psmini's own fabrics")
    parser.add_argument("--fill-diagnostic", type=int, default=0, metavar="N",
                        help="also reconstruct psmini's own fabrics and the first N family members with near "
                        "light's filling of unconfident slopes switched off (psmini.nearlight._FILL_ABOVE_DEG and "
                        "_FILL_SLOPE_STD set to infinity): what "
                        "that fill costs the relief; a diagnostic for the near-light solver, not a configuration")
    parser.add_argument("--no-ledger", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    from data_synth import FABRICS, make_fabric
    from data_synth.rig import RigConfig, render_card
    from data_synth.weaves import WEAVES, draw_weave
    from psmini.fabric import describe_surface_options, fabric_structure, structure_surface

    iso = describe_surface_options(PITCH)
    rig = RigConfig(bit_depth=8, size=args.size)
    card = render_card(rig, seed=10_007)
    tag = source_tag(CONFIG, {"rig": rig.__dict__, "card": 10_007})
    start = time.perf_counter()

    # 1. the family: descriptors (truth, reconstruction) and relief
    found_kinds: dict[str, collections.defaultdict[str, collections.Counter]] = {
        "truth": collections.defaultdict(collections.Counter),
        "reconstruction": collections.defaultdict(collections.Counter)}
    counts: collections.Counter = collections.Counter()
    relief: collections.defaultdict[str, collections.defaultdict[str, list]] = collections.defaultdict(
        lambda: collections.defaultdict(list))
    steep: collections.defaultdict[str, list[float]] = collections.defaultdict(list)  # % of pixels > STEEPEST_RISE
    failures = []
    seeds = range(args.first_seed, args.first_seed + args.samples)
    for seed in seeds:
        fabric, truth = draw_weave(seed, size=args.size)
        lift = lift_of(seed)
        rec = reconstruct_capture(f"weave{seed}-{args.size}", capture_maker(fabric, rig, card, seed, lift), args.cache,
                                  tag, CONFIG)
        counts[fabric.name] += 1
        # the reconstruction's structure is read as describe_reconstruction reads it: from its slopes' integration
        for source, (height, mask) in {"truth": (fabric.height_mm, None),
                                       "reconstruction": (structure_surface(rec.p, rec.q, PITCH, rec.mask),
                                                          rec.mask)}.items():
            kinds = structure_failures(fabric_structure(height, PITCH, mask)[0], truth)
            found_kinds[source][fabric.name]["right" if not kinds else " + ".join(kinds)] += 1
            if kinds:
                failures.append((source, seed, fabric.name, kinds, fabric.params))
        for key, value in measure_relief(rec.depth, rec.mask, fabric.height_mm, fabric.mask).items():
            relief[fabric.name][key].append(value)
        true = amplitude(fabric.height_mm, None, iso)
        p, q = true_slopes(fabric.height_mm)
        relief[fabric.name]["true normals"].append(slopes_bias(p, q, true))
        relief[fabric.name]["walls limited"].append(slopes_bias(p, q, true, STEEPEST_RISE))
        relief[fabric.name]["true normals, cloth"].append(
            slopes_bias(p, q, amplitude(fabric.height_mm, fabric.mask, iso), region=fabric.mask))
        # what leaving the unsolved pixels out costs by itself: the true height over the solved ones
        relief[fabric.name]["solved pixels"].append(bias(amplitude(fabric.height_mm, rec.mask, iso), true))
        steep[fabric.name].append(steep_share(p, q))
        if seed < args.first_seed + args.fill_diagnostic:
            make = capture_maker(fabric, rig, card, seed, lift)
            unfilled = without_fill(lambda key=f"weave{seed}-{args.size}-nofill", make=make: reconstruct_capture(
                key, make, args.cache, tag, CONFIG))
            relief[fabric.name]["without the fill"].append(measure_relief(unfilled.depth, unfilled.mask,
                                                                          fabric.height_mm, fabric.mask)["describe"])
            relief[fabric.name]["with the fill"].append(relief[fabric.name]["describe"][-1])
        if (seed - args.first_seed + 1) % 20 == 0:
            print(f"  {seed - args.first_seed + 1} family members, {time.perf_counter() - start:.0f} s", flush=True)

    weaves = [w for w in WEAVES if counts[w]]
    rows = []
    for source in ("truth", "reconstruction"):
        right = sum(found_kinds[source][w]["right"] for w in weaves)
        rows.append([source, f"{right}/{args.samples} ({right / args.samples:.1%})"]
                    + [f"{found_kinds[source][w]['right']}/{counts[w]}" for w in weaves])
    kinds_rows = []
    for source in ("truth", "reconstruction"):
        for w in weaves:
            for kind, n in sorted(found_kinds[source][w].items()):
                if kind != "right":
                    kinds_rows.append([source, w, kind, n])
    failure_lines = [f"- {source}, seed {seed} ({name}): {', '.join(kinds)}; {params['warp_per_cm']:.1f} x "
                     f"{params['weft_per_cm']:.1f}/cm at {params['orientation_deg']:.1f} deg, crimp "
                     f"{params['crimp_ratio']:.2f} x the yarn height" for source, seed, name, kinds, params in failures]
    relief_rows = []
    columns = ("plane", "describe", "true normals", "walls limited", "solved pixels", "cloth", "true normals, cloth")

    for w in weaves:
        r = relief[w]
        relief_rows.append([w, counts[w]] + [f"{summary([v[0] for v in r[k]])} / {summary([v[1] for v in r[k]])}"
                                             for k in columns] + [f"{np.mean(steep[w]):.1f}%", within(r["describe"]),
                                                                  within(r["cloth"])])
    every = {k: [v for w in weaves for v in relief[w][k]] for k in columns + ("with the fill", "without the fill")}
    relief_rows.append(["all", args.samples] + [f"{summary([v[0] for v in every[k]])} / "
                                                f"{summary([v[1] for v in every[k]])}" for k in columns]
                       + [f"{np.mean([v for w in weaves for v in steep[w]]):.1f}%", within(every["describe"]),
                          within(every["cloth"])])

    body = [
        f"{args.samples} members of `data_synth.weaves` (seeds {seeds[0]}..{seeds[-1]}), {args.size}x{args.size} px at "
        f"{PITCH} mm, 8-bit simulated rig captures lifted 0-1 mm above the card, reconstructed by psmini's default "
        f"pipeline (`ReconstructionConfig()`: near light). Built in {time.perf_counter() - start:.0f} s"
        + (" (reconstructions from the cache where present)." if args.cache else "."),
        "",
        "Descriptors right (both densities within 3%, both directions within 1.5 deg, the repeat along each system "
        "exact), by `fabric_structure` (the reconstruction's from its slopes' unweighted integration, "
        "`structure_surface`, as `describe_reconstruction` reads it):",
        "",
        table(["height", "all"] + weaves, rows),
        "",
        "Failures by kind:",
        "",
        table(["height", "weave", "kind", "samples"], kinds_rows) if kinds_rows else "none",
        "",
        *failure_lines,
        "",
        "Relief amplitude of the reconstruction (over its solved pixels) against the true height (the whole field), "
        "Sa / Sq bias in per "
        "cent (mean ± sd, extremes): levelled by a plane; on describe's ISO surface (80 um S-filter, 2.5 mm "
        "L-filter); the true normals integrated by the same integration, on describe's surface; the same with every "
        f"slope clipped to a rise of {STEEPEST_RISE:g} ({np.degrees(np.arctan(STEEPEST_RISE)):.1f} deg: what a "
        "reconstruction would read that measured every facet exactly up to that steepness and none beyond); the true "
        "height over the reconstruction's solved pixels alone (what leaving the unsolved ones out costs by itself); "
        "the share of pixels steeper than that; on describe's surface over the cloth alone, both heights (the holes, "
        "where the card shows, left out of both: there the generator's height is the cloth's base, 0, which no "
        "camera sees), and the true normals integrated, over the cloth; samples whose reconstruction has both within "
        "5% on describe's surface, and over the cloth:",
        "",
        table(["weave", "n", "plane", "describe's surface", "true normals, describe's surface",
               f"true normals, walls limited to {np.degrees(np.arctan(STEEPEST_RISE)):.0f} deg",
               "true height, solved pixels", "over the cloth", "true normals, over the cloth", "steeper pixels",
               "within 5%",
               "within 5%, over the cloth"], relief_rows),
    ]
    if args.fill_diagnostic:
        n = len(every["without the fill"])
        body += ["", f"Near light's fill of unconfident slopes (the first {n} members, describe's surface, Sa / Sq "
                 f"bias in per cent): with it (the default) {summary([v[0] for v in every['with the fill']])} / "
                 f"{summary([v[1] for v in every['with the fill']])}; switched off "
                 f"{summary([v[0] for v in every['without the fill']])} / "
                 f"{summary([v[1] for v in every['without the fill']])}."]

    if not args.no_named:
        clean_rig = rig.replace(noise=False)
        clean_card = render_card(clean_rig, seed=10_007)
        clean_tag = source_tag(CONFIG, {"rig": clean_rig.__dict__, "card": 10_007})

        def cell(pair: tuple[float, float]) -> str:
            return f"{pair[0]:+.1f} / {pair[1]:+.1f}"

        named_rows = []
        for name in FABRICS:
            fabric = make_fabric(name, size=args.size, seed=0)
            height = fabric.height_mm
            rec = reconstruct_capture(f"{name}-0-{args.size}", capture_maker(fabric, rig, card, 0, 0.5), args.cache,
                                      tag, CONFIG)
            named = measure_relief(rec.depth, rec.mask, height, fabric.mask)
            # the split, on a noise-free capture (unweighted integration of noisy slopes is no reference)
            clean = reconstruct_capture(f"{name}-0-{args.size}-clean",
                                        capture_maker(fabric, clean_rig, clean_card, 0, 0.5), args.cache,
                                        clean_tag, CONFIG)
            m = clean.mask
            t = amplitude(height, None, iso)
            pt, qt = true_slopes(height)
            filled = integrated(torch.where(m, clean.p.double(), pt), torch.where(m, clean.q.double(), qt))
            extra = []
            if args.fill_diagnostic:
                unfilled = without_fill(lambda fabric=fabric, name=name: reconstruct_capture(
                    f"{name}-0-{args.size}-nofill", capture_maker(fabric, rig, card, 0, 0.5), args.cache, tag, CONFIG))
                extra = [cell(measure_relief(unfilled.depth, unfilled.mask, height, fabric.mask)["describe"])]
            named_rows.append([name, f"{t[0]:.1f} / {t[1]:.1f}", f"{1 - float(fabric.mask.float().mean()):.1%}",
                               cell(named["plane"]), cell(named["describe"]), cell(named["cloth"]),
                               cell(slopes_bias(pt, qt, t)),
                               cell(bias(amplitude(clean.depth, m, iso), t)),
                               cell(bias(amplitude(filled, None, iso), t)),
                               f"{1 - float(m.float().mean()):.1%}", *extra])
        body += [
            "",
            f"psmini's own fabrics (`data_synth.FABRICS`, seed 0, {args.size} px, 0.5 mm above the card), Sa / Sq bias "
            "in per cent: levelled by a plane and on describe's surface as above (the reconstruction over its solved "
            "pixels, the true height over the whole field), and over the cloth alone (its holes, whose share is "
            "given, left out of both). The last four columns split the loss on describe's surface: the true normals "
            "integrated by "
            "the same integration; a noise-free capture reconstructed by the default pipeline; its slopes integrated "
            "unweighted with the true slopes put in where it left pixels unsolved (what remains is the fit's); and the "
            "share of unsolved pixels:",
            "",
            table(["fabric", "true Sa / Sq (um)", "holes", "plane", "describe's surface", "over the cloth",
                   "true normals", "noise-free capture", "noise-free, true slopes where unsolved", "unsolved"]
                  + (["near light without its fill, describe's surface"] if args.fill_diagnostic else []),
                  named_rows),
        ]
    text = "\n".join(body)
    print(text)
    if not args.no_ledger:
        append_results("Fabric family: descriptors on 200 random weaves and the relief's amplitude", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
