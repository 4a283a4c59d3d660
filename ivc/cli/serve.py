"""``ivc serve``: a live source served over OpenIGTLink as PLUS serves a tracker (docs/igtl.md)."""

from __future__ import annotations

import logging

import click

from ivc.igtl import DEFAULT_PORT


@click.command()
@click.argument("source")
@click.option("--port", type=click.IntRange(0, 65535), default=DEFAULT_PORT, show_default=True,
              help="TCP port to serve on (0: a free one, printed).")
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on (0.0.0.0: every one).")
@click.option("--poses-only", is_flag=True, help="Send TRANSFORMs only, no NDARRAY signal matrices (what PLUS sends).")
@click.option("--seed", type=int, default=0, show_default=True, help="sim: the simulator's seed.")
@click.option("--frames", type=click.IntRange(1), help="sim: frames per step (default: the protocol's).")
@click.option("--pause", type=click.FloatRange(0), default=5.0, show_default=True,
              help="sim, replay: seconds between two steps (the person moving the fixtures).")
@click.option("--speed", type=click.FloatRange(0, min_open=True), default=1.0, show_default=True,
              help="sim, replay: times real time.")
@click.option("--sensors", help="polhemus, igtl: sensor names in order, comma-separated.")
@click.option("--hemisphere", default="+x", show_default=True, help="polhemus: the tracking hemisphere.")
@click.option("--duration", type=click.FloatRange(0, min_open=True), help="Stop after this many seconds.")
def serve(source, port, host, poses_only, seed, frames, pause, speed, sensors, hemisphere, duration):
    """Serve SOURCE over OpenIGTLink, as PLUS serves a tracker: a TRANSFORM per sensor per frame (mm, PLUS's
    TransformStatus/TransformValid metadata), and each sensor's signal matrix as an NDARRAY unless --poses-only.

    SOURCE: sim or sim:SCENE (the simulator running the whole protocol in real time, steps labelled, --pause s
    between them; it starts when the first client connects), replay:FILE (a session file), polhemus:DEVICE (a
    Polhemus serial port). Any number of clients (3D Slicer, PLUS, `ivc collect --source igtl://`,
    `ivc correct --live`); Ctrl-C stops.
    """
    from ivc.app.serve import IgtlServer, serve_source
    from ivc.sim import Simulator, load_scene

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    counts = None
    if frames is not None and (source == "sim" or source.startswith("sim:")):
        counts = {name: frames for name in Simulator(load_scene(source[4:] or "default"), seed).steps}
    names = [s.strip() for s in sensors.split(",")] if sensors else None
    if source == "sim" or source.startswith("sim:"):
        click.echo("simulating the protocol (the default wand sweep takes a while; --frames shortens it) ...", err=True)
    live = serve_source(source, seed=seed, pause_s=pause, speed=speed, frames=counts, sensors=names,
                        hemisphere=hemisphere)
    rehearsal = source == "sim" or source.startswith(("sim:", "replay:"))
    # a rehearsal (simulated or replayed) waits for a slow client rather than drop frames: every frame reaches it
    server = IgtlServer(live, port, host, signals=not poses_only, start_on_connect=rehearsal, lossless=rehearsal)
    click.echo(f"serving {source} on {server.address[0]}:{server.address[1]}"
               + (" (starts when a client connects)" if rehearsal else ""), err=True)
    try:
        stats = server.run(duration)
    except KeyboardInterrupt:
        stats = server.stats
        click.echo("stopped", err=True)
    click.echo(f"served {stats.frames} frames ({stats.messages} messages) to {stats.clients} client(s)"
               + (f"; slow clients lost {stats.dropped_for_slow_clients} messages"
                  if stats.dropped_for_slow_clients else ""))
