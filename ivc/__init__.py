"""ivc: interpolation-volume calibration for AC electromagnetic trackers.

Metal near an AC electromagnetic tracker bends every pose it reports. ivc maps the
secondary field of that metal with two cheap fixtures (an 8-sensor interpolation cube
and a mapping wand) and corrects measurements with the map. The whole job in Python,
on a simulated room::

    import ivc

    session = ivc.Simulator(ivc.load_scene("default"), seed=0).protocol({"wand_sweep": 20_000})
    table = ivc.fit_lut(session, ivc.FitOptions(fitter="harmonic"))
    check = session.steps["check"]
    corrected = ivc.Corrector(table).batch(check.signal_matrices(), check.valid_mask)
    report = ivc.evaluate(table, session)                 # errors against truth, mm and mrad
    print(report["ivc"]["position_mm"]["p50"], report["dipole"]["position_mm"]["p50"])
    ivc.write_lut(table, "room_lut.h5")
    ivc.export_table(table, "vti", "room.vti")            # ParaView; also slicer, vrui, csv, npz, hdf5
    ahead = ivc.predict.make("mmdq2", rate_hz=240.0).predict(corrected.quaternion, 0.05)

A real tracker's recording enters as a session file (:func:`read_session`) or a
recording CSV (:func:`ivc.collect.replay`). Docs: docs/python.md walks through the same
job; docs/conventions.md gives units (metres, seconds, quaternions ``[w, x, y, z]``).

The package is laid out as the pipeline it implements, each stage importing only those above it in
this list (docs/architecture.md; tests/test_layout.py checks it):

``rotations``  quaternion and rotation-matrix conventions (with ``linalg``, ``errors``, ``compiled``, ``units``)
``files``      atomic writes and file digests
``dipole``     the AC dipole field model, the closed-form pose solver, the tracker's own coil model
``session``    the HDF5 session file every command reads and writes
``pose``       the batched pose solver with a known secondary field; the tracker's own solvers and calibration
``fixtures``   cube and wand calibration, the sweep solved through the cube, the measurement model
``truth``      evaluation against truth: percentiles, pose errors, the declared-frame map
``collect``    recording protocol steps from the simulator or a tracker's recording
``sim``        a simulated tracker in a distorted room
``table``      the look-up table itself: grid, interpolation, file, fit report
``correct``    corrected poses from signals or reported poses (pose-only trackers); evaluation against truth
``lut``        fitting the secondary-field look-up table
``predict``    head-motion prediction filters
``live``       live correction of OpenIGTLink streams
``export``     the table for firmware, ParaView, 3D Slicer and Vrui
``report``     figures and an HTML page on a table
``demo``       the whole pipeline on a simulated room in one call
``warmup``     the compiled kernels built ahead of their first use (``ivc warmup``)
``compiled``   compiled kernels, or their NumPy / interpreted forms for small inputs on a cold cache
``app``        each command as a call: :func:`correct_file`, :func:`predict_file` with their options
``cli``        the ``ivc`` command line

The names below are loaded on first use, so ``import ivc`` stays cheap.
"""

from __future__ import annotations

import importlib as _importlib
import os as _os
import sys as _sys
from importlib.metadata import PackageNotFoundError as _PackageNotFoundError
from importlib.metadata import version as _version
from pathlib import Path as _Path

from ivc.errors import (
    CsvError,
    ExportError,
    InputError,
    IvcError,
    LiveError,
    LutError,
    OptionsError,
    PredictorError,
    SceneError,
    SessionError,
    TrackerError,
)


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
    __version__ = _version("ivc")
except _PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"

#: public name -> (module, attribute); attribute None is the module itself
_EXPORTS = {
    # data
    "Session": ("ivc.session", "Session"),
    "Step": ("ivc.session", "Step"),
    "Truth": ("ivc.session", "Truth"),
    "read_session": ("ivc.session", "read"),
    "write_session": ("ivc.session", "write"),
    "replay": ("ivc.collect", "replay"),
    # simulation
    "Simulator": ("ivc.sim", "Simulator"),
    "SimulatedTracker": ("ivc.sim", "SimulatedTracker"),
    "Scene": ("ivc.sim", "Scene"),
    "load_scene": ("ivc.sim", "load_scene"),
    # fixtures and the table
    "FixtureModel": ("ivc.fixtures.mapping", "FixtureModel"),
    "fit_lut": ("ivc.lut", "fit_lut"),
    "FitOptions": ("ivc.lut", "FitOptions"),
    "HarmonicFit": ("ivc.lut", "HarmonicFit"),
    "PolyFit": ("ivc.lut", "PolyFit"),
    "LookupTable": ("ivc.lut", "LookupTable"),
    "read_lut": ("ivc.lut", "read"),
    "write_lut": ("ivc.lut", "write"),
    # correction and evaluation
    "Corrector": ("ivc.correct", "Corrector"),
    "PoseCorrector": ("ivc.correct", "PoseCorrector"),
    "Correction": ("ivc.correct", "Correction"),
    "evaluate": ("ivc.correct.evaluate", "evaluate"),
    "agree_with_body": ("ivc.correct.rigid", "agree_with_body"),
    "decide_with_body": ("ivc.correct.rigid", "decide_with_body"),
    "WandCalibration": ("ivc.fixtures.wand", "WandCalibration"),
    # the app layer: a command as a call (ivc correct, ivc predict)
    "correct_file": ("ivc.app.correct", "correct_file"),
    "CorrectOptions": ("ivc.app.correct", "CorrectOptions"),
    "CorrectResult": ("ivc.app.correct", "CorrectResult"),
    "live_corrector": ("ivc.app.correct", "live_corrector"),
    "LiveOptions": ("ivc.app.correct", "LiveOptions"),
    "predict_file": ("ivc.app.predict", "predict_file"),
    "PredictOptions": ("ivc.app.predict", "PredictOptions"),
    "PredictResult": ("ivc.app.predict", "PredictResult"),
    # export
    "export_table": ("ivc.export", "export"),
    # the tracker's own coil model (docs/tracker.md)
    "Tracker": ("ivc.dipole", "Tracker"),
    "load_tracker": ("ivc.dipole", "load_tracker"),
    "save_tracker": ("ivc.dipole", "save_tracker"),
    "calibrate_tracker": ("ivc.pose.calibrate", "calibrate"),
    # subpackages a script uses by name
    "collect": ("ivc.collect", None),
    "correct": ("ivc.correct", None),
    "export": ("ivc.export", None),
    "demo": ("ivc.demo", None),
    "dipole": ("ivc.dipole", None),
    "fixtures": ("ivc.fixtures", None),
    "live": ("ivc.live", None),
    "lut": ("ivc.lut", None),
    "pose": ("ivc.pose", None),
    "predict": ("ivc.predict", None),
    "report": ("ivc.report", None),
    "rotations": ("ivc.rotations", None),
    "session": ("ivc.session", None),
    "sim": ("ivc.sim", None),
    "truth": ("ivc.truth", None),
    "warmup": ("ivc.warmup", None),
}

__all__ = ["CsvError", "ExportError", "InputError", "IvcError", "LiveError", "LutError", "OptionsError",
           "PredictorError", "SceneError", "SessionError", "TrackerError", "__version__", *_EXPORTS]


def __getattr__(name: str):
    try:
        module, attribute = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module 'ivc' has no attribute {name!r}") from None
    value = _importlib.import_module(module)
    if attribute is not None:
        value = getattr(value, attribute)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(__all__) | {"errors"})  # the public names, not this module's own imports
