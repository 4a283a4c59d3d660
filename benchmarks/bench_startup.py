"""Start-up (issue 25): the first commands after an install, with an empty compile cache.

Each figure runs ``python -m ivc.cli`` in a subprocess with ``NUMBA_CACHE_DIR`` pointing at a
new, empty directory (what a fresh install has: every kernel compiles on first use), and the
baseline is the same command run again on the cache that first run filled.

Targets: the first ``ivc correct`` of a 10-row pose CSV <= 15 s; the first ``ivc correct --live``
connected to its tracking server <= 5 s after start. Printed beside them: ``ivc warmup`` on an
empty cache, and ``--live`` after it. The cold test suite (target <= 240 s) takes minutes and
runs only with ``IVC_BENCH_SUITE=1`` (the README's ``python -m pytest``, its baseline the same run again on the
cache the first one filled).
"""

from __future__ import annotations

import csv
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
        if os.environ.get("IVC_BENCH_SUITE") == "1":
            cold, cold_passed = _suite(folder / "cache-suite")
            warm, warm_passed = _suite(folder / "cache-suite")  # again, on the cache the first run filled
            passed = cold <= 240 and cold_passed and warm_passed
            figures.append(Figure("test suite (README's command), empty cache", cold, "s", "the same, cache filled",
                                  warm, "<= 240 s, all passing", passed=passed, higher_is_better=False))
        else:
            print("test suite on an empty cache: not run (set IVC_BENCH_SUITE=1; several minutes)")
    return figures
