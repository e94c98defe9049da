"""``psmini describe PATH``: what the cloth is: yarn directions and densities, weave repeat, ISO 25178-2 parameters.

PATH is a capture or DiLiGenT folder (reconstructed first with psmini's default pipeline) or a reconstruction
output folder of ``psmini reconstruct`` (its ``depth.npy``, NaN outside the mask, ``outputs.json`` with the pixel
pitch, and ``normals.png``). The ISO parameters are measured on the depth, the yarn structure on the slopes
integrated without weights (:func:`psmini.fabric.describe_reconstruction`). Prints a table; ``--json`` prints one
object; ``--out DIR`` writes ``structure.json`` and ``structure.png`` (the spectrum the structure was read from,
with the detected peaks; the levelled height with the yarn directions) into DIR, atomically; ``--model FILE`` adds
the class and its probabilities from a fabric model (JSON, see ``benchmarks/fabric_recognition.py``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from psmini.commands._common import add_config_flags, add_json_flag, config_from_args, emit_json
from psmini.errors import DataFormatError, InputError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "describe",
        help="measure the fabric's structure: yarn densities and directions, weave repeat, ISO 25178 parameters",
        description=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("path", type=Path, metavar="PATH",
                        help="capture or DiLiGenT folder, or a reconstruction output folder (depth.npy, outputs.json)")
    parser.add_argument("--out", type=Path, metavar="DIR", help="write structure.json and structure.png into DIR")
    parser.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    parser.add_argument("--model", type=Path, metavar="FILE", help="fabric model (JSON) to classify the sample")
    add_config_flags(parser)
    add_json_flag(parser)
    parser.set_defaults(run=run)


def read_model(path: Path):
    """A :class:`~psmini.fabric.FabricClassifier` from its JSON file (no code runs on loading).

    Raises:
        DataFormatError: unreadable file, another format or version, or features other than
            :data:`psmini.fabric.DESCRIPTOR_NAMES`.
    """
    from psmini.fabric import DESCRIPTOR_NAMES, FabricClassifier

    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataFormatError(f"cannot read fabric model {path}: {error}") from error
    model = FabricClassifier.from_dict(data)
    if model.feature_names != tuple(DESCRIPTOR_NAMES):
        raise DataFormatError(f"fabric model {path} uses features {list(model.feature_names)}; this psmini computes "
                              f"{list(DESCRIPTOR_NAMES)}")
    return model


def write_model(path: Path, model) -> None:
    """Write a classifier's JSON file (through a temporary file renamed into place)."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.tmp")
    try:
        temporary.write_text(json.dumps(model.to_dict(), indent=1) + "\n", encoding="utf-8")
        temporary.replace(path)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise DataFormatError(f"cannot write fabric model {path}: {error}") from error


def _is_reconstruction(path: Path) -> bool:
    return (path / "outputs.json").is_file() or (path / "depth.npy").is_file()


def load_for_description(path: Path, config) -> SimpleNamespace:
    """What :func:`psmini.fabric.describe_reconstruction` needs, from any accepted PATH: ``depth`` (1, 1, H, W) mm,
    ``mask``, ``albedo`` (or None), the slopes ``p`` and ``q`` (from ``normals.png`` in a reconstruction folder;
    None without one), ``pitch`` (mm) and ``name``."""
    import torch

    path = Path(path)
    if _is_reconstruction(path):
        depth_file, outputs = path / "depth.npy", path / "outputs.json"
        if not depth_file.is_file():
            raise DataFormatError(f"{path} has outputs.json but no depth.npy: nothing to describe")
        from psmini.io._npy import read_npy

        depth = read_npy(depth_file, "depth")  # empty or cut short: a DataFormatError naming it
        try:
            meta = json.loads(outputs.read_text(encoding="utf-8")) if outputs.is_file() else {}
        except (OSError, ValueError) as error:
            raise DataFormatError(f"cannot read the reconstruction in {path}: {error}") from error
        if not isinstance(meta, dict):
            raise DataFormatError(f"{outputs} must hold a JSON object, got {type(meta).__name__}")
        if depth.ndim != 2:
            raise DataFormatError(f"{depth_file} must hold an (H, W) array, got shape {depth.shape}")
        pitch = meta.get("pixel_pitch_mm")
        if pitch is None:
            raise InputError(f"{path}: the reconstruction has no pixel pitch (outputs.json pixel_pitch_mm), so no "
                             "length in mm can be measured")
        height = torch.from_numpy(depth.astype(np.float32))[None, None].to(config.device)
        mask = torch.isfinite(height)
        p, q = _slopes(path / "normals.png", mask)
        albedo = None
        if (path / "albedo.png").is_file():  # 8-bit, divided by a robust maximum: a relative albedo, what is needed
            from psmini.io.images import read_gray

            values, _ = read_gray(path / "albedo.png")  # a DataFormatError for an unreadable file
            values = values.astype(np.float32)
            if values.shape == depth.shape:
                albedo = torch.from_numpy(values)[None, None].to(config.device)
        return SimpleNamespace(depth=height, mask=mask, albedo=albedo, p=p, q=q, pitch=float(pitch), name=path.name)
    from psmini.fabric import reconstruct_for_description
    from psmini.io import load_sample

    if not path.is_dir():
        raise DataFormatError(f"{path} does not exist or is not a folder")
    try:
        sample = load_sample(path)
    except DataFormatError as error:
        raise DataFormatError(f"{path} is neither a reconstruction folder (depth.npy, outputs.json) nor a "
                              f"sample folder: {error}") from error
    if sample.pixel_pitch_mm is None:
        raise InputError(f"{path}: the sample has no pixel pitch (DiLiGenT has none), so no length in mm can be "
                         "measured")
    rec = reconstruct_for_description(sample, config)
    return SimpleNamespace(depth=rec.depth[:1], mask=rec.mask[:1], albedo=rec.albedo[:1], p=rec.p[:1], q=rec.q[:1],
                           pitch=float(sample.pixel_pitch_mm), name=sample.name)


