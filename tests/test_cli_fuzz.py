"""Property-based test of the command line itself (issue 41): for every command click knows, drawn option values
and small corrupted inputs give a result or a one-line error, never a traceback, never a hang past the bound, and
never a changed input (every pool file is checksummed before and after each invocation; an existing output file
is unchanged unless ``--force`` was given).

The commands and options are discovered from click (tests/cli_fuzz.py), so a new command or option is fuzzed
without editing this file.

Cost: the commands that do real work on valid input (demo, fit, collect with the simulator, report, fixtures
report, tracker calibrate) are kept cheap in two ways: the options that scale the work (frames, sweep and check
frames, evaluations, degree...; ``cli_fuzz.COST_CAPS``) are always given, drawn at most a few hundred frames, and
every invocation of those commands carries one value from ``cli_fuzz.POISON`` (-1, nan, empty, 1e309, text, a
missing file) on a drawn parameter, so combinations that would legitimately run for minutes (a demo or a
simulated collection tabulates the room's field first: a minute and more on a loaded machine) are not drawn.
What those commands do with a value they accept is checked by their own tests.
Invocations that may open a socket (``--live``, ``--publish``, ``igtl://`` sources, ``ivc serve``) aim only at
127.0.0.1 ports nothing listens on and run in a subprocess killed at the bound.

Counts: ``IVC_CLI_FUZZ_EXAMPLES`` invocations per command (default 12, the whole file in about a minute warm);
the issue's target is 1,000::

    IVC_CLI_FUZZ_EXAMPLES=1000 IVC_CLI_FUZZ_LOG=/tmp/cli-fuzz.jsonl python -m pytest tests/test_cli_fuzz.py -n 0 -q

``IVC_CLI_FUZZ_LOG`` appends one JSON line per invocation (command, argv, seconds, verdict);
``IVC_CLI_FUZZ_SURVEY=1`` logs findings instead of failing on the first (to list them all in one run);
``IVC_CLI_FUZZ_BOUND`` is the hang bound in seconds (30).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, assume, given, settings
from hypothesis import strategies as st

from ivc.export import REPORTED_GRID_FORMATS
from tests import cli_fuzz

EXAMPLES = int(os.environ.get("IVC_CLI_FUZZ_EXAMPLES", 12))
LOG = os.environ.get("IVC_CLI_FUZZ_LOG")
SURVEY = bool(os.environ.get("IVC_CLI_FUZZ_SURVEY"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=not os.environ.get("IVC_CLI_FUZZ_RANDOM"),
                database=None, phases=[Phase.explicit, Phase.generate],
                suppress_health_check=list(HealthCheck))

#: the commands that do real work on valid input: every invocation of them carries at least one edge value
WORK = {"demo", "fit", "collect", "report", "fixtures report", "tracker calibrate"}

#: KNOWN findings in files this test's author does not own (issue 41), keyed by command, each with a short reason;
#: ``skip`` matches an argv that would hang (not drawn), ``line`` a verdict text that is tolerated. The lead
#: removes an entry when its bug is fixed (see the report of branch h41-fuzz).
KNOWN: list[dict] = []  # none: the findings of the first runs (binary tracker and rig files) are fixed

#: combinations that legitimately run for longer than the bound (not drawn; see the module docstring):
#: the reported-region grid formats at their default spacing (the table's / 8) invert the correction at about
#: a million nodes, 14 CPU seconds for the sample table (over a minute on a loaded machine)
COSTLY: list[dict] = [
    # a server started with a valid simulated source serves until it is stopped: that is its job, not a hang
    {"command": "serve", "reason": "a valid `ivc serve sim` serves until stopped",
     "skip": lambda argv: any(a == "sim" or a.startswith("sim:") for a in argv)},
    {"command": "export", "reason": "reported-region grid at the default spacing",
     "skip": lambda argv: any(f in argv for f in REPORTED_GRID_FORMATS) and "--spacing" not in argv},
]


def _known(command: str, argv: list[str], problem: str | None) -> dict | None:
    for entry in KNOWN:
        if entry["command"] != command:
            continue
        if "skip" in entry and entry["skip"](argv):
            return entry
        if problem is not None and "line" in entry and entry["line"] in problem:
            return entry
    return None


COMMANDS = cli_fuzz.commands()


@pytest.fixture(scope="module")
def pool():
    old = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="ivc-cli-fuzz-") as folder:
        os.chdir(folder)  # a command writing beside the working folder writes here, not into the repository
        try:
            yield cli_fuzz.Pool(Path(folder))
        finally:
            os.chdir(old)


def test_discovery_finds_every_command():
    """The walk reaches the leaves of groups (``fixtures print``, ``tracker check``) and the plain commands."""
    names = {command.name for command in COMMANDS}
    assert {"info", "correct", "predict", "export", "fixtures print", "tracker check"} <= names
    assert not any(isinstance(command.command, type(cli_fuzz.cli)) for command in COMMANDS)


@pytest.mark.parametrize("command", COMMANDS, ids=lambda command: command.name.replace(" ", "-"))
def test_command_never_tracebacks_hangs_or_changes_inputs(command, pool):
    before = pool.checksums()

    @FUZZ
    @given(data=st.data())
    def check(data):
        outdir = Path(tempfile.mkdtemp(dir=pool.root, prefix="out-"))
        try:
            (outdir / "victim.h5").write_bytes(b"an existing file the user cares about\n")
            (outdir / "victim.svg").write_bytes(b"<svg/>\n")
            (outdir / "victim.csv").write_bytes(b"a,b\n1,2\n")
            (outdir / "a-folder").mkdir()
            victims = cli_fuzz.checksum_tree(outdir)
            argv = data.draw(cli_fuzz.invocation(command, pool, outdir, poison=command.name in WORK))
            assume(not any(entry["command"] == command.name and entry["skip"](argv) for entry in COSTLY))
            known = _known(command.name, argv, None)
            assume(known is None)
            outcome = cli_fuzz.run(argv, outdir)
            problem = cli_fuzz.verdict(outcome)
            after = pool.checksums()
            # a new file beside an input is a default output (``ivc export LUT`` writes LUT.csv there): removed
            for new in sorted(set(after) - set(before), reverse=True):
                Path(new).unlink() if Path(new).is_file() else shutil.rmtree(new, ignore_errors=True)
            changed = sorted(k for k in before if after.get(k) != before[k])
            if changed:
                problem = (problem + "; " if problem else "") + f"changed inputs {changed}"
            if "--force" not in argv:
                now = cli_fuzz.checksum_tree(outdir)
                replaced = sorted(k for k in victims if now.get(k) != victims[k])
                if replaced:
                    problem = (problem + "; " if problem else "") + f"replaced without --force {replaced}"
            known = _known(command.name, argv, problem)
            if LOG:
                with open(LOG, "a") as log:
                    log.write(json.dumps({"command": command.name, "argv": argv, "seconds": round(outcome.seconds, 2),
                                          "exit": outcome.exit_code, "problem": problem,
                                          "error": next((line for line in outcome.output.splitlines()
                                                         if line.startswith("Error:")), None),
                                          "known": known and known["reason"]}) + "\n")
            if problem and known is None and not SURVEY:
                pytest.fail(f"{cli_fuzz.shell(argv)}\n  -> {problem}\n{outcome.output[-2000:]}")
            if changed:
                raise AssertionError(f"inputs in {pool.root} were changed ({changed}); the pool cannot be trusted")
        finally:
            shutil.rmtree(outdir, ignore_errors=True)

    check()

