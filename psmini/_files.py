"""Write a file atomically: into a temporary sibling, renamed into place only when complete; find what stands in the
way of a path before any work. Internal.

Beside :mod:`psmini.io._atomic` (folders) rather than in it: :mod:`psmini.viz`, which the maths modules reach
through :meth:`~psmini.result.Reconstruction.show`, writes its pages this way and may not import :mod:`psmini.io`.
"""

from __future__ import annotations

import logging
import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from psmini.errors import DataFormatError

logger = logging.getLogger(__name__)


@contextmanager
def atomic_file(destination: str | Path) -> Iterator[Path]:
    """Yield a fresh, empty temporary file beside ``destination``; on success rename it to ``destination``.

    The temporary file is named ``.NAME.tmp-XXXXXXXX`` in the destination's folder (created when missing), with
    the permissions a plain ``open`` gives (the umask's). On any exception it is removed and the exception
    propagates (an ``OSError`` as a DataFormatError naming the destination): an earlier file at ``destination``
    is kept, and no half-written one is left there.

    Raises:
        DataFormatError: the destination is a folder, its folder cannot be created (a file stands on the path),
            or the file cannot be written.
    """
    destination = Path(destination)
    if destination.is_dir():
        raise DataFormatError(f"{destination} is a folder; expected the path of a file to write")
    try:
        destination.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:  # a file where a folder of the path should be
        raise DataFormatError(f"cannot write {destination}: cannot create its folder {destination.parent} "
                              f"({error})") from error
    try:
        while True:
            temporary = destination.parent / f".{destination.name}.tmp-{secrets.token_hex(4)}"
            try:
                os.close(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
                break
            except FileExistsError:
                continue
    except OSError as error:
        raise DataFormatError(f"cannot write {destination}: {error}") from error
    try:
        yield temporary
        os.replace(temporary, destination)
    except BaseException as error:
        temporary.unlink(missing_ok=True)
        if isinstance(error, OSError) and not isinstance(error, DataFormatError):
            raise DataFormatError(f"cannot write {destination}: {error}") from error
        raise
    logger.debug("wrote file %s", destination)


def nearest_existing(path: Path) -> Path:
    """``path`` when it exists, else the nearest folder above it that does: where creating ``path`` starts, which
    a caller checks before any work (a file there is a file where a folder should be)."""
    return next(candidate for candidate in (path, *path.parents) if candidate.exists())
