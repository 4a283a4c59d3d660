"""``ivc collect``: record protocol steps into a session file, from the simulator, a recording or a live tracker."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from ivc import rotations
from ivc import session as session_io
from ivc.cli.options import POSITIVE, RATE_HZ, SIM_FRAMES
from ivc.cli.paths import refuse_inputs_as_outputs
from ivc.cli.progress import ON_TERMINAL
from ivc.cli.tracker import tracker_option
from ivc.collect import check_step, replay
from ivc.collect.guide import instruction, save_step
from ivc.collect.sources import is_live_spec
from ivc.files import check_writable
from ivc.fixtures.geometry import load_geometries, part_declared_pose
from ivc.session import STEPS, Session, SessionError, Step, Truth, is_extension_step
from ivc.sim import Simulator, load_scene


def _floats(count: int):
    def parse(ctx, param, value):
        if value is None:
            return None
        try:
            numbers = np.array([float(v) for v in value.replace(" ", "").split(",")])
        except ValueError:
            raise click.BadParameter(f"expected {count} comma-separated numbers, got {value!r}") from None
        if numbers.shape != (count,):
            raise click.BadParameter(f"expected {count} comma-separated numbers, got {value!r}")
        return numbers

    return parse


def _parse_source(source: str) -> tuple[str, str | None]:
    if is_live_spec(source):
        return "live", source
    kind, _, argument = source.partition(":")
    if kind == "sim":
        return kind, argument or None
    if kind == "replay" and argument:
        return kind, argument
    raise click.BadParameter(f"{source!r}: use sim, sim:SCENE (a built-in name or a .toml file), replay:FILE, "
                             "igtl://HOST:PORT or polhemus:DEVICE", param_hint="--source")


class SimulatorProgress:
    """Builds the simulator once and shows what the slow parts are doing."""

    def __init__(self, scene_name: str | None, seed: int, tracker=None, geometries=None):
        self.scene = load_scene(scene_name)
        geometries = geometries or {}
        self.simulator = Simulator(self.scene, seed, tracker, cube_geometry=geometries.get("cube"),
                                   wand_geometry=geometries.get("wand"))
        self.prepared = False

    def prepare(self, distorted: bool) -> None:
        if not distorted or self.prepared:
            return
        self.prepared = True
        click.echo(f"Solving eddy currents in scene {self.scene.name!r} ...", err=True)
        field = self.simulator.secondary
        if field.dipoles is not None and field.roi is not None:
            with tqdm(desc="tabulating the secondary field", unit="slab", leave=False, disable=ON_TERMINAL) as bar:

                def advance(done: int, total: int) -> None:
                    bar.total = total
                    bar.update(done - bar.n)

                self.simulator.prepare(progress=advance)


    @contextmanager
    def protocol_progress(self, hemisphere: str) -> Iterator[Callable[[str, Step, Session], None]]:
        """An ``on_step`` for :meth:`Simulator.protocol`: a bar over the steps, each step's warnings on stderr,
        and the eddy-current solve (with its own progress) before the first distorted step."""
        with tqdm(total=len(self.simulator.steps), desc="protocol", unit="step", disable=ON_TERMINAL) as bar:

            def on_step(name: str, new: Step, collected: Session) -> None:
                for warning in check_step(name, new, collected, hemisphere):
                    click.echo(f"warning: {warning}", err=True)
                bar.update()
                if name == "cube_calibration":
                    self.prepare(distorted=True)

            yield on_step


def summary(name: str, step: Step, truth: Truth | None) -> str:
    text = f"{name}: {step.n_frames} frames x {step.n_sensors} sensors, {100 * step.valid_mask.mean():.2f}% valid"
    if truth is not None and step.position is not None:
        ok = step.valid_mask
        error = np.linalg.norm(step.position - truth.position, axis=-1)[ok]
        angle = rotations.angle_between(step.quaternion, truth.quaternion)[ok]
        text += (f"; tracker's own (dipole) error: median {1000 * np.median(error):.1f} mm, "
                 f"{1000 * np.median(angle):.1f} mrad")
    return text


def _record(name, sim, kind, argument, frames, rate, declared_position, declared_quaternion, device=None,
            hemisphere="+x"):
    step, truth = _record_raw(name, sim, kind, argument, frames, rate, declared_position, declared_quaternion)
    if device is not None:
        from ivc.collect.tracker_units import apply_tracker

        step = apply_tracker(step, device[0], hemisphere, device[1], name)
    return step, truth


def _record_raw(name, sim, kind, argument, frames, rate, declared_position, declared_quaternion):
    if kind == "sim":
        sim.prepare(name in ("cube_survey", "wand_sweep", "check") or is_extension_step(name))
        step, truth = sim.simulator.step(name, frames)
    else:
        step, truth = replay(argument, name, rate)
        if frames is not None:
            raise click.BadParameter("--frames is for simulated sources; a replay keeps every frame")
    if name == "cube_survey":
        _declare(step, declared_position, declared_quaternion)
    return step, truth


def _declare(step: Step, declared_position, declared_quaternion) -> None:
    """Set the cube_survey's declared pose from the command line, where given; refuse a survey without one."""
    if declared_position is not None:
        step.attrs["declared_position"] = declared_position
    if declared_quaternion is not None:
        if abs(np.linalg.norm(declared_quaternion) - 1) > 1e-6:
            raise click.BadParameter("must be a unit quaternion w,x,y,z", param_hint="--declared-quaternion")
        step.attrs["declared_quaternion"] = rotations.canonical(declared_quaternion)
    if "declared_position" not in step.attrs or "declared_quaternion" not in step.attrs:
        raise click.UsageError(
            "cube_survey needs the cube's declared pose: pass --declared-position x,y,z (metres) and "
            "--declared-quaternion w,x,y,z (the cube fixture frame, origin at sensor 0, in the source frame)"
        )