def _slopes(normals_png: Path, mask) -> tuple[Any, Any]:
    """The slopes (p, q) of a reconstruction folder's ``normals.png`` (1, 1, H, W), 0 where it is black (outside its
    writer's mask); (None, None) without the file or when its size is not the depth ``mask``'s."""
    import torch

    from psmini.io import read_normal_png
    from psmini.normals import normals_to_gradients

    if not normals_png.is_file():
        return None, None
    stored = read_normal_png(normals_png)  # a DataFormatError for an unreadable file
    if stored.shape[1:] != tuple(mask.shape[2:]):
        return None, None
    # outside the mask the file is black: a zero normal, whose slopes are 0
    return normals_to_gradients(torch.from_numpy(np.nan_to_num(stored, nan=0.0))[None].to(mask.device))


def add_structure_columns(out: Path, summary: dict, config) -> dict:
    """``psmini batch --describe``: the :func:`psmini.fabric.structure_row` columns of every sample, added to the
    summary and to ``OUT/summary.csv`` and ``OUT/summary.json`` (each replaced through a temporary file).

    A finished sample is measured on its written ``depth.npy`` and ``normals.png`` (:func:`load_for_description`); a
    failed one, one without a pixel pitch (DiLiGenT) or one whose output cannot be read gets empty cells and
    ``structure_found`` False with the reason.
    """
    from psmini.batch import SUMMARY_FIELDS, save_summary
    from psmini.fabric import structure_row

    empty = structure_row(None, None)
    for row in summary["samples"]:
        if row["status"] not in ("done", "skipped"):
            extra = {**empty, "structure_reason": "the sample was not reconstructed"}
        else:
            try:
                loaded = load_for_description(Path(out) / row["sample"], config)
                extra = structure_row(loaded, loaded.pitch)
            except InputError as error:  # no pixel pitch, no valid pixel
                extra = {**empty, "structure_reason": str(error)}
            except DataFormatError as error:
                extra = {**empty, "structure_reason": f"cannot read the reconstruction: {error}"}
        row.update(extra)
    save_summary(Path(out), summary, list(SUMMARY_FIELDS) + [k for k in empty if k not in SUMMARY_FIELDS])
    return summary


