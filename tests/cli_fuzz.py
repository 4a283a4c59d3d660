"""Helpers of the property-based test of the command line (tests/test_cli_fuzz.py).

The commands and their options are DISCOVERED from click (:func:`commands` walks ``ivc.cli.main.cli``'s groups
recursively), and each parameter's values are drawn from its click type (:func:`param_tokens`): choices,
integer and float ranges, paths, flags, ``multiple`` and ``nargs=-1`` parameters, custom ``ParamType``s. The
draws lean on edge values (0, -1, huge, nan, inf, empty strings, unit-less or wrong-unit lengths and horizons,
missing paths, paths to the wrong kind of file). Plain string options carry no type to read, so a short table of
name hints (:data:`STRING_HINTS`) adds the values that mean something for them (sources, horizons, ports); an
option the table does not know gets the generic edge strings, so a new option is fuzzed from the day it lands.

Input files come from :class:`Pool`, made once per session: the sample data copied to a temporary folder,
truncated and corrupted copies, an empty file, a folder, a semicolon CSV, a text file, an HDF5 file of the wrong
kind. Output paths are drawn in a fresh folder per invocation, which also holds an existing "victim" file: a
command run without ``--force`` must leave it as it was.

An invocation runs in-process through the same entry as ``ivc`` (``cli.main(standalone_mode=True)`` via click's
``CliRunner``), in a watchdog thread bounded in time; invocations that may open sockets run in a subprocess that
is killed at the bound. The outcome is classified by :func:`verdict`.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import click
import h5py
import numpy as np
from click.testing import CliRunner
from hypothesis import strategies as st

from ivc.cli.main import cli

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "sample_data"

#: how long one invocation may take before it counts as a hang (s); the issue's bound is 30 s
BOUND = float(os.environ.get("IVC_CLI_FUZZ_BOUND", 30))


# --- discovery ---------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Command:
    """One leaf command: its words after ``ivc`` and its click object."""

    words: tuple[str, ...]
    command: click.Command

    @property
    def name(self) -> str:
        return " ".join(self.words)


def commands(root: click.Group = cli) -> list[Command]:
    """Every leaf command under ``root``, groups walked recursively (their modules imported as ``ivc`` would)."""
    found: list[Command] = []

    def walk(group: click.Group, words: tuple[str, ...]) -> None:
        ctx = click.Context(group)
        for name in group.list_commands(ctx):
            sub = group.get_command(ctx, name)
            if isinstance(sub, click.Group):
                walk(sub, (*words, name))
            elif sub is not None:
                found.append(Command((*words, name), sub))

    walk(root, ())
    return found


#: parameter names that are written, not read (a Path type does not say which): drawn as output paths
OUTPUT_NAME = re.compile(r"output|directory|_dir$|plot|preview|keep|geometry_path")


def is_output(param: click.Parameter) -> bool:
    return bool(OUTPUT_NAME.search(param.name or ""))


# --- the input pool ----------------------------------------------------------------------------------------------

def free_port() -> int:
    """A 127.0.0.1 TCP port nothing listens on at the moment of the call (bound, then released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Pool:
    """Input files made once: valid samples, damaged copies and wrong kinds, all checksummed."""

    def __init__(self, root: Path):
        self.root = root
        folder = root / "inputs"
        folder.mkdir(parents=True)
        files: dict[str, Path] = {}
        for sample in sorted((SAMPLES / "recordings").iterdir()) + sorted((SAMPLES / "scenes").iterdir()):
            files[sample.name] = shutil.copy(sample, folder / sample.name)
        rng = np.random.default_rng(41)
        for name in ("default_room_check.h5", "default_room_lut.h5", "default_room_check.csv",
                     "head_aggressive_120hz.csv", "tray_and_sphere.toml"):
            data = (SAMPLES / ("scenes" if name.endswith(".toml") else "recordings") / name).read_bytes()
            stem, ext = name.rsplit(".", 1)
            files[f"{stem}-truncated.{ext}"] = _write(folder / f"{stem}-truncated.{ext}", data[: len(data) // 3])
            flipped = bytearray(data)
            where = rng.integers(0, len(data), 40)
            flipped_values = rng.integers(0, 256, 40).astype(np.uint8)
            for at, value in zip(where, flipped_values, strict=True):
                flipped[at] = value
            files[f"{stem}-flipped.{ext}"] = _write(folder / f"{stem}-flipped.{ext}", bytes(flipped))
        csv = (SAMPLES / "recordings" / "default_room_check.csv").read_text().splitlines()
        files["semicolon.csv"] = _write(folder / "semicolon.csv", "\n".join(line.replace(",", ";")
                                                                           for line in csv[:30]).encode())
        files["header-only.csv"] = _write(folder / "header-only.csv", (csv[0] + "\n").encode())
        files["empty.h5"] = _write(folder / "empty.h5", b"")
        files["empty.csv"] = _write(folder / "empty.csv", b"")
        files["notes.txt"] = _write(folder / "notes.txt", b"not a recording\n")
        files["notes.h5"] = _write(folder / "notes.h5", b"not an HDF5 file\n")
        with h5py.File(folder / "wrong-kind.h5", "w") as handle:
            handle["numbers"] = np.arange(10.0)
            handle.attrs["kind"] = "something else"
        files["wrong-kind.h5"] = folder / "wrong-kind.h5"
        with h5py.File(folder / "empty-group.h5", "w"):
            pass
        files["empty-group.h5"] = folder / "empty-group.h5"
        (folder / "a-folder").mkdir()
        files["a-folder"] = folder / "a-folder"
        self.files = {name: Path(path) for name, path in files.items()}
        self.missing = [str(root / "no-such-file.h5"), str(root / "no-such-folder" / "x.csv"), ""]

    def paths(self) -> list[str]:
        return [str(path) for path in self.files.values()]

    def checksums(self) -> dict[str, str]:
        """Content hash of every file under the pool (a folder's listing included)."""
        sums = {}
        for path in sorted(self.root.joinpath("inputs").rglob("*")):
            sums[str(path)] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "dir"
        return sums


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def checksum_tree(folder: Path) -> dict[str, str]:
    return {str(path): hashlib.sha256(path.read_bytes()).hexdigest()
            for path in sorted(folder.rglob("*")) if path.is_file()}


# --- value strategies ---------------------------------------------------------------------------------------------

HUGE = ["1e12", "1e300", "1e309", "9223372036854775808", "-9223372036854775809", "2147483648"]
NUMERIC_EDGES = ["0", "-1", "-0", "nan", "inf", "-inf", "1e-300", "-1e-300", "", "abc", "1,5", "0x10", " 1"]
LENGTH_EDGES = ["50mm", "0mm", "-1mm", "1e9m", "nanmm", "infmm", "50", "50 kg", "mm", "5 cm", "2in", "50ms"]
GENERIC = NUMERIC_EDGES + HUGE + LENGTH_EDGES + ["ü", "-", "--", "a b", "0,0,0", "1,2", "nan,0,0"]

#: the options that cost time in proportion to a number: valid draws are capped so that a command stays cheap
#: (the demo at its default 100,000 frames runs for minutes); invalid draws (0, -1, above the range) still come
COST_CAPS = {"frames": 300, "sweep_frames": 300, "check_frames": 60, "max_frames": 300, "evaluations": 10,
             "compare_cubes": 1, "degree": 4, "max_refinements": 1, "sensors": 16}


def _string_hints(pool: Pool) -> dict[str, tuple[st.SearchStrategy[str], st.SearchStrategy[str]]]:
    """Values that mean something for plain-string options, by parameter name: (valid ones, edge ones)."""
    csvs = [p for p in pool.paths() if p.endswith(".csv")]
    h5s = [p for p in pool.paths() if p.endswith(".h5")]
    ports = st.builds(free_port)
    igtl = ports.map(lambda port: f"igtl://127.0.0.1:{port}")
    pick = st.sampled_from
    return {
        "horizon": (pick(["50ms", "0.05s", "20 ms", "100ms", "0ms"]),
                    pick(["-10ms", "50", "50 kg", "1e12s", "nanms", "infms", "ms", "", "1e-300s", "3 frames",
                          "50mm"])),
        "source": (st.one_of(pick(["sim"]), pick(csvs + h5s).map(lambda p: f"replay:{p}")),
                   st.one_of(pick(["", "bogus:x", "replay:", "serial:/dev/null", "igtl://127.0.0.1:99999",
                                   "igtl://127.0.0.1:-1", "igtl://"]), igtl)),
        "live_url": (igtl, pick(["igtl://127.0.0.1:99999", "igtl://127.0.0.1:0", "igtl://", "",
                                 "tcp://127.0.0.1:1", "igtl://127.0.0.1:abc"])),
        "publish": (ports.map(lambda port: f"127.0.0.1:{port}"),
                    pick(["127.0.0.1:99999", "127.0.0.1:-1", "127.0.0.1", ":", "", "x:y"])),
        "hemisphere": (pick(["+x", "-x", "+y", "-y", "+z", "-z"]), pick(["up", "", "x", "++z", "+X"])),
        "declared_position": (pick(["0,0,0", "0.3,0,0", "0.1,-0.2,0.05"]),
                              pick(["500,0,0", "nan,0,0", "inf,0,0", "1,2", "a,b,c", "", "1e300,0,0"])),
        "declared_quaternion": (pick(["1,0,0,0", "0,1,0,0", "0.7071,0.7071,0,0"]),
                                pick(["0,0,0,0", "nan,0,0,0", "1,0,0", "2,0,0,0", ""])),
        "grid": (pick(["4", "4,4,4", "8"]), pick(["0", "-1", "1e9", "abc", "", "2,2", "nan"])),
        "step": (pick(["check", "cube_calibration", "wand_calibration", "wand_sweep"]), pick(["nope", "", "-"])),
        "steps": (pick(["check", "wand_sweep"]), pick(["nope", ""])),
        "sensor": (pick(["0", "1", "liberty-rx2"]), pick(["-1", "99", "nope", ""])),
        "sensors": (pick(["0", "1"]), pick(["-1", "99", "a", ""])),
        "scene": (pick(["default", "mild"] + [p for p in pool.paths() if p.endswith(".toml")]),
                  pick(["nope", ""] + [p for p in pool.paths() if p.endswith((".stl", ".txt", "truncated.toml",
                                                                                  "flipped.toml"))])),
    }


#: values no parameter of a work-doing command should accept (an option given twice: the last one counts)
POISON = ["-1", "nan", "", "1e309", "abc", "-inf", "/no/such/file.h5"]


@dataclass
class Draw:
    """The argv tokens of one parameter and whether its value is an edge (likely invalid) one."""

    tokens: list[str] = field(default_factory=list)
    edge: bool = False


def _mix(valid: st.SearchStrategy[str], edges: list[str], edge: bool) -> st.SearchStrategy[tuple[str, bool]]:
    """An edge value (when ``edge``) or a valid one."""
    return st.sampled_from(edges).map(lambda v: (v, True)) if edge else valid.map(lambda v: (v, False))


def scalar(param: click.Parameter, pool: Pool, outdir: Path, hints: dict,
           edge: bool) -> st.SearchStrategy[tuple[str, bool]]:
    """One value of ``param`` as a command-line string, and whether it is an edge value."""
    kind = param.type
    cap = COST_CAPS.get(param.name or "")
    if isinstance(kind, click.Choice):
        return _mix(st.sampled_from([str(c) for c in kind.choices]), ["", "nope", "CUBIC", "1"], edge)
    if isinstance(kind, click.IntRange):
        low = kind.min if kind.min is not None else -5
        high = kind.max if kind.max is not None else 10**6
        if cap is not None:
            high = min(high, max(low, cap))
        edges = [str(v) for v in (kind.min, kind.max) if v is not None and (cap is None or v <= cap)]
        edges += [str(v - 1) for v in (kind.min,) if v is not None]
        edges += [str(kind.max + 1)] if kind.max is not None else []
        edges += ["0", "-1", "1.5", "abc", "", "nan", *HUGE[:2]]
        if cap is None:
            edges += HUGE[3:]
        return _mix(st.integers(low, high).map(str), edges, edge)
    if isinstance(kind, click.FloatRange):
        low = kind.min if kind.min is not None else -1e3
        high = kind.max if kind.max is not None else 1e3
        edges = [repr(v) for v in (kind.min, kind.max) if v is not None]
        edges += [repr(kind.min - 1e-9)] if kind.min is not None else []
        edges += [repr(kind.max * 1.0001 + 1)] if kind.max is not None else []
        return _mix(st.floats(low, high, allow_nan=False).map(repr), edges + NUMERIC_EDGES + HUGE, edge)
    if kind is click.INT or isinstance(kind, click.types.IntParamType):
        valid = st.integers(0, cap) if cap is not None else st.integers(-3, 10**6)
        return _mix(valid.map(str), NUMERIC_EDGES + HUGE + ["1.5", "-2147483649"], edge)
    if kind is click.FLOAT or isinstance(kind, click.types.FloatParamType):
        return _mix(st.floats(-1e3, 1e3, allow_nan=False).map(repr), NUMERIC_EDGES + HUGE, edge)
    if isinstance(kind, click.Path):
        if is_output(param):
            return _mix(st.sampled_from(["new.h5", "new.csv", "new.svg", "new.png", "new", "sub/new.h5", "out.vti",
                                         "new.npz", "new.json", "new.txt", "new.html", "new.stl"])
                        .map(lambda name: str(outdir / name)),
                        [str(outdir / "victim.h5"), str(outdir / "victim.svg"), str(outdir / "victim.csv"),
                         str(outdir / "a-folder"), str(outdir / "missing-dir" / "x" / "y.h5"), str(outdir), "",
                         "/proc/version", "/dev/null"], edge)
        return _mix(st.sampled_from(pool.paths()), pool.missing, edge)
    hinted = hints.get(param.name or "")
    if hinted is not None:
        return hinted[1].map(lambda v: (v, True)) if edge else hinted[0].map(lambda v: (v, False))
    typed = st.text(st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",)), max_size=6)
    if kind is click.STRING:  # a plain string the hints do not know: short texts and the generic edges
        return _mix(typed, GENERIC, edge)
    # a custom ParamType (a positive number, a length): its valid draws are the plausible values it accepts
    accepted = [value for value in PLAUSIBLE if _converts(kind, value)]
    return _mix(st.sampled_from(accepted) if accepted else typed, GENERIC, edge)


#: candidate valid values of a custom parameter type: those its ``convert`` accepts are drawn as valid ones
PLAUSIBLE = ["1", "0.5", "0.001", "2", "10", "240", "1e-6", "50mm", "2in", "5cm", "0.2mm", "3mm", "50ms", "a"]


def _converts(kind: click.ParamType, value: str) -> bool:
    try:
        kind.convert(value, None, None)
    except (click.BadParameter, click.UsageError, ValueError, TypeError):
        return False
    return True


@st.composite
def param_draw(draw, param: click.Parameter, pool: Pool, outdir: Path, hints: dict, required: bool,
               edge: bool) -> Draw:
    """The tokens of one parameter (possibly none: optional parameters are given one time in three), its value
    an edge one when ``edge``."""
    cap = (param.name or "") in COST_CAPS
    if isinstance(param, click.Option) and param.is_flag:
        return Draw([param.opts[0]] if draw(st.booleans()) else [])
    if not required and not cap and not edge and draw(st.integers(0, 2)) > 0:
        return Draw()  # an optional parameter is given one time in three
    repeat = 1
    if isinstance(param, click.Argument) and param.nargs == -1:
        repeat = draw(st.integers(0 if not param.required else 1, 3))
    elif isinstance(param, click.Option) and param.multiple:
        repeat = draw(st.integers(1, 3))
    elif param.nargs > 1:
        repeat = param.nargs
    values = [draw(scalar(param, pool, outdir, hints, edge and i == 0)) for i in range(repeat)]
    edge = any(e for _, e in values)
    if isinstance(param, click.Argument):
        return Draw([v for v, _ in values], edge)
    if param.nargs > 1:
        return Draw([param.opts[0], *(v for v, _ in values)], edge)
    return Draw([token for v, _ in values for token in (draw(st.sampled_from(param.opts)), v)], edge)


@st.composite
def invocation(draw, command: Command, pool: Pool, outdir: Path, poison: bool = False) -> list[str]:
    """One argv for ``command``: options in a drawn order, then the arguments; ``poison`` adds one value from
    :data:`POISON` to a drawn parameter (the commands that do real work on valid input are kept to invalid draws:
    valid ones would run for tens of seconds to minutes, a simulated room being tabulated each time)."""
    hints = _string_hints(pool)
    params = command.command.params
    # at most two parameters take an edge value: with more, nearly every draw is a usage error that never
    # reaches the command's own code
    edged = set(draw(st.lists(st.integers(0, max(len(params) - 1, 0)), max_size=2))) if params else set()
    poisoned = None
    if poison:
        # the parameters click does not check itself (plain strings, numbers, input paths) first: their values
        # reach the command's own checks; an output path is never poisoned (``-1`` is a good folder name)
        candidates = [i for i, p in enumerate(params) if not (isinstance(p, click.Option) and p.is_flag)
                      and not (isinstance(p.type, click.Path) and is_output(p))]
        unchecked = [i for i in candidates if _unchecked_by_click(params[i])]
        candidates = unchecked or candidates
        if candidates:
            poisoned = draw(st.sampled_from(candidates))
    options, arguments = [], []
    for index, param in enumerate(params):
        required = param.required and draw(st.integers(0, 19)) > 0  # a required one left out now and then
        got = draw(param_draw(param, pool, outdir, hints, required, index in edged))
        if index == poisoned:
            value = draw(st.sampled_from(POISON))
            got = Draw([value] if isinstance(param, click.Argument) else [param.opts[0], value], True)
        if isinstance(param, click.Argument):
            arguments.extend(got.tokens)
        elif got.tokens:
            options.append(got.tokens)
    options = draw(st.permutations(options))
    return [*command.words, *(t for group in options for t in group), *arguments]


def _unchecked_by_click(param: click.Parameter) -> bool:
    """A parameter whose values click passes on to the command unchecked (beyond being a number or a path)."""
    kind = param.type
    if isinstance(kind, (click.Choice, click.IntRange, click.FloatRange)):
        return False
    return kind in (click.STRING, click.INT, click.FLOAT) or isinstance(kind, click.Path)


# --- running --------------------------------------------------------------------------------------------------------

@dataclass
class Outcome:
    argv: list[str]
    exit_code: int | None
    output: str
    exception: BaseException | None = None
    traceback_line: str = ""
    seconds: float = 0.0
    hung: bool = False


def needs_subprocess(argv: list[str]) -> bool:
    """Invocations that may open sockets or wait on a peer: run where a hang can be killed."""
    return argv[0] == "serve" or any(token.startswith("igtl://") or token == "--live" for token in argv)


def run(argv: list[str], cwd: Path, bound: float = BOUND) -> Outcome:
    """Run ``ivc ARGV`` as a user would (standalone mode: usage and IvcError as one line, bugs as tracebacks)."""
    if needs_subprocess(argv):
        return _run_subprocess(argv, cwd, bound)
    return _run_in_process(argv, cwd, bound)


def _run_in_process(argv: list[str], cwd: Path, bound: float) -> Outcome:
    """In this process (the working folder is the caller's: a hung thread must not hold a changed one)."""
    runner = CliRunner()
    box: dict = {}

    def target() -> None:
        try:
            box["result"] = runner.invoke(cli, argv, catch_exceptions=True, standalone_mode=True,
                                          env={"COLUMNS": "120"})
        except BaseException as error:  # noqa: BLE001 - reported as the outcome
            box["error"] = error

    start = time.monotonic()
    thread = threading.Thread(target=target, daemon=True, name="ivc-cli-fuzz")
    thread.start()
    thread.join(bound)
    seconds = time.monotonic() - start
    if thread.is_alive():
        return Outcome(argv, None, "", seconds=seconds, hung=True)
    if "error" in box:
        error = box["error"]
        return Outcome(argv, None, "", error, f"{type(error).__name__}: {error}", seconds)
    result = box["result"]
    output = result.output
    exception = result.exception
    line = ""
    if exception is not None and not isinstance(exception, SystemExit):
        line = f"{type(exception).__name__}: {exception}".splitlines()[0] if str(exception) else type(
            exception).__name__
    else:
        exception = None
    return Outcome(argv, result.exit_code, output, exception, line, seconds)


def _run_subprocess(argv: list[str], cwd: Path, bound: float) -> Outcome:
    env = dict(os.environ, PYTHONPATH=str(REPO), COLUMNS="120")
    start = time.monotonic()
    process = subprocess.Popen([sys.executable, "-m", "ivc.cli", *argv], cwd=cwd, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True)
    # the interpreter's start and ivc's import are not the command's time: the bound is doubled here
    try:
        output, _ = process.communicate(timeout=2 * bound)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        return Outcome(argv, None, "", seconds=time.monotonic() - start, hung=True)
    line = ""
    if "Traceback (most recent call last)" in output:
        line = [text for text in output.splitlines() if text.strip()][-1]
    return Outcome(argv, process.returncode, output, None, line, time.monotonic() - start)


def verdict(outcome: Outcome) -> str | None:
    """What is wrong with an outcome (None when it is a result or a one-line error)."""
    if outcome.hung:
        return f"no result within {BOUND:g} s"
    if outcome.traceback_line:
        return f"traceback: {outcome.traceback_line}"
    if outcome.exit_code not in (0, 1, 2):
        return f"exit code {outcome.exit_code}"
    if outcome.exit_code != 0:
        errors = [line for line in outcome.output.splitlines() if line.startswith("Error:")]
        if len(errors) != 1:
            return f"exit {outcome.exit_code} without exactly one 'Error:' line: {outcome.output[-300:]!r}"
    return None


def shell(argv: list[str]) -> str:
    """The invocation as a user would type it."""
    import shlex

    return "ivc " + " ".join(shlex.quote(token) for token in argv)
