"""The full default protocol simulated (issue: simulator).

Target: all five steps (100,000-frame sweep with 8 wand sensors, 10,000 check poses)
in <= 60 s on 2 cores with peak memory <= 2 GB, run as a user runs it (`ivc collect
protocol`, in a child process so its peak memory is its own). Baseline: the sweep's
secondary field by direct summation over the triangle dipoles (no tabulation),
timed on 20,000 points and scaled to the sweep's 800,000.
"""

from __future__ import annotations

import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import Figure, best_time
from ivc.sim import Simulator, load_scene


def run() -> list[Figure]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "protocol.h5"
        start = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "ivc.cli", "collect", "protocol", "-o", str(out)],
            check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        elapsed = time.perf_counter() - start
        peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024**2
    simulator = Simulator(load_scene("default"), 0)
    field = simulator.secondary
    points = simulator.scene.cube.center + 0.1 * np.random.default_rng(0).standard_normal((20_000, 3))
    direct = best_time(lambda: field.exact(points), repeat=1) * 800_000 / 20_000
    return [
        Figure("collect protocol (default scene), wall time", elapsed, "s", "direct-sum G of sweep alone", direct,
               "<= 60 s", passed=elapsed <= 60.0, higher_is_better=False),
        Figure("collect protocol, peak memory", peak_gb, "GB", target="<= 2 GB", passed=peak_gb <= 2.0,
               higher_is_better=False),
    ]