def _figure(target: Path, loaded: SimpleNamespace, entry: dict) -> None:
    """The spectrum the structure was read from (the slopes' integration when there are slopes) with its peaks, and
    the levelled height with the yarn directions (structure.png)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from psmini.fabric import StructureOptions, scale_limited_surface, structure_spectrum, structure_surface
    from psmini.fabric.surface import SurfaceOptions

    height, mask, pitch = loaded.depth, loaded.mask, loaded.pitch
    read = height if loaded.p is None else structure_surface(loaded.p, loaded.q, pitch, mask)
    spectrum, step = structure_spectrum(read, pitch, mask, StructureOptions())
    power = spectrum[0, 0].double().cpu().numpy()
    n = power.shape[0]
    surface, _ = scale_limited_surface(height, pitch, mask, SurfaceOptions(form_degree=2, l_cutoff_mm=2.5))
    z = surface[0, 0].double().cpu().numpy() * 1000
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.6))
    density = entry.get("threads_per_cm") or []
    reach = 1.6 * max(density) / 10 if density else n / 2 * step
    half = n / 2 * step
    left.imshow(np.log10(power + power.max() * 1e-12), cmap="magma", extent=(-half, half - step, -half + step, half))
    left.set_xlim(-reach, reach)
    left.set_ylim(-reach, reach)
    for peak in entry.get("peaks", [])[:24]:
        for sign in (1, -1):
            left.plot(sign * peak["fx_per_mm"], sign * peak["fy_per_mm"], "o", mfc="none", mec="cyan", ms=6)
    # no angles (no structure found): nothing to draw; a yarn system without an angle is not drawn either
    for d, a in zip(density, entry.get("thread_angles_deg") or [], strict=False):
        across = math.radians(a - 90)
        f = d / 10
        left.plot([f * math.cos(across), -f * math.cos(across)], [f * math.sin(across), -f * math.sin(across)],
                  "x", color="lime", ms=11, mew=2)
    left.set_title("height power spectrum (log), peaks; x: yarn systems")
    left.set_xlabel("fx (cycles/mm)")
    left.set_ylabel("fy (cycles/mm)")
    h, w = z.shape
    image = right.imshow(z, cmap="gray", extent=(0, w * pitch, 0, h * pitch))
    fig.colorbar(image, ax=right, label="height (um)")
    cx, cy = w * pitch / 2, h * pitch / 2
    length = 0.4 * min(h, w) * pitch
    # as above; one colour per yarn system (at most two)
    systems = zip(density, entry.get("thread_angles_deg") or [], strict=False)
    for (d, a), colour in zip(systems, ("tab:red", "tab:blue"), strict=False):
        t = math.radians(a)
        right.plot([cx - length * math.cos(t), cx + length * math.cos(t)],
                   [cy - length * math.sin(t), cy + length * math.sin(t)], color=colour, lw=2,
                   label=f"{d:.1f} threads/cm at {_direction(a, 1)} deg")
    if density:
        right.legend(loc="lower right", fontsize=8)
    right.set_title("levelled height, yarn directions")
    right.set_xlabel("x (mm)")
    right.set_ylabel("y (mm)")
    fig.tight_layout()
    fig.savefig(target, dpi=110)
    plt.close(fig)


def _direction(angle_deg: float, digits: int) -> str:
    """A yarn direction in [0, 180) with ``digits`` decimals: 179.996 is 0.00, not 180.00."""
    return f"{round(angle_deg, digits) % 180.0:.{digits}f}"


def _table(name: str, entry: dict) -> str:
    lines = [f"{name}:"]
    if entry["structure_found"]:
        density = ", ".join(f"{d:.2f}" for d in entry["threads_per_cm"])
        angles = ", ".join(_direction(a, 2) for a in entry["thread_angles_deg"])
        lines += [f"  threads per cm     {density}", f"  yarn directions    {angles} deg",
                  f"  weave repeat       {entry['weave_repeat']} (float {entry['float_length']})",
                  f"  crimp              {entry['crimp_um']:.1f} um"]
        if entry.get("wales_per_cm") is not None:
            lines.append(f"  wales / courses    {entry['wales_per_cm']:.2f} / {entry['courses_per_cm']:.2f} per cm")
    else:
        lines.append(f"  no periodic structure: {entry['structure_reason']}")
    lines.append(f"  openness           {entry['openness']:.3f}")
    units = entry["iso25178_units"]
    for key, value in entry["iso25178"].items():
        text = "n/a" if value is None else f"{value:.4g}"
        lines.append(f"  {key:<18} {text} {units[key] if units[key] != '1' else ''}".rstrip())
    if "class" in entry:
        lines.append(f"  class              {entry['class']} (p = {entry['class_probabilities'][entry['class']]:.3f})")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from psmini.fabric import describe_reconstruction, descriptor_vector

    config = config_from_args(args)
    model = read_model(args.model) if args.model is not None else None  # fail before any work
    start = time.perf_counter()
    loaded = load_for_description(args.path, config)
    entry = describe_reconstruction(loaded, loaded.pitch)[0]
    if model is not None:
        probabilities = model.predict_proba(descriptor_vector(entry))[0]
        entry["class_probabilities"] = {c: float(p) for c, p in zip(model.classes, probabilities, strict=True)}
        entry["class"] = model.classes[int(np.argmax(probabilities))]
    entry["name"] = loaded.name
    entry["time_s"] = time.perf_counter() - start
    print(_table(loaded.name, entry))
    if args.out is not None:
        from psmini.io._atomic import atomic_folder

        with atomic_folder(args.out, args.overwrite) as target:
            (target / "structure.json").write_text(json.dumps(entry, indent=2, allow_nan=False) + "\n",
                                                   encoding="utf-8")
            _figure(target / "structure.png", loaded, entry)
        print(f"  wrote {args.out / 'structure.json'}, {args.out / 'structure.png'}")
    if args.json:
        emit_json(entry)
    return 0
