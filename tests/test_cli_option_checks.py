"""Options refused before any work (issue 41, found by tests/test_cli_fuzz.py): each bad value gives one
line naming it, not a traceback after minutes of simulation."""

import pytest
from click.testing import CliRunner

from ivc.cli.main import cli
from ivc.errors import InputError, SceneError
from ivc.sim import Simulator, load_scene


@pytest.mark.parametrize("seed", [-1, 2**63, 99999999999999999999999, 1.5, "3", True])
def test_simulator_refuses_a_seed_it_cannot_use_or_store(seed):
    with pytest.raises(InputError, match="seed"):
        Simulator(load_scene("default"), seed)


@pytest.mark.parametrize("seed", [0, 2**63 - 1])
def test_simulator_keeps_every_storable_seed(seed):
    assert Simulator(load_scene("default"), seed).seed == seed


@pytest.mark.parametrize("seed", ["-1", "99999999999999999999999"])
def test_demo_refuses_a_bad_seed_in_one_line(seed, tmp_path):
    result = CliRunner().invoke(cli, ["demo", "--seed", seed, "--sweep-frames", "10", "--check-frames", "10",
                                      "--keep", str(tmp_path / "kept")])
    assert result.exit_code == 1, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    assert "Error: seed must be" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "kept").exists()


@pytest.mark.parametrize("name", [""])
@pytest.mark.parametrize("fmt", ["csv", "slicer-itk", "itk"])
def test_export_refuses_a_table_path_without_a_file_name(name, fmt):
    """`ivc export '' --format slicer-itk` ended in pathlib's ValueError deriving the default output name."""
    result = CliRunner().invoke(cli, ["export", name, "--format", fmt])
    assert result.exit_code == 2, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    assert "is not a file name" in result.output


def test_a_binary_file_as_the_scene_is_refused_in_one_line(tmp_path):
    """`ivc demo --scene tray.stl` ended in UnicodeDecodeError (found by the CLI fuzz)."""
    mesh = tmp_path / "tray.stl"
    mesh.write_bytes(b"solid\x00\x80\x8b binary mesh")
    with pytest.raises(SceneError, match="not a scene .toml file"):
        load_scene(mesh)
    result = CliRunner().invoke(cli, ["demo", "--scene", str(mesh), "--sweep-frames", "10", "--check-frames", "10"])
    assert result.exit_code == 1, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    assert "Error:" in result.output and "not a scene .toml file" in result.output


def test_a_binary_file_given_as_a_tracker_model_or_a_rig_csv_is_refused_in_one_line(tmp_path):
    from ivc.collect.rig_csv import read_rig_csv
    from ivc.dipole.tracker import load_tracker
    from ivc.errors import CsvError, TrackerError

    binary = tmp_path / "table.h5"
    binary.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(TrackerError, match="a binary file, not a tracker file"):
        load_tracker(binary)
    with pytest.raises(CsvError, match="not a text file, so not a rig CSV"):
        read_rig_csv(binary)
