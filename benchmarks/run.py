"""Run every benchmark: ``python -m benchmarks.run [NAME ...]``.

Each ``bench_<name>.py`` module has ``run() -> list[Figure]``. Every figure is printed
with the baseline measured in the same run and the ratio between them; the exit code
is 1 if a figure misses its target.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
import sys
from pathlib import Path

# speed figures are of the compiled kernels: no small input runs their interpreted forms while the
# cache is cold (ivc.compiled; bench_startup measures that behaviour in subprocesses of its own)
os.environ.setdefault("IVC_INTERPRETED_MAX", "0")

from benchmarks.harness import HEADER


def main(argv: list[str]) -> int:
    here = Path(__file__).parent
    names = sorted(m.name[len("bench_") :] for m in pkgutil.iter_modules([str(here)]) if m.name.startswith("bench_"))
    chosen = argv or names
    unknown = set(chosen) - set(names)
    if unknown:
        print(f"unknown benchmark(s) {sorted(unknown)}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    print(HEADER)
    failed = False
    for name in chosen:
        module = importlib.import_module(f"benchmarks.bench_{name}")
        for figure in module.run():
            print(figure.line(), flush=True)
            failed |= figure.passed is False
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