def _step_name(ctx, param, value: str) -> str:
    if value in (*STEPS, "protocol") or is_extension_step(value):
        return value
    raise click.BadParameter(f"{value!r}: use one of {', '.join(STEPS)}, extension_sweep_N (N = 1 to 99) or protocol")


@click.command()
@click.argument("step", callback=_step_name, metavar="STEP")
@click.option("--source", default="sim", show_default=True, help="sim, sim:SCENE (name or .toml), replay:FILE "
              "(a session .h5 or a recording .csv), or a live tracker: igtl://HOST:PORT (an OpenIGTLink server: "
              "PLUS, 3D Slicer, `ivc serve`) or polhemus:DEVICE (a Polhemus serial port), collected guided.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Session file to add to.")
@click.option("--frames", type=SIM_FRAMES, help="Frames to simulate (default: the step's protocol default); from a "
              "live source, stop each step after N frames instead of by its stop rule.")
@click.option("--sweep-frames", type=SIM_FRAMES, help="protocol: frames of the wand sweep (default 100,000).")
@click.option("--check-frames", type=SIM_FRAMES, help="protocol: check poses (default 10,000).")
@click.option("--seed", type=int, default=0, show_default=True, help="Simulator seed.")
@click.option("--hemisphere", help="Hemisphere of a replayed recording (default +x; a scene declares its own).")
@click.option("--rate", type=RATE_HZ, help="Sample rate (Hz) of a replayed CSV (default: inferred from its times).")
@click.option("--declared-position", callback=_floats(3), help="cube_survey: declared cube position x,y,z in m.")
@click.option("--declared-quaternion", callback=_floats(4), help="cube_survey: declared cube orientation w,x,y,z.")
@click.option("--force", is_flag=True, help="Replace a step that is already in the session file.")
@click.option("--geometry", "geometry_files", multiple=True, type=click.Path(dir_okay=False),
              help="A printed cube's and/or wand's geometry file (repeat for both; docs/printing.md): the simulator "
                   "builds that fixture, and --declared-position/--declared-quaternion give the cube's part frame "
                   "(its corner mark), from which the declared frame follows.")
@click.option("--sensors", help="Live sources: the device names in the step's order, sensor 0 first "
              "(NAME0,NAME1,...).")
@click.option("--duration", type=POSITIVE, help="Live sources: stop the step after this many seconds of tracker "
              "time instead of by its stop rule.")
@click.option("--guided", is_flag=True, help="Stream replay:FILE (a session .h5) through guided collection as a "
              "live tracker would (a rehearsal: each step records the frames the file holds for it).")
@click.option("--view", is_flag=True, help="Live sources: also show the collection in 3D in a browser, served "
              "on loopback (needs the `view` extra: pip install 'ivc[view]').")
