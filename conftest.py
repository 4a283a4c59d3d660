"""Repository-wide pytest set-up: the doctest of docs/python.md runs the whole pipeline, so it is slow.

The suite runs on two processes (pytest-xdist, ``addopts`` in pyproject.toml). On an empty compile cache both
would compile the same numba kernels at the same time; :func:`_compile_once_across_workers` makes the second
process wait for the first one's compilation and load it from numba's on-disk cache instead.
"""

import contextlib
import hashlib
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

import pytest

try:
    import fcntl
except ImportError:  # not on Windows: the workers may then compile a kernel twice, nothing worse
    fcntl = None

# the tests exercise the compiled kernels, whatever the state of the cache: no interpreted stand-ins for small
# inputs (ivc.compiled; tests/test_compiled.py tests those on purpose). Subprocesses inherit it.
os.environ.setdefault("IVC_INTERPRETED_MAX", "0")


#: test modules that run a live loop against sockets with a few seconds' timeouts: kept on one worker, one after
#: the other (on a loaded machine, a sibling test's compilation or interpreted kernels starved them)
LIVE_LOOP_MODULES = {"test_live.py", "test_live_robust.py", "test_live_startup.py", "test_pose_only.py"}


def pytest_configure(config):
    """One folder per run for the simulator's tabulated fields (``IVC_FIELD_CACHE``, ``ivc.sim.field``), made by
    the controlling process before the xdist workers start: the workers and the CLI subprocesses of the tests
    inherit it, so a scene simulated in several modules is tabulated once per run (5-14 CPU seconds each for
    the built-in scenes), not once per module and process. Removed when the run ends; a run never reuses an
    earlier run's tables, so a cold run stays cold."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return
    if _parallel(config):
        # one BLAS thread per worker: the workers already keep the cores busy, and OpenBLAS's own threads,
        # two per worker on the 2-core machine, spun against each other (the 8000-sample sources fit
        # tests/test_fit_sources.py had then: 35 CPU s and 47 s with two, 14 CPU s and 22 s with one, under load).
        # Set before the workers start, so it holds from their first import of numpy.
        config._ivc_set_threads = [name for name in ("OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")
                                   if name not in os.environ]
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        # the same for numba's threads: each worker's parallel kernels ran on two OpenMP threads, four on two cores,
        # and a parallel loop ends when its last thread does, which the other worker had often descheduled
        # (the cold suite back to back: 230 s and 436 CPU s with two, 205 s and 395 CPU s with one). The
        # kernels are the same compiled parallel code, run on one thread; results are within the tests' tolerances
        # either way (docs/kernels.md). Both are removed again when the run ends (pytest_unconfigure): this process's
        # numba, imported before this hook, must not see a thread count other than the one it started with.
        os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    if os.environ.get("IVC_FIELD_CACHE"):
        return
    folder = tempfile.mkdtemp(prefix="ivc-field-cache-")
    os.environ["IVC_FIELD_CACHE"] = folder
    config._ivc_field_cache = folder


def _parallel(config) -> bool:
    """Whether this run spreads its tests over several xdist workers (``-n 2`` in pyproject.toml)."""
    n = getattr(config.option, "numprocesses", None)
    return bool(n) and (not isinstance(n, int) or n > 1) and config.getvalue("dist") != "no"


def pytest_unconfigure(config):
    for name in getattr(config, "_ivc_set_threads", ()):
        os.environ.pop(name, None)
    folder = getattr(config, "_ivc_field_cache", None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop("IVC_FIELD_CACHE", None)


def pytest_collection_modifyitems(config, items):
    for item in items:
        if type(item).__name__ == "DoctestItem":
            item.add_marker(pytest.mark.slow)


def worker_group(nodeid: str) -> str:
    """The worker group of a test: its module, or ``live-loop`` for the modules of :data:`LIVE_LOOP_MODULES`."""
    module = nodeid.split("::", 1)[0]
    return "live-loop" if Path(module).name in LIVE_LOOP_MODULES else module


def pytest_xdist_make_scheduler(config, log):
    """``--dist loadgroup`` (pyproject.toml) by module: a module's tests stay on one worker, one after the other (its
    module-scoped fixtures, e.g. a simulated session or a demo run, are built once), the live-loop modules share one.

    Done here rather than with ``xdist_group`` marks: pytest-xdist 3.8 groups marked tests by renaming their node
    ids (``item._nodeid``), which pytest 9 no longer reads, so the marks grouped nothing and a module's tests were
    spread over both workers, each building the module's fixtures.
    """
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return worker_group(nodeid)

    return ModuleScheduling(config, log)


def _compile_once_across_workers(run_id: str) -> None:
    """Serialise, across the xdist workers of one run, the compilation of each cached numba kernel.

    Numba compiles a ``cache=True`` kernel only after looking for it in its on-disk cache, and writes it there
    when done (atomically). Holding a per-kernel file lock around that compile means a worker that needs a
    kernel the other worker is compiling waits for it, then finds it in the cache (well under a second)
    instead of compiling it again (tens of seconds). The lock is taken inside numba's own (re-entrant,
    per-process) compiler lock, so within a process only one thread ever waits on a file lock; kernels call
    kernels along an acyclic graph, so two workers cannot wait on each other. Results are the same: the
    cache holds what either worker would have compiled.
    """
    from numba.core import caching, dispatcher
    from numba.core.compiler_lock import global_compiler_lock

    log = os.environ.get("IVC_TEST_COMPILE_LOG")  # a file: each compile's worker, CPU seconds and kernel
    folder = Path(tempfile.gettempdir()) / f"ivc-compile-locks-{run_id}"
    folder.mkdir(exist_ok=True)
    held: dict[str, int] = {}  # lock name -> depth (a kernel compiling for one signature inside another's)
    guard = threading.Lock()
    nesting = threading.local()
    compile_ = dispatcher.Dispatcher.compile

    @contextlib.contextmanager
    def locked(name: str):
        with guard:
            depth = held.get(name, 0)
            held[name] = depth + 1
        try:
            if depth:
                yield
                return
            with open(folder / name, "w") as f:
                fcntl.flock(f, fcntl.LOCK_EX)
                try:
                    yield
                finally:
                    fcntl.flock(f, fcntl.LOCK_UN)
        finally:
            with guard:
                held[name] -= 1

    def compile_once(self, sig):
        cache = getattr(self, "_cache", None)
        if cache is None or isinstance(cache, caching.NullCache):
            return compile_(self, sig)
        try:
            index = str(cache._cache_file._index_path)
        except AttributeError:  # another numba's internals: compile as numba would
            return compile_(self, sig)
        with global_compiler_lock, locked(hashlib.sha1(index.encode()).hexdigest()):
            if log is None:
                return compile_(self, sig)
            before, known = time.thread_time(), len(self.overloads)
            nesting.depth = getattr(nesting, "depth", 0) + 1
            try:
                return compile_(self, sig)
            finally:  # a line per compile or cache load: worker, nesting depth (1: called from Python), CPU
                # seconds (those of the kernels it compiled on the way included), kernel
                nesting.depth -= 1
                if len(self.overloads) > known:
                    with open(log, "a") as f:
                        f.write(f"{os.environ.get('PYTEST_XDIST_WORKER', '-')}\t{nesting.depth + 1}\t"
                                f"{time.thread_time() - before:.3f}\t"
                                f"{self.py_func.__module__}.{self.py_func.__qualname__}\n")

    dispatcher.Dispatcher.compile = compile_once


if os.environ.get("PYTEST_XDIST_WORKER") and fcntl is not None and os.environ.get("IVC_TEST_COMPILE_LOCK", "1") != "0":
    _compile_once_across_workers(os.environ.get("PYTEST_XDIST_TESTRUNUID", "run"))
