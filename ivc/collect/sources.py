"""Opening a live source from its command-line spelling: ``igtl://HOST:PORT``, ``polhemus:DEVICE``, ``replay:FILE``.

Each kind lives in its own module and class, imported only when asked for, and is built by its
``from_spec(argument, *, sensors, hemisphere)`` class method (``argument`` is what follows the prefix, e.g.
``HOST:PORT`` or ``/dev/ttyUSB0``). The registry is the one place that knows the prefixes.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence

from ivc.collect.stream import LiveSource
from ivc.errors import LiveError

#: prefix -> (module, class) of each live source kind
LIVE_SOURCES = {
    "igtl://": ("ivc.collect.igtl", "IgtlSource"),
    "polhemus:": ("ivc.collect.polhemus_serial", "PolhemusSource"),
    "replay:": ("ivc.collect.stream", "SessionSource"),
}


def is_live_spec(spec: str) -> bool:
    """True when ``spec`` names a live source kind (``igtl://``, ``polhemus:``), as against ``sim`` or a file."""
    return spec.startswith(("igtl://", "polhemus:"))


def open_live_source(spec: str, *, sensors: Sequence[str] | None = None, hemisphere: str = "+x") -> LiveSource:
    """The (not yet opened) live source that ``spec`` names; raises LiveError naming the kinds otherwise."""
    for prefix, (module, name) in LIVE_SOURCES.items():
        if spec.startswith(prefix):
            argument = spec[len(prefix):]
            if not argument:
                raise LiveError(f"source {spec!r} names no {prefix.rstrip(':/')} address")
            cls = getattr(importlib.import_module(module), name)
            return cls.from_spec(argument, sensors=sensors, hemisphere=hemisphere)
    raise LiveError(f"source {spec!r}: use igtl://HOST:PORT (an OpenIGTLink server such as PLUS, 3D Slicer or "
                    "`ivc serve`), polhemus:DEVICE (a Polhemus serial port) or replay:FILE (a session file)")
