"""How an app function reports while it works: a callback ``report(kind, text)`` that the caller chooses.

The app functions (:func:`ivc.correct_file`, :func:`ivc.predict_file`) print nothing: what ``ivc correct``
prints line by line, they pass to ``report`` as it happens. ``kind`` is :data:`INFO` (a result: a step's
summary, a stream's timing, a tuning), :data:`WARNING` (what to check: most samples flagged, a renamed column,
an irregular sample rate) or :data:`NOTE` (how it ran). Texts name the functions' keyword arguments
(``overwrite=True``); the command line says its flags instead (``ivc.cli.flags``).
"""

from __future__ import annotations

from collections.abc import Callable

#: ``report(kind, text)``: one message of an app function
Report = Callable[[str, str], None]

INFO, WARNING, NOTE = "info", "warning", "note"


def silent(kind: str, text: str) -> None:
    """The report of a caller that passed none: every message dropped (the result holds what matters)."""
