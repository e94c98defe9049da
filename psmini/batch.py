"""Offline reconstruction of whole folder trees of samples: decode in workers, solve in batches, write atomically.

Every capture folder and DiLiGenT folder under a root (:func:`psmini.io.find_samples`) is decoded, grouped into
batches of samples that share a size, a light model and a flat-field card, solved in one batched call of
:class:`psmini.pipeline.PhotometricStereo` (or the near-light solver), and written into
``OUT/<path relative to the root>`` with the atomic folder writer of :mod:`psmini.io`. A sample whose output
folder holds ``outputs.json`` is finished (the folder appears only complete) and is skipped by the next run, so
a run killed half-way resumes where it stopped. A sample that fails (a corrupt file, a solver error) is reported
in the summary and the others go on.

The unit of work is a *chunk*: ``batch_size`` consecutive sample folders, decoded, grouped, solved, scored and
written by one process (:func:`_run_chunk`). Where it runs depends on the device:

- CPU: ``workers`` ``DataLoader`` processes each run whole chunks, with ``torch.get_num_threads() // workers``
  intra-op threads each (parallel samples beat parallel threads on small machines, and nothing but the summary
  row crosses processes); ``workers=0`` runs the chunks in this process.
- CUDA: ``workers`` ``DataLoader`` processes decode, the batches are solved on the GPU in this process and
  written from it.
- Dask (``scheduler`` or ``client``): each chunk is one task on a ``dask.distributed`` worker, on that worker's
  device (:mod:`psmini._dask`).

Each flat-field card is decoded once per process that needs it (once per run in this process; once per worker).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import re
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, fields
from functools import partial
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from psmini._files import nearest_existing
from psmini.config import ReconstructionConfig
from psmini.errors import DataFormatError, InputError, PsminiError
from psmini.result import Reconstruction

__all__ = [
    "OUTPUT_KINDS",
    "SUMMARY_FIELDS",
    "BatchRecord",
    "reconstruct_dataset",
    "iter_reconstructions",
    "parse_outputs",
]

logger = logging.getLogger(__name__)

#: What ``outputs`` may name: ``albedo.png``, ``normals.png``, ``depth.npy/.png/.json``, ``points.ply``.
OUTPUT_KINDS = ("normals", "albedo", "depth", "ply")
#: Columns of ``summary.csv`` (and keys of each entry of ``summary.json``'s ``samples``).
SUMMARY_FIELDS = (
    "sample", "status", "solver", "time_s", "decode_s", "compute_s", "write_s", "batch_size", "mean_angular_error_deg",
    "median_angular_error_deg", "unsolved_share", "normal_std_median_deg", "depth_rmse_mm", "depth_mae_mm", "error",
)
_MARKER = "outputs.json"


@dataclass
class BatchRecord:
    """One sample's line of the summary.

    Attributes:
        sample: the sample folder relative to the root (its output folder relative to ``out``).
        status: ``"done"`` (reconstructed in this run), ``"skipped"`` (finished by an earlier run) or ``"failed"``.
        solver: the solver that ran (``"near"`` or ``"distant"``, as the configuration resolved for its lights).
        time_s: decode + its share of the batch computation + write, seconds.
        decode_s, compute_s, write_s: the parts of ``time_s``.
        batch_size: how many samples were solved together with it.
        normal_std_median_deg: near light: the median over its solved pixels of each normal's predicted RMS angular
            error (:attr:`psmini.nearlight.NearLightResult.normal_std`, written as ``normal_std.npy``/``.png``);
            None with distant lights.
        scores: errors against ground truth (:func:`psmini.evaluation.score_reconstruction`) when it has some.
        error: the error message of a failed sample.
    """

    sample: str
    status: str
    solver: str = ""
    time_s: float = 0.0
    decode_s: float = 0.0
    compute_s: float = 0.0
    write_s: float = 0.0
    batch_size: int = 0
    normal_std_median_deg: float | None = None
    scores: dict[str, float] = field(default_factory=dict)
    error: str = ""

    def row(self) -> dict[str, Any]:
        """The summary row: ``SUMMARY_FIELDS`` with empty cells where a figure does not apply."""
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "scores"}
        values.update(self.scores)
        return {key: "" if values.get(key) is None else values[key] for key in SUMMARY_FIELDS}


def parse_outputs(outputs: str | Sequence[str] | None) -> tuple[str, ...]:
    """The output kinds of ``--outputs`` (``"normals,albedo,depth,ply"``), validated; None means all.

    Raises:
        InputError: an empty list, a name that is not one of :data:`OUTPUT_KINDS`, or neither a string nor names.

    Example:
        >>> parse_outputs("depth, normals")
        ('normals', 'depth')
    """
    if outputs is None:
        return OUTPUT_KINDS
    if not (isinstance(outputs, str) or (isinstance(outputs, Sequence) and all(isinstance(n, str) for n in outputs))):
        raise InputError(f"outputs must be a comma-separated string or a sequence of names, got {outputs!r}")
    names = [n.strip() for n in (outputs.split(",") if isinstance(outputs, str) else outputs)]
    names = [n for n in names if n]
    unknown = sorted(set(names) - set(OUTPUT_KINDS))
    if unknown or not names:
        raise InputError(f"outputs must be a comma-separated subset of {','.join(OUTPUT_KINDS)}, got {outputs!r}")
    return tuple(kind for kind in OUTPUT_KINDS if kind in names)


@dataclass(frozen=True)
class _Settings:
    """What every chunk needs to know; picklable, sent to worker processes and Dask workers."""

    config: ReconstructionConfig
    kinds: tuple[str, ...] = OUTPUT_KINDS
    score: bool = True

    @property
    def device(self) -> str:
        return self.config.device

    @property
    def dtype(self) -> torch.dtype:
        return self.config.torch_dtype


# ------------------------------------------------------------------------------------------------ decoding


@dataclass
class _Decoded:
    """A decoded sample without its card (added by the process that solves it), or the error."""

    rel: str
    sample: Any = None
    card: str | None = None
    decode_s: float = 0.0
    error: str = ""


def _decode(folder: Path, rel: str, ground_truth: bool = True) -> _Decoded:
    """Decode one sample folder (its ground truth only with ``ground_truth``, for scoring); an error becomes the
    record's message (one bad file must not end the run)."""
    from psmini.io import load_sample  # OpenCV: imported where files are decoded, not with psmini

    start = time.perf_counter()
    try:
        # cards are decoded once per process, not per sample
        sample = load_sample(folder, with_flatfield=False, with_ground_truth=ground_truth)
        card = sample.meta.get("flatfield")  # absent for DiLiGenT folders
        card = None if card is None else str(Path(card).resolve())
    except (PsminiError, OSError, ValueError) as error:
        return _Decoded(rel, error=f"{type(error).__name__}: {error}", decode_s=time.perf_counter() - start)
    return _Decoded(rel, sample, card, time.perf_counter() - start)


