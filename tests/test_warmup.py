"""`ivc warmup` and where the compiled kernels are cached."""

import numba
import pytest
from click.testing import CliRunner

import ivc
from ivc.cli import cli
from ivc.errors import InputError
from ivc.warmup import cache_location, warm_up


def test_cache_goes_to_the_user_cache_dir_when_the_package_is_read_only(monkeypatch, tmp_path):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(numba.config, "CACHE_DIR", numba.config.CACHE_DIR)  # restored after the test
    monkeypatch.setattr(ivc._os, "access", lambda path, mode: False)
    ivc._numba_cache_dir()
    assert ivc._os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "ivc" / "numba") == numba.config.CACHE_DIR
    assert cache_location() == tmp_path / "ivc" / "numba"


def test_an_explicit_cache_dir_wins(monkeypatch, tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    monkeypatch.setattr(ivc._os, "access", lambda path, mode: False)
    ivc._numba_cache_dir()
    assert ivc._os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "mine")


def test_warm_up_runs_the_correction_kernels_and_refuses_unknown_groups():
    timings = warm_up(["correct"])
    assert [group for group, _ in timings] == ["correct"] and timings[0][1] >= 0
    with pytest.raises(InputError, match="unknown warm-up group"):
        warm_up(["nope"])


def test_warmup_command():
    result = CliRunner().invoke(cli, ["warmup", "--only", "correct"])
    assert result.exit_code == 0, result.output
    assert "correct: ready in" in result.output
