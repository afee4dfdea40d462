"""Atomic file writes and file-name helpers shared by every writer of the library.

Every output file is written to a temporary file in the destination folder and renamed over the
target only once it is complete, so a failed or cancelled run never leaves a partial file. The
temporary file is created with mode 0666 minus the process umask (as ``open()`` would), so the
final file has the usual permissions (0644 under umask 022).
"""

from __future__ import annotations

import contextlib
import os
import secrets
from typing import Union

from ..errors import InputError

PathLike = Union[str, os.PathLike]

# Permission bits requested for a new output file; the kernel removes the umask's bits.
NEW_FILE_MODE = 0o666


@contextlib.contextmanager
def atomic_path(path: PathLike):
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    The temporary file keeps the target's extension because some writers choose the format
    by extension. On any exception (including KeyboardInterrupt) it is removed.

    Parameters
    ----------
    path : str or os.PathLike
        The final file. Its folder must exist (InputError otherwise).
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"Output folder does not exist: {folder}")
    base = os.path.basename(path)
    ext = extension(base) or os.path.splitext(base)[1]
    while True:
        tmp = os.path.join(folder, f".{base}.{secrets.token_hex(4)}.part{ext}")
        try:
            # O_EXCL: never reuse another writer's file; the mode is filtered by the umask.
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, NEW_FILE_MODE)
        except FileExistsError:
            continue
        os.close(fd)
        break
    try:
        yield tmp
        if not os.path.exists(tmp) or os.path.getsize(tmp) == 0:
            raise OSError(f"Writing {path} produced no data.")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_text(text: str, path: PathLike) -> None:
    """Write a text file atomically (reports, summaries)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as f:
            f.write(text)


def ensure_folder(path: PathLike) -> str:
    """Create the folder of ``path`` if needed; return ``path``."""
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    return path


def extension(name: PathLike) -> str:
    """Lower-case extension, with the double extensions this module knows (.seg.nrrd, .nii.gz)."""
    low = os.fspath(name).lower()
    for double in (".seg.nrrd", ".nii.gz"):
        if low.endswith(double):
            return double
    return os.path.splitext(low)[1]