class _SampleFolders(Dataset):
    """Decodes one sample folder per item (the CUDA path: decode in workers, solve in the main process)."""

    def __init__(self, root: Path, folders: Sequence[Path], ground_truth: bool = True) -> None:
        self.root, self.folders, self.ground_truth = root, list(folders), ground_truth

    def __len__(self) -> int:
        return len(self.folders)

    def __getitem__(self, index: int) -> _Decoded:
        folder = self.folders[index]
        return _decode(folder, _relative(self.root, folder), self.ground_truth)


def _collate(items: list) -> list:
    """Keep what the loader gives as a list: no tensor collation of samples that may differ in size."""
    return items


def _relative(root: Path, folder: Path) -> str:
    rel = folder.relative_to(root)
    return root.name if rel == Path(".") else rel.as_posix()


def _group_key(item: _Decoded) -> tuple:
    """Samples solved together must share size, card, light model, pitch and the presence of optional frames."""
    from psmini.io import lights_to_dict

    sample = item.sample
    try:
        lights = json.dumps(lights_to_dict(sample.lights), sort_keys=True)
    except InputError:  # a light model the capture format does not know: solve it alone
        lights = f"object-{id(sample.lights)}"
    return (tuple(sample.images.shape), item.card, lights, sample.pixel_pitch_mm, sample.card_albedo,
            sample.saturation_level, sample.dark is not None, sample.mask is not None)


