"""Every error ivc raises on purpose, under one root.

``IvcError`` means "the input or the request is wrong, and the message says how": the
command line prints it as one line. Anything else that escapes the library is a bug
and keeps its traceback. Each class also derives from ``ValueError`` so that code
written against earlier versions (``except ValueError``) still catches it.

    IvcError
    ├── InputError        bad arguments to a library function: shape, range, NaN, units
    │   └── OptionsError  options of an app function (ivc.correct_file, ...) that do not go together or fit the input
    ├── SessionError      a session file, or data about to be written to one, breaks the format
    │   └── CsvError      a recording CSV is malformed
    ├── LutError          a look-up table file is missing, malformed or unusable
    │   └── ExportError   the table cannot be written in the asked format
    ├── SceneError        a simulator scene file is malformed
    ├── PredictorError    bad input to a head-motion predictor
    ├── LiveError         a live stream cannot be set up
    ├── TrackerError      a tracker model file is malformed, or a tracker calibration cannot run
    └── FixtureError      a fixture geometry file is malformed, or a printable fixture does not fit
"""

from __future__ import annotations

__all__ = ["IvcError", "InputError", "OptionsError", "SessionError", "CsvError", "LutError", "ExportError",
           "SceneError", "PredictorError", "LiveError", "TrackerError", "FixtureError"]


class IvcError(Exception):
    """Root of every error ivc raises on purpose; the message says what is wrong and what to do."""


class InputError(IvcError, ValueError):
    """Bad arguments to a library function: wrong shape, out of range, NaN, wrong unit."""


class OptionsError(InputError):
    """Options of an app function (:func:`ivc.correct_file`, :func:`ivc.predict_file`) that do not go together, or
    that do not fit the input; the message names the keyword arguments (the command line, its flags)."""


class SessionError(IvcError, ValueError):
    """A session file, or data about to be written to one, breaks the format."""


class CsvError(SessionError):
    """A recording CSV is malformed; the message lists the bad lines."""


class LutError(IvcError, ValueError):
    """A look-up table file is missing, malformed, or unusable for what was asked."""


class ExportError(LutError):
    """The table cannot be written in the asked format (or to the asked place)."""


class SceneError(IvcError, ValueError):
    """A scene file is malformed; the message names the entry."""


class PredictorError(IvcError, ValueError):
    """Bad input to a predictor: wrong shape, non-unit quaternions, bad horizon."""


class LiveError(IvcError, ValueError):
    """A live stream cannot be set up: bad address, unreachable server, bad message layout."""


class TrackerError(IvcError, ValueError):
    """A tracker model file is malformed, or a tracker calibration cannot run on the data given."""


class FixtureError(IvcError, ValueError):
    """A fixture geometry file is malformed, or a printable fixture does not fit (the message gives the numbers)."""
