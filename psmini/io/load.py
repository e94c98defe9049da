"""One entry point for every sample folder (DiLiGenT or psmini capture), and a walker for batches."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

from psmini.errors import DataFormatError
from psmini.io.capture import MANIFEST_NAME, read_capture, read_manifest
from psmini.io.diligent import is_diligent_folder, read_diligent
from psmini.io.sample import Sample

__all__ = ["load_sample", "find_samples", "scan_samples", "SampleScan", "NOT_SAMPLE_KINDS"]

logger = logging.getLogger(__name__)

#: Capture kinds that are calibration or focus data, not samples to reconstruct.
NOT_SAMPLE_KINDS = ("flatfield", "sphere", "focus")


def load_sample(path: str | Path, *, with_flatfield: bool = True, with_ground_truth: bool = True) -> Sample:
    """Load a DiLiGenT object folder or a psmini capture folder as a :class:`Sample`.

    A folder with ``capture.json`` is a capture (``docs/capture-format.md``); one with ``filenames.txt`` and
    ``light_directions.txt`` is DiLiGenT (:func:`read_diligent`). For a capture, the referenced flat-field
    capture is read too: its images become ``reference``, its dark frame ``reference_dark`` and its card
    albedo ``card_albedo``; ``saturation_level`` is 1.0 (the largest code of the sensor's bit depth).

    Args:
        path: the sample folder.
        with_flatfield: read the referenced flat-field capture. ``False`` leaves ``reference`` and
            ``reference_dark`` empty (the card's path stays in ``meta["flatfield"]`` and its albedo in
            ``card_albedo``), for callers that decode each card once for many samples (:mod:`psmini.batch`).
        with_ground_truth: read a capture's ground truth (``normals_gt``, ``depth_gt``, ...); ``False`` leaves
            them ``None`` without opening the files, for callers that do not score (DiLiGenT's normals are read
            either way: they come with the images).

    Returns:
        the :class:`Sample` (CPU tensors, ``float32``).

    Raises:
        DataFormatError: a folder that is neither kind, a ``focus`` capture (no lights to reconstruct with),
            a flat-field capture with a different number of images or a different size, and every error of
            :func:`read_diligent` and :func:`psmini.io.read_capture`.

    Example:
        >>> sample = load_sample("../shared/data/DiLiGenT/cat")  # doctest: +SKIP
        >>> sample.images.shape  # doctest: +SKIP
        torch.Size([96, 512, 612])
    """
    path = Path(path)
    if (path / MANIFEST_NAME).is_file():
        return _capture_sample(path, with_flatfield, with_ground_truth)
    if is_diligent_folder(path):
        return read_diligent(path)
    if not path.is_dir():
        raise DataFormatError(f"sample folder {path} does not exist or is not a folder")
    raise DataFormatError(
        f"{path} is not a sample folder: expected {MANIFEST_NAME} (psmini capture) or filenames.txt and "
        "light_directions.txt (DiLiGenT)"
    )


def _capture_sample(path: Path, with_flatfield: bool, with_ground_truth: bool) -> Sample:
    capture = read_capture(path, ground_truth=with_ground_truth)
    if capture.lights is None:
        raise DataFormatError(f"capture {path} is a {capture.kind!r} capture without lights; it cannot be "
            "reconstructed")
    reference = reference_dark = None
    if capture.flatfield_path is not None and with_flatfield:
        card = read_capture(capture.flatfield_path)
        if card.images.shape != capture.images.shape:
            raise DataFormatError(
                f"flat-field capture {capture.flatfield_path} has images {tuple(card.images.shape)} (K, H, W) but "
                f"capture {path} has {tuple(capture.images.shape)}; the card must be imaged under the same LEDs"
            )
        reference, reference_dark = card.images, card.dark
    gt = capture.gt
    # the card's albedo comes with its folder (a capture without one: no card, and the flat-field takes none)
    card_albedo = capture.card_albedo if capture.flatfield_path is not None and capture.card_albedo is not None else 1.0
    return Sample(
        name=path.name,
        images=capture.images,
        lights=capture.lights,
        mask=capture.mask,
        dark=capture.dark,
        reference=reference,
        reference_dark=reference_dark,
        card_albedo=card_albedo,
        pixel_pitch_mm=capture.pixel_pitch_mm,
        normals_gt=gt.get("normals"),
        depth_gt=gt.get("depth"),
        albedo_gt=gt.get("albedo"),
        saturation_level=1.0,
        gt_mask=gt.get("mask"),
        meta={
            "source": "capture",
            "path": str(path),
            "kind": capture.kind,
            "bit_depth": capture.bit_depth,
            "flatfield": str(capture.flatfield_path) if capture.flatfield_path is not None else None,
            "gt_lights": gt.get("lights"),
            "crop": capture.crop,
            "camera": capture.camera,
            "metadata": capture.metadata,
        },
    )


@dataclass(frozen=True)
class SampleScan:
    """What :func:`scan_samples` found under a root.

    Attributes:
        root: the folder walked.
        samples: the sample folders, sorted, as seen from ``root`` (through symbolic links, not resolved).
        problems: folders that could not be walked, as seen from ``root``, each with a message naming it: a
            dangling symbolic link, a link that loops back to a folder above it, a folder that cannot be read.
    """

    root: Path
    samples: list[Path]
    problems: dict[Path, str] = field(default_factory=dict)


def scan_samples(root: str | Path) -> SampleScan:
    """Walk ``root`` for sample folders, following symbolic links, and report what cannot be walked.

    A folder counts when it is a DiLiGenT object folder or a capture folder whose kind is not a calibration
    or focus kind (``flatfield``, ``sphere``, ``focus``). A capture whose manifest cannot be parsed is listed
    (with a warning) so that the batch reports its error. The walk does not descend into sample folders
    (their ``gt/`` is part of them) nor into hidden folders (such as a capture being written).

    Datasets are often assembled from several places with symbolic links: a link to a sample folder, or to a
    folder of them, is followed, and its samples are listed under the link's path (so that outputs go under
    their path relative to ``root`` as seen through the link). A link to a folder already on the current path
    (a cycle) is not followed, and a link whose target does not exist is not either; both are reported in
    ``problems`` by their path, and the walk goes on with the other folders.

    Args:
        root: the folder to walk (itself a link or not).

    Returns:
        a :class:`SampleScan`: the samples sorted, and the problems.

    Raises:
        DataFormatError: when ``root`` is not a folder (or a link to one).

    Example:
        >>> import tempfile
        >>> top = Path(tempfile.mkdtemp())
        >>> (top / "cycle").symlink_to(top)
        >>> (top / "broken").symlink_to(top / "nowhere")
        >>> scan = scan_samples(top)
        >>> scan.samples, sorted(path.name for path in scan.problems)
        ([], ['broken', 'cycle'])
    """
    root = Path(root)
    if not root.is_dir():
        raise DataFormatError(f"{root} does not exist or is not a folder")
    found: list[Path] = []
    problems: dict[Path, str] = {}
    # depth-first, each folder with the real paths of the folders above it (and itself): a link into one of
    # them would loop
    stack: list[tuple[Path, frozenset[str]]] = [(root, frozenset({os.path.realpath(root)}))]
    while stack:
        folder, above = stack.pop()
        if (folder / MANIFEST_NAME).is_file():
            if _is_sample_capture(folder):
                found.append(folder)
            continue
        if is_diligent_folder(folder):
            found.append(folder)
            continue
        try:
            entries = sorted(os.scandir(folder), key=lambda entry: entry.name, reverse=True)
        except OSError as error:
            problems[folder] = f"cannot read the folder {folder}: {error.strerror or error}"
            continue
        for entry in entries:
            if entry.name.startswith("."):
                continue
            path = folder / entry.name
            if entry.is_symlink():
                target = os.readlink(path)
                if not path.exists():
                    problems[path] = f"dangling symbolic link {path} -> {target}: its target does not exist"
                    continue
                if not path.is_dir():
                    continue
                real = os.path.realpath(path)
                if real in above:
                    problems[path] = (f"symbolic link {path} -> {target} loops back to {real}, a folder above it;"
                                      " not followed")
                    continue
            elif entry.is_dir(follow_symlinks=False):
                real = os.path.realpath(path)
            else:
                continue
            stack.append((path, above | {real}))
    for message in problems.values():
        logger.warning("%s", message)
    return SampleScan(root, sorted(found), problems)


def find_samples(root: str | Path) -> list[Path]:
    """List the sample folders under ``root`` (``root`` included), sorted, for batch processing.

    The walk of :func:`scan_samples`: symbolic links to sample folders and to folders of them are followed
    (samples are listed under the link's path), a cycle is never followed, and a dangling link or a cycle is
    logged as a warning naming it (:func:`scan_samples` returns them, for callers that report them).

    Args:
        root: the folder to walk.

    Returns:
        the sample folders, sorted.

    Raises:
        DataFormatError: when ``root`` is not a folder.

    Example:
        >>> find_samples("../shared/data/DiLiGenT")  # doctest: +SKIP
        [PosixPath('../shared/data/DiLiGenT/ball'), PosixPath('../shared/data/DiLiGenT/cat')]
    """
    return scan_samples(root).samples


def _is_sample_capture(folder: Path) -> bool:
    try:
        kind = read_manifest(folder)["kind"]
    except DataFormatError as error:
        logger.warning("listing %s although its manifest is invalid: %s", folder, error)
        return True
    return kind not in NOT_SAMPLE_KINDS
