"""``.npy`` arrays read and written with psmini's errors: each failure a DataFormatError naming the file. Internal."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from psmini._files import atomic_file, nearest_existing
from psmini.errors import DataFormatError


def read_npy(path: str | Path, what: str = "array") -> np.ndarray:
    """The array of a ``.npy`` file (no pickled objects).

    Args:
        path: the file.
        what: what the file holds, for the message (``"normals"``, ``"ground truth 'gt/depth.npy'"``).

    Raises:
        DataFormatError: the file is missing, not a file, empty, cut short, not an ``.npy`` array (an ``.npz``
            archive, pickled objects, another format).
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{what} file {path} does not exist" if not path.exists() else
                              f"{what} {path} is not a file")
    try:
        # numpy raises EOFError for an empty file, ValueError for a cut or foreign one, OSError for unreadable
        array = np.load(path, allow_pickle=False)
    except EOFError as error:
        raise DataFormatError(f"cannot read {what} {path}: the file is empty or cut short ({error})") from error
    except (OSError, ValueError) as error:
        raise DataFormatError(f"cannot read {what} {path}: {error}") from error
    if not isinstance(array, np.ndarray):  # an .npz archive under an .npy name
        raise DataFormatError(f"cannot read {what} {path}: expected one .npy array, got an .npz archive")
    return array


def save_npy(path: str | Path, array: np.ndarray) -> Path:
    """Write ``array`` to ``path`` atomically (a temporary file beside it, renamed into place when complete).

    As :func:`numpy.save`, ``.npy`` is appended to a name that does not end with it; the path written is returned.

    Raises:
        DataFormatError: ``path`` is a folder, or it (or its folder) cannot be written; nothing is left at
            ``path`` then (an earlier file there is kept).
    """
    path = npy_path(path)
    # a file object, not the temporary's name: np.save would append .npy to it
    with atomic_file(path) as temporary, temporary.open("wb") as stream:
        np.save(stream, array)
    return path


def npy_path(path: str | Path) -> Path:
    """The path :func:`save_npy` writes for ``path``: ``.npy`` appended to a name without it, as numpy does."""
    path = Path(path)
    return path if path.name.endswith(".npy") else path.with_name(path.name + ".npy")


def check_npy_target(path: str | Path) -> Path:
    """Refuse, before any work, a ``.npy`` output that :func:`save_npy` could not write: a folder at its path, or a
    file where one of its folders should be (a command writing two maps left the first written when the second
    failed). Nothing is created.

    Raises:
        DataFormatError: naming the path and what stands in its way.
    """
    path = npy_path(path)
    if path.is_dir():
        raise DataFormatError(f"{path} is a folder; expected the path of a file to write")
    existing = nearest_existing(path.parent)
    if not existing.is_dir():
        raise DataFormatError(f"cannot write {path}: {existing} is a file, not a folder")
    return path
