"""ivc: interpolation-volume calibration for AC electromagnetic trackers.

The package is laid out as the pipeline it implements:

``rotations``  quaternion and rotation-matrix conventions (MATH.md section 1)
``dipole``     the AC dipole field model and the closed-form pose solver
``session``    the HDF5 session file every command reads and writes
``cli``        the ``ivc`` command line
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ivc")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