class _Cards:
    """Flat-field cards by resolved path, decoded once and kept on the device.

    A card is known by its path and by the identity of its content (folder inode, manifest time): a card rewritten
    in place (the capture writer replaces whole folders) is decoded again by a long-lived Dask worker. At most
    ``limit`` cards are kept, the oldest dropped first.
    """

    def __init__(self, device: torch.device, dtype: torch.dtype, limit: int = 8) -> None:
        self.device, self.dtype, self.limit = device, dtype, limit
        self._cards: dict[tuple, tuple[Tensor, Tensor | None] | PsminiError] = {}

    def get(self, path: str, shape: tuple[int, ...]) -> tuple[Tensor, Tensor | None]:
        key = (path, _content_stamp(path))
        if key not in self._cards:
            for stale in [k for k in self._cards if k[0] == path]:  # an older content of the same card
                del self._cards[stale]
            while len(self._cards) >= self.limit:
                del self._cards[next(iter(self._cards))]
            self._cards[key] = self._load(path)
        card = self._cards[key]
        if isinstance(card, PsminiError):
            raise card
        if tuple(card[0].shape[1:]) != shape:
            raise DataFormatError(
                f"flat-field capture {path} has images {tuple(card[0].shape[1:])} (K, H, W) but the sample has "
                f"{shape}; the card must be imaged under the same LEDs"
            )
        return card

    def _load(self, path: str) -> tuple[Tensor, Tensor | None] | PsminiError:
        from psmini.io import read_capture

        try:
            card = read_capture(path)
        except PsminiError as error:
            return error
        logger.info("decoded flat-field card %s once for every sample of this process that references it", path)
        images = card.images.to(self.device, self.dtype).unsqueeze(0)
        return images, None if card.dark is None else card.dark.to(self.device, self.dtype).unsqueeze(0)


def _content_stamp(path: str) -> tuple[int, int]:
    try:
        return os.stat(path).st_ino, os.stat(Path(path) / "capture.json").st_mtime_ns
    except OSError:  # a missing card: read_capture reports it
        return 0, 0


#: The cards of this process by (device, dtype), for chunks run in worker processes (a DataLoader worker lives for
#: one run, a Dask worker for many).
_PROCESS_CARDS: dict[tuple[str, torch.dtype], _Cards] = {}


def _process_cards(device: torch.device, dtype: torch.dtype) -> _Cards:
    return _PROCESS_CARDS.setdefault((str(device), dtype), _Cards(device, dtype))


# ------------------------------------------------------------------------------------------------ solving


@dataclass
class _Solved:
    """One sample out of the batched solver (or its error)."""

    item: _Decoded
    result: Reconstruction | None
    compute_s: float
    batch_size: int
    error: str = ""


def _stack(tensors: list[Tensor], device: torch.device, dtype: torch.dtype | None) -> Tensor:
    stacked = torch.stack(tensors)
    return stacked.to(device=device, dtype=dtype or stacked.dtype, non_blocking=True)


def _solve_group(group: list[_Decoded], cards: _Cards, device: torch.device, settings: _Settings) -> list[_Solved]:
    """Reconstruct samples that share a key in one batched call; the batch is ``(B, K, H, W)``."""
    from psmini.pipeline import PhotometricStereo

    first, dtype = group[0].sample, settings.dtype
    start = time.perf_counter()
    reference = reference_dark = None
    if group[0].card is not None:
        reference, reference_dark = cards.get(group[0].card, tuple(first.images.shape))
    images = _stack([item.sample.images for item in group], device, dtype)
    dark = None if first.dark is None else _stack([item.sample.dark for item in group], device, dtype)
    mask = None if first.mask is None else _stack([item.sample.mask.bool() for item in group], device, None)
    lights = first.lights.to(device=device, dtype=dtype)
    model = PhotometricStereo(lights, first.pixel_pitch_mm, settings.config)
    with torch.no_grad():
        result = model(images, reference, dark, reference_dark, mask, first.card_albedo or 1.0, first.saturation_level)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    share = (time.perf_counter() - start) / len(group)
    return [_Solved(item, result.item(i), share, len(group)) for i, item in enumerate(group)]


def _solve(items: list[_Decoded], cards: _Cards, device: torch.device, settings: _Settings) -> list[_Solved]:
    """Group decoded samples by key and solve each group; a failing group is retried sample by sample so that
    one bad sample does not fail its neighbours."""
    solved: list[_Solved] = [_Solved(item, None, 0.0, 0, item.error) for item in items if item.error]
    groups: dict[tuple, list[_Decoded]] = {}
    for item in items:
        if not item.error:
            groups.setdefault(_group_key(item), []).append(item)
    for group in groups.values():
        try:
            solved += _solve_group(group, cards, device, settings)
            continue
        except PsminiError as error:
            if len(group) == 1:
                solved.append(_Solved(group[0], None, 0.0, 1, f"{type(error).__name__}: {error}"))
                continue
        for item in group:
            try:
                solved += _solve_group([item], cards, device, settings)
            except PsminiError as error:
                solved.append(_Solved(item, None, 0.0, 1, f"{type(error).__name__}: {error}"))
    return solved


def _finished(out: Path, rel: str) -> bool:
    return (out / rel / _MARKER).is_file()


