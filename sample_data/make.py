"""Regenerate the shipped recordings in sample_data/recordings (see sample_data/README.md).

    python sample_data/make.py [--out DIR] [--only head|room]

``room`` runs the demo (:func:`ivc.demo.run`, as ``ivc demo``) on the default scene (seed 0,
about a minute and a half) and keeps its fitted table plus a small slice of its session;
``head`` writes 10 s of synthetic aggressive head motion. Existing files are never replaced: remove them first.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ivc import demo
from ivc import session as session_io
from ivc.collect import write_csv
from ivc.predict.motion import head_motion
from ivc.session import Session, Step

HERE = Path(__file__).resolve().parent / "recordings"
#: frames kept from the demo's steps: the cube survey (for the declared frame) and the check poses
SURVEY_FRAMES, CHECK_FRAMES, CHECK_CSV_FRAMES = 100, 1000, 240
#: the head recording: 10 s at 120 Hz, a sensor on the head 0.45 m in front of the source
HEAD_FRAMES, HEAD_RATE_HZ, HEAD_SEED, HEAD_POSITION = 1200, 120.0, 7, (0.45, 0.0, 0.05)


def _refuse_existing(*paths: Path) -> None:
    existing = [str(p) for p in paths if p.exists()]
    if existing:
        raise SystemExit(f"exists, not replaced: {', '.join(existing)}; remove it first")


def head(out: Path) -> None:
    """``head_aggressive_120hz.csv``: one sensor's synthetic aggressive head motion (docs/math.md §14.2-§14.3)."""
    path = out / "head_aggressive_120hz.csv"
    _refuse_existing(path)
    motion = head_motion("aggressive", HEAD_FRAMES, HEAD_RATE_HZ, seed=HEAD_SEED)
    time = np.arange(HEAD_FRAMES) / HEAD_RATE_HZ
    position = np.broadcast_to(np.asarray(HEAD_POSITION, dtype=float), (HEAD_FRAMES, 1, 3))
    step = Step(time=time, position=position.copy(), quaternion=motion.measured[:, None, :],
                sample_rate_hz=HEAD_RATE_HZ, sensor_ids=["head"])
    with session_io.atomic_path(path) as tmp:
        write_csv(step, tmp)


def room(out: Path) -> None:
    """``default_room_lut.h5``, ``default_room_check.h5`` and ``default_room_check.csv`` from ``ivc demo``."""
    table, check, check_csv = (out / "default_room_lut.h5", out / "default_room_check.h5",
                               out / "default_room_check.csv")
    _refuse_existing(table, check, check_csv)
    with tempfile.TemporaryDirectory(prefix="ivc-samples-") as scratch:
        result = demo.run("default", seed=0, folder=scratch)  # what `ivc demo --seed 0 --keep DIR` writes
        full = result.session
        kept = {"cube_survey": slice(0, SURVEY_FRAMES), "check": slice(0, CHECK_FRAMES)}
        steps = {name: full.steps[name].select(frames) for name, frames in kept.items()}
        truth = {name: session_io.Truth(full.truth[name].position[frames], full.truth[name].quaternion[frames])
                 for name, frames in kept.items()}
        session_io.write(Session(full.hemisphere, steps, truth, full.attrs), check)
        with session_io.atomic_path(check_csv) as tmp:
            write_csv(steps["check"].select(slice(0, CHECK_CSV_FRAMES)), tmp)
        with session_io.atomic_path(table) as tmp:
            shutil.copyfile(result.table_file, tmp)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=HERE, help="output folder (default: sample_data/recordings)")
    parser.add_argument("--only", choices=("head", "room"), help="make one group only")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.only in (None, "head"):
        head(args.out)
    if args.only in (None, "room"):
        room(args.out)


if __name__ == "__main__":
    main()
