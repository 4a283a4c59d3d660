"""Compiled kernels when they are ready, the same kernels interpreted when compiling would cost more.

Every numba kernel of ivc is compiled on its first call and cached on disk (``cache=True``):
the first run after an install pays seconds to minutes of compilation, later runs load the
kernels in well under a second. For a handful of samples (a 10-row CSV, a live stream's first
frames) compiling costs far more than it saves, so a wrapper asks :func:`choose` for its
kernel: the compiled dispatcher when it is compiled in this process or found in the on-disk
cache, or when the input is large; otherwise :func:`interpreted`, the kernel's own Python
source run by the interpreter, with every compiled function it calls replaced by its
interpreted form too. Same code, same arithmetic (IEEE double, no fast-math), so the results
agree with the compiled kernel to rounding (tested to 1e-12); about a thousand times slower
per sample, which is why it is kept to small inputs.

:data:`used` names the kernels that ran interpreted in this process (the CLI says so, and
points at ``ivc warmup``).
"""

from __future__ import annotations

import os
import threading
import types
from collections.abc import Callable
from contextlib import contextmanager

import numpy as np
from numba.core.registry import CPUDispatcher

#: inputs up to this many samples run interpreted while their kernel is not compiled or cached
#: (``IVC_INTERPRETED_MAX`` overrides; 0 always compiles, as the test suite does)
SMALL = int(os.environ.get("IVC_INTERPRETED_MAX", "64"))
#: the same for kernels with a vectorised NumPy form (a few times slower than compiled, not a thousand)
VECTORISED = 200_000

#: kernels (module.name) that ran interpreted in this process
used: set[str] = set()

_interpreted: dict[CPUDispatcher, Callable] = {}
_lock = threading.Lock()
_local = threading.local()


@contextmanager
def compiling():
    """Within this block (on this thread), :func:`choose` always returns the compiled kernel: what
    ``ivc warmup`` and a background compilation use to build the cache with tiny inputs."""
    before = getattr(_local, "forced", False)
    _local.forced = True
    try:
        yield
    finally:
        _local.forced = before


def name_of(kernel: CPUDispatcher) -> str:
    """``module.function`` of a compiled kernel."""
    return f"{kernel.py_func.__module__}.{kernel.py_func.__name__}"


#: the ids of the kernels found ready (dispatchers live as long as their module: an id is not reused)
_ready: set[int] = set()


def is_ready(kernel: CPUDispatcher) -> bool:
    """Whether calling ``kernel`` needs no compilation: compiled in this process, or an entry for this
    machine in numba's on-disk cache (fresh for the current source). True when numba's cache layout
    is not the one this reads (then the kernel simply compiles, as it would anyway). Once ready, a kernel
    stays ready for the process, and is remembered: asking numba costs tens of microseconds a call, which a
    live frame's few samples notice."""
    if id(kernel) in _ready:
        return True
    ready = bool(kernel.signatures)
    if not ready:
        cache = getattr(kernel, "_cache", None)
        try:
            index = cache._cache_file._load_index()
            magic = kernel.targetctx.codegen().magic_tuple()
            ready = any(key[1] == magic for key in index)
        except Exception:  # noqa: BLE001 - another numba version's internals: behave as without this module
            ready = True
    if ready:
        _ready.add(id(kernel))
    return ready


def _code_names(code: types.CodeType) -> set[str]:
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _code_names(const)
    return names


def interpreted(kernel: CPUDispatcher) -> Callable:
    """The kernel's Python function, calling the interpreted forms of the compiled functions it uses
    (so that nothing it calls compiles, or waits for another thread's compilation)."""
    with _lock:
        return _build(kernel)


def _build(kernel: CPUDispatcher) -> Callable:
    if kernel in _interpreted:
        return _interpreted[kernel]
    source = kernel.py_func
    scope = dict(source.__globals__)
    closure = source.__closure__
    if closure:  # a kernel made by a factory (ivc.pose.kernels.lm_driver) calls the kernels it closes over
        closure = tuple(types.CellType(_build(cell.cell_contents)) if isinstance(cell.cell_contents, CPUDispatcher)
                        else cell for cell in closure)
    function = types.FunctionType(source.__code__, scope, source.__name__, source.__defaults__, closure)
    _interpreted[kernel] = function
    for name in _code_names(source.__code__):
        value = scope.get(name)
        if isinstance(value, CPUDispatcher):
            scope[name] = _build(value)
    return function


def choose(kernel: CPUDispatcher, samples: int, small: int | None = None, fallback: Callable | None = None
           ) -> Callable:
    """``kernel`` itself, or, for at most ``small`` (default :data:`SMALL`) samples while it is not ready,
    ``fallback`` (a NumPy form with the kernel's arguments) or else its interpreted form."""
    limit = SMALL if small is None else small
    if SMALL <= 0 or samples > limit or getattr(_local, "forced", False) or is_ready(kernel):
        return kernel
    used.add(name_of(kernel))
    function = interpreted(kernel) if fallback is None else fallback

    def quiet(*args):
        with np.errstate(all="ignore"):  # NumPy scalars warn where compiled code silently gives inf/NaN
            return function(*args)

    return quiet
