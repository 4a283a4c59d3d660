"""ivc: interpolation-volume calibration for AC electromagnetic trackers.

The package is laid out as the pipeline it implements:

``rotations``  quaternion and rotation-matrix conventions (MATH.md section 1)
``dipole``     the AC dipole field model and the closed-form pose solver
``session``    the HDF5 session file every command reads and writes
``cli``        the ``ivc`` command line
"""

import os as _os
import sys as _sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path as _Path


def _numba_cache_dir() -> None:
    """Compiled kernels are cached beside the sources; when the installed package directory is
    read-only (a system or shared site-packages), under the user's cache directory instead:
    ``$XDG_CACHE_HOME/ivc/numba`` (default ``~/.cache/ivc/numba``; ``%LOCALAPPDATA%`` on Windows).
    An explicit ``NUMBA_CACHE_DIR`` always wins. Set before numba is imported (or on its
    config, when it already is) so that every kernel's cache uses it."""
    if _os.environ.get("NUMBA_CACHE_DIR") or _os.access(_Path(__file__).parent, _os.W_OK):
        return
    base = _os.environ.get("XDG_CACHE_HOME") or _os.environ.get("LOCALAPPDATA") or _Path.home() / ".cache"
    location = str(_Path(base) / "ivc" / "numba")
    _os.environ["NUMBA_CACHE_DIR"] = location
    if "numba" in _sys.modules:
        _sys.modules["numba"].config.CACHE_DIR = location


_numba_cache_dir()

try:
    __version__ = version("ivc")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