@click.option("--view-port", type=click.IntRange(0, 65535), default=8080, show_default=True,
              help="--view: the loopback port to serve on.")
@tracker_option
def collect(step, source, output, frames, sweep_frames, check_frames, seed, hemisphere, rate, declared_position,
            declared_quaternion, force, geometry_files, sensors, duration, guided, view, view_port, tracker_file):
    """Record protocol STEP (or the whole `protocol`) into the session file OUTPUT.

    The protocol (Himberg 2010, ch. 4.4.3): cube_calibration (free space), cube_survey (cube at
    its declared pose in the distorted room), wand_calibration (free space), wand_sweep
    (wand sensor 0 inside the cube, far end sweeping), then any extension sweeps
    extension_sweep_1, extension_sweep_2, ... (the wand walked freely through the working volume,
    part of it inside the region mapped so far), and check (independent poses).
    With --tracker-model the signals are stored in ideal-dipole units (a simulated device
    records with that coil model first).

    From a live tracker (--source igtl://HOST:PORT or polhemus:DEVICE; or a session file
    rehearsed with --source replay:FILE --guided) each step is guided: every sensor shown
    OK / missing / stale with its rate and jitter, progress toward the step's stop rule
    (stated when it starts), the region still thin and the problems; the step ends when the
    rule is met (or after --frames / --duration). Ctrl-C ends it cleanly: it is kept if it
    makes a valid step, else dropped, and the output says which (docs/collect.md).
    """
    kind, argument = _parse_source(source)
    check_writable(output)  # a folder it cannot write into is found now, not after a step of collection
    geometries = load_geometries(geometry_files)
    if "cube" in geometries and (declared_position is not None or declared_quaternion is not None):
        declared_position, declared_quaternion = part_declared_pose(geometries["cube"], declared_position,
                                                                    declared_quaternion)
    if guided and kind != "replay":
        raise click.UsageError("--guided replays a session file: use it with --source replay:FILE")
    if kind == "live" or guided:
        if tracker_file is not None or rate is not None or sweep_frames or check_frames:
            raise click.UsageError("--tracker-model, --rate, --sweep-frames and --check-frames are for sim and "
                                   "replay sources; a live step stops by its rule, --frames or --duration")
        if guided:
            refuse_inputs_as_outputs({"--output": output}, {"the --source file": argument})
        guided_collect(step, source, Path(output), frames=frames, duration=duration, sensors=sensors,
                       hemisphere=hemisphere, declared_position=declared_position,
                       declared_quaternion=declared_quaternion, force=force, view=view, view_port=view_port)
        return
    if sensors is not None or duration is not None or view:
        raise click.UsageError("--sensors, --duration and --view are for live sources (igtl://, polhemus:)")
    if kind == "replay" or argument is not None:
        refuse_inputs_as_outputs({"--output": output}, {"the --source file": argument})
    device = None
    if tracker_file is not None:
        from ivc.collect.tracker_units import load_labelled_tracker

        device = load_labelled_tracker(tracker_file)
    sim = SimulatorProgress(argument, seed, device[0] if device else None, geometries) if kind == "sim" else None
    hemisphere = hemisphere or (sim.scene.hemisphere if sim else "+x")
    output = Path(output)
    if step == "protocol":
        if kind != "sim":
            raise click.UsageError("`ivc collect protocol` simulates; replay a recording one step at a time")
        if output.exists() and not force:
            raise FileExistsError(f"{output}: exists; choose a new file or pass --force to replace it")
        counts = {name: frames for name in sim.simulator.steps} | {"wand_sweep": sweep_frames, "check": check_frames}
        with sim.protocol_progress(hemisphere) as on_step:
            collected = sim.simulator.protocol(counts, on_step=on_step)
        collected.hemisphere = hemisphere
        _declare(collected.steps["cube_survey"], declared_position, declared_quaternion)
        if device is not None:
            from ivc.collect.tracker_units import apply_tracker_to_session

            collected = apply_tracker_to_session(collected, *device)
        session_io.write(collected, output, overwrite=force, on_wait=lambda m: click.echo(m, err=True))
        for name in sim.simulator.steps:
            click.echo(summary(name, collected.steps[name], collected.truth.get(name)))
        click.echo(f"wrote {output}")
        return
    existing = session_io.read(output) if output.exists() else None
    if existing is not None and step in existing.steps and not force:
        raise FileExistsError(f"{output}: step {step!r} is already recorded; pass --force to replace it")
    new, truth = _record(step, sim, kind, argument, frames, rate, declared_position, declared_quaternion, device,
                         hemisphere)
    for warning in check_step(step, new, existing or Session(hemisphere=hemisphere), hemisphere):
        click.echo(f"warning: {warning}", err=True)
    try:
        session_io.add_step(output, step, new, truth, hemisphere=hemisphere, force=force,
                            on_wait=lambda m: click.echo(m, err=True))
    except SessionError as error:
        raise SessionError(f"{error} (nothing was written)") from None
    click.echo(summary(step, new, truth))
    click.echo(f"wrote {step} to {output}")