def _solved_stream(root: Path, folders: Sequence[Path], settings: _Settings, batch_size: int,
                   workers: int) -> Iterator[_Solved]:
    """Decode ``folders`` with ``workers`` processes and solve them here, in batches (the CUDA and notebook path)."""
    loader = DataLoader(
        _SampleFolders(root, folders, settings.score), batch_size=batch_size, shuffle=False, num_workers=workers,
        collate_fn=_collate, persistent_workers=False, prefetch_factor=2 if workers else None,
    )
    device = torch.device(settings.device)
    cards = _Cards(device, settings.dtype)
    for items in loader:
        yield from _solve(items, cards, device, settings)


# ------------------------------------------------------------------------------------------------ chunks


def _run_chunk(out: str | Path, chunk: Sequence[tuple[str, str]], settings: _Settings,
               cards: _Cards | None = None) -> list[BatchRecord]:
    """Decode, solve, score and write one chunk of sample folders: the unit of work of the CPU workers and of
    each Dask task.

    Args:
        out: the output folder (on a Dask worker: as the worker sees it).
        chunk: ``(sample folder, path relative to the root)`` pairs; samples sharing a key are solved in one batch.
            The relative path names the output folder ``out/<rel>`` and the summary row.
        settings: the run's settings.
        cards: the card cache to use; None: this process's (:data:`_PROCESS_CARDS`).

    Returns:
        each sample's record, done or failed, in the order the groups were solved.

    Raises:
        InputError: ``settings.device`` is CUDA and this process sees no CUDA device.
    """
    device = torch.device(settings.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {settings.device} was asked for, but torch sees no CUDA device on this worker")
    out = Path(out)
    cards = _process_cards(device, settings.dtype) if cards is None else cards
    items = [_decode(Path(folder), rel, settings.score) for folder, rel in chunk]
    return [_finish(out, solved, settings) for solved in _solve(items, cards, device, settings)]


class _Chunks(Dataset):
    """One item is one chunk run to the end in a worker process: only its summary rows come back."""

    def __init__(self, out: Path, chunks: list[list[tuple[str, str]]], settings: _Settings) -> None:
        self.out, self.chunks, self.settings = out, chunks, settings

    def __len__(self) -> int:
        return len(self.chunks)

    def __getitem__(self, index: int) -> list[BatchRecord]:
        return _run_chunk(self.out, self.chunks[index], self.settings)


def _set_threads(threads: int, worker_id: int) -> None:
    """DataLoader worker start: the worker's share of the intra-op threads (the loader sets 1)."""
    torch.set_num_threads(threads)


def _chunked(root: Path, folders: Sequence[Path], size: int) -> list[list[tuple[str, str]]]:
    """Consecutive ``(absolute folder, relative path)`` chunks of ``size`` samples (in ``find_samples`` order,
    samples of one calibration lie together)."""
    pairs = [(str(folder.absolute()), _relative(root, folder)) for folder in folders]
    return [pairs[start : start + size] for start in range(0, len(pairs), size)]


def _local_chunks(root: Path, out: Path, folders: Sequence[Path], settings: _Settings, batch_size: int,
                  workers: int) -> Iterator[BatchRecord]:
    """Run the chunks on the CPU: in this process (``workers=0``) or in ``workers`` DataLoader processes, each with
    ``torch.get_num_threads() // workers`` threads (a sample per core beats a sample over all cores: elementwise
    maths on 5 MB stacks is memory bound, and threads in two processes on one core stall each other)."""
    chunks = _chunked(root, folders, batch_size)
    if workers == 0:
        cards = _Cards(torch.device(settings.device), settings.dtype)  # this run's own: decoded once per run
        for chunk in chunks:
            yield from _run_chunk(out, chunk, settings, cards)
        return
    threads = max(1, torch.get_num_threads() // workers)
    loader = DataLoader(_Chunks(out, chunks, settings), batch_size=None, shuffle=False, num_workers=workers,
                        collate_fn=_collate, worker_init_fn=partial(_set_threads, threads), persistent_workers=False)
    for records in loader:
        yield from records


def _dask_chunks(root: Path, out: Path, folders: Sequence[Path], settings: _Settings, batch_size: int,
                 scheduler: str | None, client: Any, timeout_s: float) -> Iterator[BatchRecord]:
    """Run the chunks as Dask tasks; a task that raises (or whose worker dies) fails its own samples only."""
    from psmini import _dask

    chunks = _chunked(root, folders, batch_size)
    task = partial(_run_chunk, str(out.absolute()), settings=settings)
    for index, records, error in _dask.map_chunks(task, chunks, scheduler=scheduler, client=client,
                                                  timeout_s=timeout_s):
        if records is None:  # the task raised (error), or its worker died
            message = f"{type(error).__name__}: {error}"
            logger.warning("a Dask task of %d samples failed: %s", len(chunks[index]), message)
            records = [BatchRecord(rel, "failed", batch_size=len(chunks[index]), error=message)
                       for _, rel in chunks[index]]
        yield from records


# ------------------------------------------------------------------------------------------------ arguments


def _check_arguments(root: str | Path, batch_size: int, workers: int, config: ReconstructionConfig,
                     local_device: bool = True) -> tuple[Path, torch.device]:
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"ROOT {root} does not exist or is not a folder")
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise InputError(f"batch_size must be a positive integer, got {batch_size!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise InputError(f"workers must be an integer >= 0, got {workers!r}")
    if not isinstance(config, ReconstructionConfig):
        raise InputError(f"config must be a psmini ReconstructionConfig, got {type(config).__name__}")
    device = torch.device(config.device)
    if local_device and device.type == "cuda" and not torch.cuda.is_available():
        raise InputError("device cuda was asked for, but torch sees no CUDA device on this machine")
    return root, device


def _check_out(out: Path) -> Path:
    """``out`` when it can become the output folder, checked before any work (it is created only when samples are
    written): a file at ``out`` or at a folder above it, or a read-only folder above it, would fail the run only
    after every sample was solved."""
    if out.exists() and not out.is_dir():
        raise DataFormatError(f"the output folder {out} exists and is not a folder")
    above = nearest_existing(out)
    if not above.is_dir():
        raise DataFormatError(f"cannot create the output folder {out}: {above} is a file, not a folder")
    if not os.access(above, os.W_OK | os.X_OK):
        raise DataFormatError(f"cannot create the output folder {out}: {above} is not writable")
    return out


def _check_out_spares_samples(root: Path, out: Path, folders: Sequence[Path]) -> None:
    """Refuse an ``out`` where a sample's output folder ``out/<rel>`` would be a sample folder or hold one: the
    atomic writer replaces the whole output folder, so the capture would be deleted (``out`` = ``root``)."""
    for folder in folders:
        sample, target = folder.resolve(), (out / _relative(root, folder)).resolve()
        if target == sample or target in sample.parents:
            raise InputError(f"out {out} would write the outputs of sample {folder} over the sample itself "
                             f"(output folder {target}); choose an output folder apart from ROOT {root}")


def _samples_under(root: Path) -> tuple[list[Path], dict[str, str]]:
    """The sample folders under ``root`` (links followed) and the links that could not be followed, by the path
    relative to ``root`` (each becomes a failed sample of the summary: the other samples go on)."""
    from psmini.io import scan_samples

    scan = scan_samples(root)
    if not scan.samples and not scan.problems:
        raise InputError(f"no sample folders (capture.json, or DiLiGenT filenames.txt + light_directions.txt) "
                         f"under {root}")
    return scan.samples, {_relative(root, path): message for path, message in scan.problems.items()}


def iter_reconstructions(
    root: str | Path,
    config: ReconstructionConfig | None = None,
    *,
    batch_size: int = 8,
    workers: int = 0,
) -> Iterator[tuple[str, Reconstruction]]:
    """Reconstruct every sample under ``root`` in batches and yield them one by one (for notebooks).

    Nothing is written. Samples are decoded in ``workers`` processes and solved in this one. Samples that cannot
    be read or solved are logged (warning) and left out.

    Args:
        root: a folder holding capture folders and DiLiGenT folders at any depth (or one of them).
        config: the :class:`~psmini.config.ReconstructionConfig` of every sample (default: the default one;
            its ``device`` and ``dtype`` say where and how to compute).
        batch_size: samples decoded per loader batch; those sharing a size, lights and card are solved together.
        workers: decoding processes (0: decode in this process).

    Yields:
        ``(sample, reconstruction)``: the sample folder relative to ``root`` and a batch-1
        :class:`~psmini.pipeline.Reconstruction` on ``device``, in the order of :func:`psmini.io.find_samples`
        within each loader batch.

    Raises:
        InputError: ``root`` missing, no samples under it, bad ``batch_size``, ``workers`` or ``config``,
            CUDA asked for and absent.

    Example:
        >>> for name, result in iter_reconstructions("captures", batch_size=16):  # doctest: +SKIP
        ...     print(name, result.depth.std())
    """
    config = ReconstructionConfig() if config is None else config
    root, _ = _check_arguments(root, batch_size, workers, config)
    folders, _ = _samples_under(root)  # scan_samples has logged the links it could not follow
    settings = _Settings(config)
    for solved in _solved_stream(root, folders, settings, batch_size, workers):
        if solved.result is None:
            logger.warning("sample %s failed: %s", solved.item.rel, solved.error)
            continue
        yield solved.item.rel, solved.result


# ------------------------------------------------------------------------------------------------ writing


def _write(out_dir: Path, result: Reconstruction, sample, outputs: tuple[str, ...], metadata: dict[str, Any]) -> None:
    """Write the chosen outputs of one sample atomically; ``outputs.json`` carries its summary row and config."""
    from psmini.geometry import depth_to_points
    from psmini.io import save_albedo_png, save_depth, save_normal_png, save_normal_std, save_ply, write_outputs
    from psmini.io._atomic import atomic_folder
    from psmini.io.export import NORMALS_BIT_DEPTH

    pitch = sample.pixel_pitch_mm
    if outputs == OUTPUT_KINDS:
        write_outputs(out_dir, result.to("cpu"), pixel_pitch_mm=pitch, metadata=metadata, overwrite=True)
        return
    albedo, normals = result.albedo.detach().cpu(), result.normals.detach().cpu()
    depth, mask = result.depth.detach().cpu(), result.mask.detach().cpu()
    names: list[str] = []
    with atomic_folder(out_dir, overwrite=True) as target:
        if "albedo" in outputs:
            save_albedo_png(target / "albedo.png", albedo, mask)
            names.append("albedo.png")
        if "normals" in outputs:
            save_normal_png(target / "normals.png", normals, mask, bit_depth=NORMALS_BIT_DEPTH)
            names.append("normals.png")
        if "depth" in outputs:
            units = "mm" if pitch is not None else "pixels"
            names += [p.name for p in save_depth(target / "depth.npy", depth, mask, units=units, pixel_pitch_mm=pitch)]
        if "ply" in outputs:
            points = depth_to_points(depth.double(), 1.0 if pitch is None else float(pitch))
            save_ply(target / "points.ply", points, albedo, mask)
            names.append("points.ply")
        normal_std = getattr(result, "normal_std", None)
        counts = {} if normal_std is None else save_normal_std(target / "normal_std.npy", normal_std.cpu(), mask)
        names += ["normal_std.npy", "normal_std.png"] if counts else []
        summary = {"files": names, "size": list(depth.shape[-1:-3:-1]), "pixel_pitch_mm": pitch, **counts,
                   "metadata": metadata}
        (target / _MARKER).write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n", encoding="utf-8")


def _remove_stale_temporaries(out_dirs: Sequence[Path]) -> None:
    """Remove the ``.NAME.tmp-XXXXXXXX`` folders that a killed run left beside the output folders ``out_dirs``
    (the atomic writer's temporaries): once per run, each parent folder listed once (listing the parent for every
    sample cost 1.8 ms a sample beside 2,000 outputs, quadratic in the dataset's size)."""
    names_by_parent: dict[Path, set[str]] = {}
    for out_dir in out_dirs:
        names_by_parent.setdefault(out_dir.parent, set()).add(out_dir.name)
    stale_name = re.compile(r"\.(.+)\.tmp-[0-9a-f]{8}")
    for parent, names in names_by_parent.items():
        try:
            entries = list(os.scandir(parent))
        except OSError:  # no such folder yet: nothing was left there
            continue
        for entry in entries:
            match = stale_name.fullmatch(entry.name)
            if match and match.group(1) in names and entry.is_dir(follow_symlinks=False):
                logger.info("removing %s, left by an interrupted run", entry.path)
                shutil.rmtree(entry.path, ignore_errors=True)


def _previous_record(out: Path, rel: str) -> BatchRecord:
    """The summary row a finished sample's ``outputs.json`` kept, marked skipped."""
    try:
        kept = json.loads((out / rel / _MARKER).read_text(encoding="utf-8")).get("metadata", {}).get("batch", {})
    except (OSError, ValueError):
        kept = {}
    scores = {k: kept[k] for k in SUMMARY_FIELDS
              if k.endswith(("_deg", "_mm", "_share")) and isinstance(kept.get(k), float)}
    return BatchRecord(rel, "skipped", solver=str(kept.get("solver", "")), scores=scores)


def _scores(result: Reconstruction, sample) -> dict[str, float]:
    from psmini.evaluation import score_reconstruction

    if sample.normals_gt is None:
        return {}
    scores = score_reconstruction(result, sample)
    return {k: float(v) for k, v in scores.items()
            if k.endswith(("_deg", "_mm", "_share")) and math.isfinite(float(v))}


def _normal_std_median(result: Reconstruction) -> float | None:
    """The median of near light's predicted normal error over the solved pixels, degrees (None for a distant-light
    result or nothing solved)."""
    normal_std = getattr(result, "normal_std", None)
    if normal_std is None or not bool(result.mask.any()):
        return None
    return float(normal_std[result.mask].median())


def _write_summary(out: Path, records: list[BatchRecord], settings: dict[str, Any]) -> dict[str, Any]:
    rows = [record.row() for record in records]
    counts = {status: sum(r["status"] == status for r in rows) for status in ("done", "skipped", "failed")}
    summary = {"settings": settings, "counts": counts, "samples": rows}
    out.mkdir(parents=True, exist_ok=True)
    save_summary(out, summary, SUMMARY_FIELDS)
    return summary


def save_summary(out: Path, summary: dict[str, Any], fieldnames: list[str] | tuple[str, ...]) -> None:
    """Write ``out/summary.csv`` (the ``fieldnames`` columns of ``summary["samples"]``; None and missing cells
    empty) and ``out/summary.json``, each through a temporary file replaced at the end."""
    def write_csv(handle) -> None:
        writer = csv.DictWriter(handle, fieldnames=list(fieldnames))
        writer.writeheader()
        writer.writerows(summary["samples"])

    for name, write in (("summary.csv", write_csv),
                        ("summary.json", lambda handle: handle.write(json.dumps(summary, indent=2) + "\n"))):
        temporary = out / f".{name}.tmp"
        with temporary.open("w", newline="", encoding="utf-8") as handle:
            write(handle)
        temporary.replace(out / name)


def reconstruct_dataset(
    root: str | Path,
    out: str | Path,
    config: ReconstructionConfig | None = None,
    *,
    batch_size: int = 8,
    workers: int = 0,
    outputs: str | Sequence[str] | None = None,
    score: bool = True,
    progress: Callable[[BatchRecord], None] | None = None,
    scheduler: str | None = None,
    client: Any = None,
    scheduler_timeout_s: float = 10.0,
) -> dict[str, Any]:
    """Reconstruct every sample under ``root`` into ``out/<relative path>``, resuming an earlier run.

    Samples whose output folder already holds ``outputs.json`` are skipped (their earlier summary row is kept).
    The rest are split into chunks of ``batch_size`` consecutive samples; each chunk is decoded, solved in batches
    of samples sharing a size, lights and card, and written atomically: ``albedo.png``, ``normals.png``,
    ``depth.npy``/``.png``/``.json``, ``points.ply`` (as :func:`psmini.io.write_outputs`; only those chosen by
    ``outputs``), with near light ``normal_std.npy`` and ``normal_std.png`` (each normal's predicted error, whatever
    ``outputs`` chooses: it concerns every product) and ``outputs.json``, whose ``metadata.batch`` holds the
    sample's summary row. ``out/summary.csv`` and ``out/summary.json`` list every sample with its status, times,
    the median predicted normal error (near light) and, when it has ground truth, errors
    (:func:`psmini.evaluation.score_reconstruction`).

    Where the chunks run: on the CPU, in ``workers`` processes that each decode, solve and write whole chunks; on
    CUDA, decoded in ``workers`` processes and solved on the GPU here; with ``scheduler`` or ``client``, as tasks
    of a ``dask.distributed`` cluster (``pip install psmini[dask]``), each on its worker's ``device``. Every
    backend runs the same chunk code and gives the same files and summary.

    Args:
        root: a folder holding capture folders and DiLiGenT folders at any depth (or one of them). With Dask,
            ``root`` and ``out`` must be the same paths on every worker (a shared file system).
        out: the output folder (created).
        config, batch_size: see :func:`iter_reconstructions`; the resolved configuration of each sample is
            written into its ``outputs.json``. On CPU, small batches (about 4) are fastest per sample.
        workers: local worker processes (0: everything in this process); not used with Dask.
        outputs: which of :data:`OUTPUT_KINDS` to write (a list or ``"normals,albedo,depth,ply"``); None: all.
        score: measure the errors against ground truth of the samples that have it (costs about as much as
            the reconstruction itself on the CPU).
        progress: called with each sample's :class:`BatchRecord` as soon as it is finished, skipped or failed.
        scheduler: a Dask scheduler address (``"tcp://head:8786"``), or ``"local"`` / ``"local:N"`` for a
            ``LocalCluster`` of N single-threaded worker processes started for this run (N: the CPU count).
        client: a ``distributed.Client`` to use instead (kept open); exclusive with ``scheduler``.
        scheduler_timeout_s: how long to wait for the scheduler, and for its first worker, seconds.

    Returns:
        the summary: ``{"settings": ..., "counts": {"done", "skipped", "failed"}, "samples": [row, ...]}`` with
        rows as in ``summary.csv`` (:data:`SUMMARY_FIELDS`), in the order of :func:`psmini.io.find_samples`.

    Raises:
        InputError: ``root`` missing, no samples under it, bad ``outputs``, ``batch_size``, ``workers`` or
            ``config``, CUDA asked for and absent (here; on Dask workers the samples fail instead), both
            ``scheduler`` and ``client``, a bad ``local:N``, a scheduler that cannot be reached or has no worker,
            dask.distributed not installed; an ``out`` where a sample's output folder would replace the sample
            (``out`` equal to ``root``), checked before any work.
        DataFormatError: ``out`` cannot be written: a file at it or above it, a read-only folder above it (checked
            before any work).

    Example:
        >>> summary = reconstruct_dataset("captures", "reconstructions", batch_size=4, workers=2)  # doctest: +SKIP
        >>> summary["counts"]  # doctest: +SKIP
        {'done': 198, 'skipped': 0, 'failed': 2}
        >>> reconstruct_dataset("captures", "out", scheduler="tcp://head:8786", device="cuda")  # doctest: +SKIP
    """
    kinds = parse_outputs(outputs)
    dask = scheduler is not None or client is not None
    if scheduler is not None and client is not None:
        raise InputError("give a Dask scheduler address or a client, not both")
    config = ReconstructionConfig() if config is None else config
    root, device = _check_arguments(root, batch_size, workers, config, local_device=not dask)
    if scheduler is not None:
        from psmini._dask import parse_scheduler

        parse_scheduler(scheduler)  # a malformed local:N fails before any work
    out = _check_out(Path(out))
    folders, problems = _samples_under(root)
    _check_out_spares_samples(root, out, folders)
    records: dict[str, BatchRecord] = {}
    for rel, message in problems.items():  # dangling links and cycles: failed, the others go on
        records[rel] = BatchRecord(rel, "failed", error=f"DataFormatError: {message}")
        if progress is not None:
            progress(records[rel])
    todo = []
    for folder in folders:
        rel = _relative(root, folder)
        if _finished(out, rel):
            records[rel] = _previous_record(out, rel)
            if progress is not None:
                progress(records[rel])
        else:
            todo.append(folder)
    logger.info("%d samples under %s: %d finished earlier, %d to do", len(folders), root, len(records), len(todo))
    _remove_stale_temporaries([out / _relative(root, folder) for folder in todo])
    settings = _Settings(config, kinds, score)
    if not todo:
        stream: Iterator[BatchRecord] = iter(())
    elif dask:
        stream = _dask_chunks(root, out, todo, settings, batch_size, scheduler, client, scheduler_timeout_s)
    elif device.type == "cpu":
        stream = _local_chunks(root, out, todo, settings, batch_size, workers)
    else:
        solved_stream = _solved_stream(root, todo, settings, batch_size, workers)
        stream = (_finish(out, solved, settings) for solved in solved_stream)
    for record in stream:
        records[record.sample] = record
        if progress is not None:
            progress(record)
    settings_row = {"root": str(root), "out": str(out), "config": config.to_dict(), "batch_size": batch_size,
                    "workers": workers, "outputs": list(kinds), "score": score,
                    "scheduler": _scheduler_name(scheduler, client)}
    return _write_summary(out, [records[_relative(root, f)] for f in folders] + [records[rel] for rel in problems],
                          settings_row)


def _scheduler_name(scheduler: str | None, client: Any) -> str | None:
    if client is not None:
        return str(client.scheduler.address)
    return scheduler


def _finish(out: Path, solved: _Solved, settings: _Settings) -> BatchRecord:
    """Score and write one solved sample; any error of its own becomes a failed record."""
    item = solved.item
    record = BatchRecord(item.rel, "failed", decode_s=item.decode_s, compute_s=solved.compute_s,
                         batch_size=solved.batch_size, error=solved.error)
    if solved.result is None:
        record.time_s = record.decode_s + record.compute_s
        logger.warning("sample %s failed: %s", item.rel, solved.error)
        return record
    start = time.perf_counter()
    try:
        resolved = settings.config.resolved(item.sample.lights, item.sample.mask is not None)
        record.solver = resolved.solver
        record.normal_std_median_deg = _normal_std_median(solved.result)
        record.scores = _scores(solved.result, item.sample) if settings.score else {}
        record.status, record.error = "done", ""
        record.time_s = item.decode_s + solved.compute_s
        _write(out / item.rel, solved.result, item.sample, settings.kinds,
               {"batch": record.row(), "config": resolved.to_dict()})
    except PsminiError as error:
        record.status, record.error = "failed", f"{type(error).__name__}: {error}"
        logger.warning("sample %s failed: %s", item.rel, record.error)
    record.write_s = time.perf_counter() - start
    record.time_s = record.decode_s + record.compute_s + record.write_s
    return record
