"""A browser view of guided collection: the cube, the wand, the samples so far, coverage and the next target in 3D.

Built on viser (the optional ``view`` extra: ``pip install 'ivc[view]'``), served on loopback only. Feed it the
:class:`~ivc.collect.guide.StepStatus` snapshots of :func:`~ivc.collect.guide.collect_step` (it is an
``on_status`` callback); every call updates the scene. Positions are drawn as given, metres in the source frame.
"""

from __future__ import annotations

import contextlib
import sys
import threading

import numpy as np

from ivc.errors import LiveError

#: loopback only: the view shows a lab's recording, not something to publish on a network
HOST = "127.0.0.1"
#: cube edges: vertex pairs n = 4x + 2y + z differing in one bit
CUBE_EDGES = [(a, a | bit) for a in range(8) for bit in (1, 2, 4) if not a & bit]


def _viser():
    try:
        import viser
    except ImportError:
        raise LiveError("the 3D view needs viser, the optional `view` extra: pip install 'ivc[view]'") from None
    return viser


def _share_colour(share: float) -> tuple[int, int, int]:
    """Red (nothing) through amber to green (the target met)."""
    share = float(np.clip(share, 0.0, 1.0))
    return int(round(230 * (1 - share))), int(round(90 + 110 * share)), 60


class BrowserView:
    """A viser server on ``HOST:port`` showing the step being collected; call it with each status.

    ``updates`` counts the statuses drawn and ``scene`` holds what was drawn last (numbers of points, the target),
    so a caller (or a test) can tell that the view follows the samples. :meth:`close` stops the server."""

    def __init__(self, port: int = 8080):
        viser = _viser()
        try:
            with contextlib.redirect_stdout(sys.stderr):  # viser's banner: stdout is the command's own output
                self.server = viser.ViserServer(host=HOST, port=int(port), verbose=False)
        except OSError as error:
            raise LiveError(f"the 3D view cannot serve on {HOST}:{port} ({error}); choose another port") from None
        self.port = int(self.server.get_port())
        self.updates = 0
        self.scene: dict = {}
        self._lock = threading.Lock()
        self._camera_set = False
        self.server.scene.set_up_direction("+z")
        self._text = self.server.gui.add_markdown("waiting for the first samples ...")

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}"

    def __call__(self, status) -> None:
        with self._lock:
            self._draw(status)
            self.updates += 1

    def _draw(self, status) -> None:
        scene = self.server.scene
        points = status.points if status.points is not None else np.empty((0, 3))
        points = np.asarray(points, float)[np.all(np.isfinite(points), axis=1)] if len(points) else np.empty((0, 3))
        centre = None
        if status.cube is not None:
            cube = np.asarray(status.cube, float)
            segments = np.stack([[cube[a], cube[b]] for a, b in CUBE_EDGES])
            scene.add_line_segments("/cube", segments.astype(np.float32), (90, 140, 255), thickness=0.002)
            centre = cube.mean(axis=0)
        if len(points):
            colours = np.tile(np.array([[250, 190, 60]], np.uint8), (len(points), 1))
            scene.add_point_cloud("/samples", points.astype(np.float32), colours, point_size=0.003,
                                  point_shape="circle")
            centre = centre if centre is not None else points.mean(axis=0)
        latest = status.latest
        if latest is not None:
            wand = np.asarray(latest, float)
            wand = wand[np.all(np.isfinite(wand), axis=1)]
            if len(wand) > 1:
                scene.add_line_segments("/wand", np.stack([wand[:-1], wand[1:]], axis=1).astype(np.float32),
                                        (70, 70, 70), thickness=0.003)
            if len(wand):
                scene.add_point_cloud("/sensors", wand.astype(np.float32), (255, 60, 200), point_size=0.008,
                                      point_shape="circle")
        for k, (cell, share) in enumerate(status.cells):
            scene.add_icosphere(f"/coverage/{k}", radius=0.01, color=_share_colour(share),
                                position=tuple(np.asarray(cell, float)), opacity=0.6)
        if status.target is not None:
            scene.add_icosphere("/target", radius=0.015, color=(255, 40, 40), wireframe=True,
                                position=tuple(np.asarray(status.target, float)))
        if centre is not None and not self._camera_set:
            self.server.initial_camera.look_at = tuple(centre)
            self.server.initial_camera.position = tuple(centre + np.array([0.45, -0.45, 0.35]))
            self._camera_set = True
        lines = [f"**{status.step}**: {status.frames:,} frames, {status.elapsed_s:.1f} s",
                 *(f"- {p.label}: {p.value:,.4g} / {p.target:,.4g} {p.unit}" for p in status.progress)]
        if status.thin:
            lines.append(f"- still thin: {status.thin}")
        lines += [f"- problem: {p}" for p in status.problems]
        if status.done:
            lines.append("- **done**: the stop rule is met")
        self._text.content = "\n".join(lines)
        self.scene = {"step": status.step, "frames": status.frames, "points": len(points),
                      "target": None if status.target is None else np.asarray(status.target, float).tolist(),
                      "cells": [float(share) for _, share in status.cells]}

    def close(self) -> None:
        with contextlib.redirect_stdout(sys.stderr):
            self.server.stop()
