"""The rehearsal a user runs with no hardware: ``ivc serve sim`` in one terminal, ``ivc collect protocol --source
igtl://`` in another, gives the session ``ivc collect protocol --source sim`` writes for the same scene and seed,
pose for pose (issue 36)."""

import re
import subprocess
import sys
import time

import numpy as np
import pytest

from ivc.session import read

FRAMES = 240  # per step: the rule of each step is then not met, and the step ends on the simulator's next label
DEADLINE_S = 600.0


def _ivc(*args: str) -> list[str]:
    return [sys.executable, "-m", "ivc.cli", *args]


@pytest.mark.slow
@pytest.mark.parametrize("poses_only", [False, True])
def test_ivc_serve_sim_then_ivc_collect_protocol_equals_the_simulator(tmp_path, poses_only):
    server = subprocess.Popen(_ivc("serve", "sim", "--frames", str(FRAMES), "--pause", "0.2", "--speed", "50",
                                   "--port", "0", *(["--poses-only"] if poses_only else [])),
                              stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + DEADLINE_S
        address = None
        while address is None:  # wait for the server's own line, not a clock
            line = server.stderr.readline()
            assert line or server.poll() is None, "ivc serve ended before serving"
            assert time.monotonic() < deadline, "ivc serve did not start serving"
            found = re.search(r"serving sim on ([\d.]+):(\d+)", line)
            address = found and f"{found[1]}:{found[2]}"
        collected = subprocess.run(_ivc("collect", "protocol", "--source", f"igtl://{address}", "-o",
                                        str(tmp_path / "via_igtl.h5"), "--declared-position", "0.5,0,0",
                                        "--declared-quaternion", "1,0,0,0"),
                                   capture_output=True, text=True, timeout=DEADLINE_S)
        assert collected.returncode == 0, collected.stdout + collected.stderr
    finally:
        server.terminate()
        server.wait(60)
    simulated = subprocess.run(_ivc("collect", "protocol", "--source", "sim", "-o", str(tmp_path / "via_sim.h5"),
                                    "--frames", str(FRAMES), "--sweep-frames", str(FRAMES), "--check-frames",
                                    str(FRAMES), "--seed", "0"), capture_output=True, text=True, timeout=DEADLINE_S)
    assert simulated.returncode == 0, simulated.stdout + simulated.stderr
    want, got = read(tmp_path / "via_sim.h5"), read(tmp_path / "via_igtl.h5")
    assert sorted(got.steps) == sorted(want.steps)
    for name, step in want.steps.items():
        other = got.steps[name]
        assert other.n_frames == step.n_frames == FRAMES, name
        assert np.array_equal(other.valid_mask, step.valid_mask), name
        position, quaternion = step.poses(want.hemisphere)
        other_position, other_quaternion = other.poses(got.hemisphere)
        valid = step.valid_mask
        assert np.max(np.abs(other_position - position)[valid]) < 1e-6, name  # metres
        assert np.min(np.abs(np.sum(other_quaternion * quaternion, axis=-1))[valid]) > 1 - 1e-12, name
        assert np.allclose(other.time, step.time - step.time[0], atol=1e-6), name
        assert (other.signal is None) == poses_only, name
