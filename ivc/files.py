"""Files: atomic writes and content digests, for every stage that writes or records a file.

:func:`atomic_path` writes beside the target and renames over it only when complete, so an
interrupted write leaves the previous file as it was; :func:`file_digest` is the SHA-256 a table's
provenance and a corrected recording record of their input.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_path", "check_writable", "file_digest"]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, copy_existing: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it over ``path`` on success.

    With ``copy_existing`` the temporary file starts as a copy of ``path``. On any
    exception the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as error:  # name the file asked for, not the hidden temporary one beside it
        raise type(error)(error.errno, f"cannot write it into {path.parent} ({error.strerror})", str(path)) from None
    os.close(fd)
    tmp = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual permissions
    try:
        if copy_existing:
            shutil.copyfile(path, tmp)
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def check_writable(path: str | os.PathLike) -> None:
    """Refuse, before any work, a file ``path`` that could not be written: its nearest existing folder is not a
    folder, or not one this process may create files in (an OSError naming ``path``)."""
    path = Path(path)
    folder = path.parent
    while not folder.exists() and folder.parent != folder:
        folder = folder.parent
    if not folder.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, f"cannot write it: {folder} is a file, not a folder", str(path))
    try:  # a real file made and removed: os.access cannot tell a read-only mount or quota from a folder's mode
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        raise type(error)(error.errno, f"cannot write it: the folder {folder} is not writable ({error.strerror}); "
                          "choose another place", str(path)) from None


def file_digest(path: str | Path) -> str:
    """The SHA-256 of the file at ``path`` (hex), read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