def guided_collect(step: str, source: str, output: Path, *, frames: int | None, duration: float | None,
                   sensors: str | None, hemisphere: str | None, declared_position, declared_quaternion, force: bool,
                   view: bool, view_port: int) -> None:
    """Collect STEP (or the whole protocol) from a live source, guided by the stop rules (ivc.collect.guide)."""
    from ivc.cli.guided_view import make_view
    from ivc.collect.guide import collect_protocol, collect_step
    from ivc.collect.sources import open_live_source

    names = [n.strip() for n in sensors.split(",")] if sensors else None
    if names is not None and (not all(names) or len(set(names)) != len(names)):
        raise click.BadParameter(f"{sensors!r}: give distinct device names, comma-separated", param_hint="--sensors")
    existing = session_io.read(output) if output.exists() else None
    hemisphere = hemisphere or (existing.hemisphere if existing else "+x")
    session = existing or Session(hemisphere=hemisphere)
    if existing is not None and existing.hemisphere != hemisphere:
        raise click.UsageError(f"{output} was recorded in hemisphere {existing.hemisphere}, not {hemisphere}")
    steps = list(STEPS) if step == "protocol" else [step]
    already = [name for name in steps if name in session.steps]
    if already and not force:
        raise FileExistsError(f"{output}: step(s) {', '.join(already)} already recorded; pass --force to replace them")
    survey = "cube_survey" in steps
    if survey and (declared_position is None or declared_quaternion is None):
        raise click.UsageError("cube_survey needs the cube's declared pose: pass --declared-position x,y,z (metres) "
                               "and --declared-quaternion w,x,y,z (the cube fixture frame in the source frame)")
    if survey and abs(np.linalg.norm(declared_quaternion) - 1) > 1e-6:
        raise click.BadParameter("must be a unit quaternion w,x,y,z", param_hint="--declared-quaternion")
    counts = {"frames": frames, "duration_s": duration} if frames is not None or duration is not None else {}
    live = open_live_source(source, sensors=names, hemisphere=hemisphere)
    terminal = make_view()
    browser = _browser(view, view_port)
    on_status = terminal if browser is None else _both(terminal, browser)
    try:
        with live:
            if step == "protocol":
                session, reports = collect_protocol(
                    live, steps, session, output=output, force=force, hemisphere=hemisphere,
                    declared_position=declared_position, declared_quaternion=declared_quaternion,
                    counts={name: counts for name in steps} if counts else None, on_step_start=terminal.on_step_start,
                    on_status=on_status, on_step=terminal.on_step)
            else:
                terminal.on_step_start(step, instruction(step))
                attrs = None
                if survey:
                    attrs = {"declared_position": declared_position,
                             "declared_quaternion": rotations.canonical(declared_quaternion)}
                new, report = collect_step(live, step, session, frames=frames, duration_s=duration,
                                           hemisphere=hemisphere, attrs=attrs, on_status=on_status)
                terminal.on_step(new, report)
                reports = [report]
                if new is not None:
                    save_step(output, step, new, session, force)
    finally:
        terminal.close()
        if browser is not None:
            browser.close()
    for report in reports:
        click.echo(report.message)
    kept = [r.step for r in reports if r.kept]
    if kept:
        click.echo(f"wrote {', '.join(kept)} to {output}")
    if not reports or not reports[-1].kept:
        raise click.exceptions.Exit(1)


def _browser(view: bool, port: int):
    if not view:
        return None
    from ivc.collect.view import BrowserView

    browser = BrowserView(port=port)
    click.echo(f"3D view: {browser.url}", err=True)
    return browser


def _both(*views):
    def on_status(status):
        for view in views:
            view(status)

    return on_status
