"""Start-up (issue 25): the first commands after an install, with an empty compile cache.

Each figure runs ``python -m ivc.cli`` in a subprocess with ``NUMBA_CACHE_DIR`` pointing at a
new, empty directory (what a fresh install has: every kernel compiles on first use), and the
baseline is the same command run again on the cache that first run filled.

Targets: the first ``ivc correct`` of a 10-row pose CSV <= 15 s; the first ``ivc correct --live``
connected to its tracking server <= 5 s after start; ``ivc warmup``'s compile no slower than the tree
before (issue 35): the CPU seconds numba spends compiling the kernel modules both trees have, in
``ivc.warmup.warm_up()`` on an empty cache, against the tree ``IVC_BENCH_BASELINE`` names (a git revision;
default :data:`BASELINE`, the tree issue 35 was filed on), the two trees alternating twice, the smaller of each
tree's two runs compared, within :data:`SPREAD` (a run of the same tree moves by 10-20 % on the shared 2-core
machine). Printed beside them: ``ivc warmup`` on an empty cache, and ``--live`` after it. The cold test suite
(target <= 240 s) takes minutes and runs only with ``IVC_BENCH_SUITE=1`` (the README's ``python -m pytest``,
its baseline the same run again on the cache the first one filled).
"""

from __future__ import annotations

import csv
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.harness import Figure

ROOT = Path(__file__).resolve().parents[1]
LUT = ROOT / "sample_data" / "recordings" / "default_room_lut.h5"
#: the tree the warm-up's compile is compared with (issue 35 was filed on it); ``IVC_BENCH_BASELINE`` overrides
BASELINE = "854092d"
#: how much slower the compile may read and still count as no slower: the machine's run-to-run spread
SPREAD = 1.05
#: run in a tree's own interpreter: warm_up() on an empty cache, printing numba's compile CPU seconds per kernel
#: module as JSON (each compile's own time, without the compiles it triggers)
_COMPILE_EVENTS = """
import collections, json, time
from numba.core import event
stack, seconds = [], collections.Counter()
class Listener(event.Listener):
    def on_start(self, ev):
        stack.append([ev.data["dispatcher"].py_func.__module__, time.thread_time(), 0.0])
    def on_end(self, ev):
        module, start, inner = stack.pop()
        spent = time.thread_time() - start
        seconds[module] += spent - inner
        if stack:
            stack[-1][2] += spent
listening = event.install_listener("numba:compile", Listener())  # kept: collected, it stops listening
listening.__enter__()
from ivc.warmup import warm_up
warm_up()
print(json.dumps(seconds))
"""
CHECK = ROOT / "sample_data" / "recordings" / "default_room_check.csv"


def _env(cache: Path) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))
    env.pop("IVC_INTERPRETED_MAX", None)  # a first run as a user has it (benchmarks/run.py sets 0)
    return env


def _poses(folder: Path) -> Path:
    """The first 10 rows of the sample check recording, poses only."""
    path = folder / "poses10.csv"
    with open(CHECK, newline="") as source, open(path, "w", newline="") as out:
        rows = csv.DictReader(source)
        fields = ["time", "sensor", "x", "y", "z", "qw", "qx", "qy", "qz", "valid"]
        writer = csv.DictWriter(out, fields)
        writer.writeheader()
        for n, row in enumerate(rows):
            if n == 10:
                break
            writer.writerow({k: row[k] for k in fields})
    return path


def _correct(cache: Path, poses: Path, out: Path) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "ivc.cli", "correct", str(LUT), str(poses), "-o", str(out), "--force"],
                   env=_env(cache), check=True, capture_output=True)
    return time.perf_counter() - start


