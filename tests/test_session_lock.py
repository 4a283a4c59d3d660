"""One writer at a time: concurrent writers of one session file each add their step, none is lost."""

import multiprocessing
import subprocess
import sys

import numpy as np
import pytest

from ivc import session as session_io
from ivc.errors import SessionError
from tests.helpers import make_step, survey_attrs

#: eight different steps, as eight `ivc collect STEP` would record them
STEPS = ["cube_calibration", "cube_survey", "wand_calibration", "wand_sweep", "check", "extension_sweep_1",
         "extension_sweep_2", "extension_sweep_3"]


def _step(name: str, seed: int):
    step = make_step(np.random.default_rng(seed), frames=30, sensors=3 if name == "check" else 8)
    if name == "cube_survey":
        step.attrs = survey_attrs()
    return step


def _writer(path, name, step, barrier):
    barrier.wait()  # all eight start together
    session_io.add_step(path, name, step)


def test_eight_concurrent_writers_keep_all_eight_steps(tmp_path):
    context = multiprocessing.get_context("fork" if sys.platform.startswith("linux") else "spawn")
    steps = {name: _step(name, i) for i, name in enumerate(STEPS)}  # made once, before the workers start
    for trial in range(20):
        path = tmp_path / f"race{trial}.h5"
        barrier = context.Barrier(len(STEPS))
        workers = [context.Process(target=_writer, args=(path, name, steps[name], barrier)) for name in STEPS]
        for worker in workers:
            worker.start()
        for worker in workers:
            worker.join(120)
        assert all(worker.exitcode == 0 for worker in workers), [worker.exitcode for worker in workers]
        assert sorted(session_io.read(path).steps) == sorted(STEPS), f"trial {trial}"


def test_a_waiting_writer_is_told_why_and_gives_up_with_the_holder_named(tmp_path):
    path = tmp_path / "held.h5"
    told = []
    with session_io.writer_lock(path):
        with pytest.raises(SessionError, match=r"ivc process \d+ has been writing this file"):
            with session_io.writer_lock(path, wait_s=0.2, on_wait=told.append):
                pass
    assert len(told) == 1 and "waiting for ivc process" in told[0]
    with session_io.writer_lock(path, wait_s=0.2):  # released: the next writer goes straight in
        pass


@pytest.mark.slow
def test_concurrent_ivc_collect_commands_keep_every_step(tmp_path):
    """The CLI path: eight `ivc collect STEP --source replay:S.h5 -o race.h5` at once (the library test above
    repeats the race 20 times; here it runs once through the command the user types)."""
    source = tmp_path / "source.h5"
    session_io.write(session_io.Session(steps={name: _step(name, i) for i, name in enumerate(STEPS)}), source)
    output = tmp_path / "race.h5"
    commands = []
    for name in STEPS:
        extra = ["--declared-position", "0.5,0.01,-0.02", "--declared-quaternion", "1,0,0,0"] \
            if name == "cube_survey" else []
        commands.append(subprocess.Popen([sys.executable, "-m", "ivc.cli", "collect", name, "--source",
                                          f"replay:{source}", "-o", str(output), *extra],
                                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    outputs = [command.communicate(timeout=300)[0] for command in commands]
    assert all(command.returncode == 0 for command in commands), outputs
    assert sorted(session_io.read(output).steps) == sorted(STEPS)
