"""The lights file: a calibrated light model in JSON, with per-LED residuals and provenance.

Specification: ``docs/lights-file.md``. ``psmini calibrate sphere`` writes it; ``psmini reconstruct --lights``
and ``psmini evaluate --lights`` use it in place of a folder's own lights.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from psmini.errors import DataFormatError, InputError, PsminiError

if TYPE_CHECKING:
    from psmini.lights import LightModel

__all__ = ["LIGHTS_FORMAT", "LIGHTS_VERSION", "LightsFile", "write_lights_file", "read_lights_file", "with_lights_file"]

LIGHTS_FORMAT = "psmini-lights"
LIGHTS_VERSION = 1


@dataclass
class LightsFile:
    """A lights file in memory.

    Attributes:
        lights: the light model (a module of :mod:`psmini.lights`).
        leds: one object per LED (``name``, ``direction``, ``residual_mm``, ``highlights_px`` where known).
        provenance: how the calibration was made.
        path: the file it was read from, or None.
    """

    lights: LightModel
    leds: list[dict[str, Any]] = field(default_factory=list)
    provenance: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    @property
    def count(self) -> int:
        """Number of LEDs K."""
        return int(self.lights.count)


def write_lights_file(
    path: str | Path,
    lights: LightModel | Mapping[str, Any],
    *,
    leds: Sequence[Mapping[str, Any]] | None = None,
    provenance: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a lights file atomically (a temporary file in the same folder, renamed into place).

    Args:
        path: the destination ``.json`` file.
        lights: a light model of :mod:`psmini.lights` or its JSON object (``docs/capture-format.md``).
        leds: optional per-LED objects (K of them), e.g. ``{"name": ..., "direction": [x, y, z],
            "residual_mm": r, "highlights_px": [[u, v], ...]}``.
        provenance: how it was calibrated (method, sources, intrinsics, sphere radius, ...).
        overwrite: replace an existing file.

    Returns:
        the path.

    Raises:
        InputError: a light model that is not valid, per-LED objects not counting K, values that do not
            serialise to JSON.
        DataFormatError: the file exists (without ``overwrite``) or cannot be written.

    Example:
        >>> from psmini.lights import DirectionalLights, ring_lights
        >>> write_lights_file("lights.json", DirectionalLights(ring_lights(8, 55.0)))  # doctest: +SKIP
    """
    from psmini import __version__
    from psmini.lights import lights_from_dict, lights_to_dict

    path = Path(path)
    try:
        module = lights_from_dict(lights) if isinstance(lights, Mapping) else lights
        entry = lights_to_dict(module)
    except PsminiError as error:
        raise InputError(f"not a valid light model: {error}") from error
    leds = [dict(led) for led in (leds or [])]
    if leds and len(leds) != module.count:
        raise InputError(f"leds must hold one object per LED ({module.count}), got {len(leds)}")
    if path.exists() and not overwrite:
        raise DataFormatError(f"{path} exists; pass overwrite=True (--overwrite) to replace it")
    document = {
        "format": LIGHTS_FORMAT,
        "version": LIGHTS_VERSION,
        "lights": entry,
        "leds": leds,
        "provenance": {
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "software": f"psmini {__version__}",
            **dict(provenance or {}),
        },
    }
    try:
        text = json.dumps(document, indent=2, allow_nan=False)
    except (TypeError, ValueError) as error:
        raise InputError(f"the lights file does not serialise to JSON: {error}") from error
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as error:  # a file where a folder of the path should be
        raise DataFormatError(f"cannot write {path}: cannot create a file in {path.parent} ({error})") from error
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as stream:
            stream.write(text + "\n")
        os.replace(temporary, path)
    except OSError as error:
        Path(temporary).unlink(missing_ok=True)
        raise DataFormatError(f"cannot write {path}: {error}") from error
    return path


def read_lights_file(path: str | Path) -> LightsFile:
    """Read and validate a lights file.

    Args:
        path: the ``.json`` file.

    Returns:
        :class:`LightsFile`.

    Raises:
        DataFormatError: a missing file, invalid JSON, a wrong format name, a newer or invalid version, a light
            model that is missing or invalid, per-LED objects that do not count the model's LEDs.

    Example:
        >>> read_lights_file("lights.json").lights.count  # doctest: +SKIP
        8
    """
    from psmini.lights import lights_from_dict

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"lights file {path} does not exist")
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataFormatError(f"lights file {path} is not valid JSON: {error}") from error
    if not isinstance(document, dict) or document.get("format") != LIGHTS_FORMAT:
        found = document.get("format") if isinstance(document, dict) else type(document).__name__
        raise DataFormatError(f"lights file {path}: format must be {LIGHTS_FORMAT!r}, got {found!r}")
    version = document.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise DataFormatError(f"lights file {path}: version must be a positive integer, got {version!r}")
    if version > LIGHTS_VERSION:
        raise DataFormatError(f"lights file {path}: version {version} is newer than this psmini reads "
                              f"({LIGHTS_VERSION})")
    entry = document.get("lights")
    if not isinstance(entry, Mapping):
        raise DataFormatError(f"lights file {path}: lights must be a JSON object (a light model), got "
                              f"{type(entry).__name__}")
    try:
        lights = lights_from_dict(entry)
    except PsminiError as error:
        raise DataFormatError(f"lights file {path}: bad light model: {error}") from error
    leds = document.get("leds") or []
    if not isinstance(leds, list) or (leds and len(leds) != lights.count) or not all(isinstance(x, dict) for x in leds):
        raise DataFormatError(f"lights file {path}: leds must be a list of {lights.count} objects, got {leds!r:.80}")
    provenance = document.get("provenance") or {}
    if not isinstance(provenance, dict):
        raise DataFormatError(f"lights file {path}: provenance must be a JSON object")
    return LightsFile(lights, leds, provenance, path)


def with_lights_file(sample: Any, path: str | Path) -> Any:
    """A copy of a loaded sample (:class:`psmini.io.Sample`) whose lights are those of a lights file.

    Args:
        sample: the sample.
        path: the lights file.

    Returns:
        the sample with ``lights`` replaced (``meta["lights_file"]`` records the file).

    Raises:
        DataFormatError: as :func:`read_lights_file`, and when the file's LED count differs from the sample's
            image count.

    Example:
        >>> sample = with_lights_file(load_sample("captures/denim"), "lights.json")  # doctest: +SKIP
    """
    lights = read_lights_file(path)
    if lights.count != sample.count:
        raise DataFormatError(
            f"lights file {path} has {lights.count} LEDs but sample {sample.name} has {sample.count} images; "
            "they must be equal"
        )
    return dataclasses.replace(sample, lights=lights.lights, meta={**sample.meta, "lights_file": str(path)})