def _live_connected(cache: Path, timeout: float = 600.0) -> float:
    """Seconds from starting ``ivc correct --live`` until it connects to a (silent) tracking server."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(timeout)
    port = server.getsockname()[1]
    start = time.perf_counter()
    process = subprocess.Popen([sys.executable, "-m", "ivc.cli", "correct", str(LUT), "--live",
                                f"igtl://127.0.0.1:{port}", "--publish", "127.0.0.1:0", "--duration", "2"],
                               env=_env(cache), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        connection, _ = server.accept()
        elapsed = time.perf_counter() - start
        connection.close()
    finally:
        server.close()
        try:
            process.wait(timeout=300)  # on an empty cache it compiles in the background, then exits
        except subprocess.TimeoutExpired:
            process.kill()
    return elapsed


def _warmup(cache: Path) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "ivc.cli", "warmup"], env=_env(cache), check=True, capture_output=True)
    return time.perf_counter() - start


def _compile_seconds(tree: Path, cache: Path) -> dict[str, float]:
    """CPU seconds numba spends compiling each kernel module of ``tree`` in ``warm_up()`` on the empty ``cache``."""
    env = dict(_env(cache), PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", _COMPILE_EVENTS], cwd=tree, env=env, check=True,
                          capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _baseline_tree(revision: str, folder: Path) -> Path | None:
    """The tree at ``revision`` (``git archive``) in ``folder``; None where this checkout has no such revision."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision], capture_output=True, check=False)
    if archive.returncode != 0:
        return None
    folder.mkdir()
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)
    return folder


def _compile_figure(folder: Path) -> Figure | None:
    """The warm-up's compile against the baseline tree's, on the kernel modules both compile (:data:`SPREAD`)."""
    revision = os.environ.get("IVC_BENCH_BASELINE", BASELINE)
    before = _baseline_tree(revision, folder / "baseline")
    if before is None:
        print(f"warm-up compile against {revision}: not run (this checkout has no such revision)")
        return None
    runs = {"before": [], "now": []}
    for n, (name, tree) in enumerate([("before", before), ("now", ROOT), ("now", ROOT), ("before", before)]):
        runs[name].append(_compile_seconds(tree, folder / f"cache-compile-{n}"))
    shared = set.intersection(*(set(run) for run in runs["before"] + runs["now"]))
    before_s, now_s = (min(sum(run[m] for m in shared) for run in runs[name]) for name in ("before", "now"))
    return Figure(f"warm-up compile, modules both have, vs {revision}", now_s, "CPU s", revision, before_s,
                  f"<= {SPREAD:g}x {revision}", passed=0 < now_s <= SPREAD * before_s, higher_is_better=False)


def _suite(cache: Path) -> tuple[float, bool]:
    """The README's test command (``python -m pytest``: tests/ and the doctest, two workers) on ``cache``: its wall
    time (s) and whether every test passed."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pytest"], cwd=ROOT,
                          env=_env(cache), check=False, capture_output=True)
    return time.perf_counter() - start, done.returncode == 0


def run() -> list[Figure]:
    figures = []
    with tempfile.TemporaryDirectory(prefix="ivc-bench-startup-") as scratch:
        folder = Path(scratch)
        poses = _poses(folder)
        first = _correct(folder / "cache-correct", poses, folder / "out.csv")
        second = _correct(folder / "cache-correct", poses, folder / "out.csv")
        figures.append(Figure("first ivc correct, 10-row CSV, empty cache", first, "s", "second run", second,
                              "<= 15 s", passed=first <= 15, higher_is_better=False))
        live_cold = _live_connected(folder / "cache-live")
        live_warm = _live_connected(folder / "cache-live")
        figures.append(Figure("first ivc correct --live, connected after", live_cold, "s", "second run", live_warm,
                              "<= 5 s", passed=live_cold <= 5, higher_is_better=False))
        warmup = _warmup(folder / "cache-warmup")
        live_after = _live_connected(folder / "cache-warmup")
        figures.append(Figure("ivc warmup, empty cache", warmup, "s", "--live after it, connected", live_after,
                              "(reference)", higher_is_better=False))
        compile_figure = _compile_figure(folder)
        if compile_figure is not None:
            figures.append(compile_figure)
        if os.environ.get("IVC_BENCH_SUITE") == "1":
            cold, cold_passed = _suite(folder / "cache-suite")
            warm, warm_passed = _suite(folder / "cache-suite")  # again, on the cache the first run filled
            passed = cold <= 240 and cold_passed and warm_passed
            figures.append(Figure("test suite (README's command), empty cache", cold, "s", "the same, cache filled",
                                  warm, "<= 240 s, all passing", passed=passed, higher_is_better=False))
        else:
            print("test suite on an empty cache: not run (set IVC_BENCH_SUITE=1; several minutes)")
    return figures
