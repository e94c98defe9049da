"""Write a folder atomically: into a temporary sibling, renamed into place only when complete (a file:
:mod:`psmini._files`). Internal."""

from __future__ import annotations

import logging
import os
import secrets
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from psmini.errors import DataFormatError

logger = logging.getLogger(__name__)


@contextmanager
def atomic_folder(destination: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a fresh temporary folder beside ``destination``; on success rename it to ``destination``.

    The temporary folder is named ``.NAME.tmp-XXXX`` in the destination's parent (same file system, so the
    rename is atomic). On any exception it is removed and the exception propagates: the destination is
    never left half-written. With ``overwrite=True`` an existing destination is replaced by :func:`swap_in`.

    Raises:
        DataFormatError: when the destination exists and ``overwrite`` is False, exists and is not a folder,
            or the parent folder cannot be created or written.
    """
    destination = Path(destination)
    _refuse_existing(destination, overwrite)
    try:
        destination.parent.mkdir(parents=True, exist_ok=True)
        temporary = _fresh_sibling(destination, "tmp")
    except OSError as error:
        raise DataFormatError(f"cannot create a folder beside {destination}: {error}") from error
    try:
        yield temporary
        _refuse_existing(destination, overwrite)  # again: someone may have created it meanwhile
        swap_in(temporary, destination)
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise
    logger.debug("wrote folder %s", destination)


def swap_in(new: Path, destination: Path) -> None:
    """Rename the folder ``new`` to ``destination``. An existing ``destination`` is first moved aside, into a fresh
    hidden sibling, and deleted once ``new`` is in place; when that rename fails it is moved back, so the old folder
    is never lost nor left hidden beside it."""
    if not destination.exists():
        os.replace(new, destination)
        return
    old = _fresh_sibling(destination, "old")
    aside = old / destination.name
    os.replace(destination, aside)
    try:
        os.replace(new, destination)
    except BaseException:
        os.replace(aside, destination)
        shutil.rmtree(old, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)


def _fresh_sibling(destination: Path, tag: str) -> Path:
    """Create ``.NAME.TAG-XXXXXXXX`` beside ``destination`` with os.mkdir, which honours the umask (mkdtemp
    would leave the finished folder readable by its owner only)."""
    while True:
        candidate = destination.parent / f".{destination.name}.{tag}-{secrets.token_hex(4)}"
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            continue


def _refuse_existing(destination: Path, overwrite: bool) -> None:
    if destination.exists() and not destination.is_dir():
        raise DataFormatError(f"{destination} exists and is not a folder")
    if destination.exists() and not overwrite:
        raise DataFormatError(f"{destination} already exists; pass overwrite=True (--overwrite) to replace it")
