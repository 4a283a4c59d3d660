"""Shared pieces of the benchmarks: timing, and one line per figure with its baseline."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass


def best_time(fn: Callable[[], object], repeat: int = 5) -> float:
    """Best wall time in seconds of ``repeat`` calls (after one warm-up call)."""
    fn()
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


@dataclass
class Figure:
    """A measured figure, its baseline measured in the same run, and its target."""

    name: str
    value: float
    unit: str
    baseline_name: str = ""
    baseline_value: float = float("nan")
    target: str = ""
    passed: bool | None = None
    higher_is_better: bool = True

    @property
    def ratio(self) -> float:
        if self.baseline_value != self.baseline_value or self.baseline_value == 0:
            return float("nan")
        r = self.value / self.baseline_value
        if self.higher_is_better:
            return r
        return 1.0 / r if r != 0 else float("inf")

    def line(self) -> str:
        status = {True: "PASS", False: "FAIL", None: ""}[self.passed]
        baseline = f"{self.baseline_name} {self.baseline_value:.4g}" if self.baseline_name else "-"
        ratio = f"{self.ratio:.2f}x" if self.ratio == self.ratio else "-"
        return (f"{self.name:<44} {self.value:>12.4g} {self.unit:<10} {baseline:<34} {ratio:>8}  "
                f"{self.target:<24} {status}")


HEADER = f"{'figure':<44} {'value':>12} {'unit':<10} {'baseline (same run)':<34} {'ratio':>8}  {'target':<24} status"
