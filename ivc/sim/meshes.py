"""Conductor shapes as triangle meshes (trimesh), in metres.

Built-in shapes are meshed as structured grids so that triangles stay well shaped
at any aspect ratio (``resolution`` is the target edge length). Any mesh file trimesh
loads (STL, OBJ, PLY, ...) can be used as well.

Sheets (``plate``) are open surfaces; solids (``box``, ``panel``, ``desk``,
``cabinet``) are closed surfaces carrying eddy currents in their skin.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from ivc.errors import InputError

SHAPES = ("plate", "box", "panel", "desk", "cabinet", "mesh")


def _grid_patch(origin, u, v, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A rectangle ``origin + s u + t v`` split into nu x nv cells of two triangles (normal u x v)."""
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    vertices = origin + s.reshape(-1, 1) * u + t.reshape(-1, 1) * v
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices, faces


def _cells(length: float, resolution: float) -> int:
    return max(1, int(np.ceil(length / resolution - 1e-9)))


def plate(size: Sequence[float], resolution: float) -> trimesh.Trimesh:
    """Open rectangular sheet ``size = (sx, sy)`` in the local xy plane, centred, normal +z."""
    sx, sy = float(size[0]), float(size[1])
    vertices, faces = _grid_patch(
        np.array([-sx / 2, -sy / 2, 0.0]), np.array([sx, 0, 0.0]), np.array([0, sy, 0.0]),
        _cells(sx, resolution), _cells(sy, resolution),
    )
    return trimesh.Trimesh(vertices, faces, process=True)


def box(size: Sequence[float], resolution: float, center: Sequence[float] = (0, 0, 0)) -> trimesh.Trimesh:
    """Closed box ``size = (sx, sy, sz)`` with outward normals, each face a structured grid."""
    half = np.asarray(size, float) / 2
    c = np.asarray(center, float)
    patches = []
    for axis in range(3):
        i, j = (axis + 1) % 3, (axis + 2) % 3
        for sign in (-1.0, 1.0):
            u = np.zeros(3)
            v = np.zeros(3)
            u[i], v[j] = 2 * half[i], 2 * half[j]
            origin = c.copy()
            origin[axis] += sign * half[axis]
            origin[i] -= half[i]
            origin[j] -= half[j]
            if sign < 0:  # keep u x v pointing outward
                origin = origin + u
                u = -u
            patches.append(_grid_patch(origin, u, v, _cells(2 * half[i], resolution), _cells(2 * half[j], resolution)))
    return _merge(patches)


def _merge(patches) -> trimesh.Trimesh:
    vertices, faces, offset = [], [], 0
    for v, f in patches:
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    mesh = trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False)
    mesh.merge_vertices(digits_vertex=9)
    mesh.remove_unreferenced_vertices()
    return mesh


def panel(size: Sequence[float], resolution: float) -> trimesh.Trimesh:
    """An LCD-like panel: a thin closed box (the metal back shield and frame), ``size = (w, h, depth)``."""
    return box(size, resolution)


def desk(size: Sequence[float], resolution: float, bar: float = 0.03) -> trimesh.Trimesh:
    """A desk frame of square bars: a rectangular top frame ``size = (length, width, height)`` and four legs.

    The top surface (wood) is not a conductor; the frame is at the top, its upper face
    at local z = 0, the legs going down to z = -height.
    """
    length, width, height = (float(s) for s in size)
    parts = []
    for y in (-width / 2 + bar / 2, width / 2 - bar / 2):
        parts.append(box((length, bar, bar), resolution, (0, y, -bar / 2)))
    for x in (-length / 2 + bar / 2, length / 2 - bar / 2):
        parts.append(box((bar, width - 2 * bar, bar), resolution, (x, 0, -bar / 2)))
    for x in (-length / 2 + bar / 2, length / 2 - bar / 2):
        for y in (-width / 2 + bar / 2, width / 2 - bar / 2):
            parts.append(box((bar, bar, height - bar), resolution, (x, y, -bar - (height - bar) / 2)))
    return trimesh.util.concatenate(parts)


def cabinet(size: Sequence[float], resolution: float) -> trimesh.Trimesh:
    """A closed sheet-metal cabinet ``size = (w, d, h)``, base at local z = 0."""
    mesh = box(size, resolution)
    mesh.apply_translation([0, 0, float(size[2]) / 2])
    return mesh


def from_file(path: str | Path, resolution: float | None = None, scale: float = 1.0) -> trimesh.Trimesh:
    """Load a mesh file (metres after ``scale``), subdivided to ``resolution`` if given."""
    mesh = trimesh.load(path, force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"{path}: no triangle mesh in this file")
    mesh.apply_scale(scale)
    if resolution is not None:
        vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=resolution)
        mesh = trimesh.Trimesh(vertices, faces, process=True)
    return mesh


def build(shape: str, size: Sequence[float] | None, resolution: float, path: str | Path | None = None,
          scale: float = 1.0) -> trimesh.Trimesh:
    """Mesh of a named built-in shape, or of a mesh file when ``shape == "mesh"``."""
    if shape == "mesh":
        if path is None:
            raise InputError("a 'mesh' conductor needs a file path")
        return from_file(path, resolution, scale)
    builders = {"plate": plate, "box": box, "panel": panel, "desk": desk, "cabinet": cabinet}
    if shape not in builders:
        raise InputError(f"unknown conductor shape {shape!r}; the shapes are {', '.join(SHAPES)}")
    if size is None:
        raise InputError(f"a {shape!r} conductor needs a size")
    return builders[shape](size, resolution)
