"""Scenes: a tracker source, distorters, fixtures and noise, described in TOML.

Built-in scenes live in ``ivc/sim/scenes/`` (``default``, ``mild``, ``severe``, ...);
``load_scene`` takes such a name or a path to a TOML file. The format is documented in
docs/simulator.md. Positions are in metres in the source frame, sizes in metres;
``rotation_deg = [rx, ry, rz]`` rotates about the source x, then y, then z axis.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ivc import rotations
from ivc.dipole import HEMISPHERES
from ivc.errors import SceneError
from ivc.pose.tracker_solver import SOLVERS
from ivc.sim import eddy, meshes
from ivc.sim.field import FerrousSphere, SecondaryField

#: conductivities in S/m of the named materials (``perfect`` has no resistance)
MATERIALS = {"aluminium": 3.5e7, "aluminum": 3.5e7, "copper": 5.8e7, "steel": 1.4e6, "brass": 1.5e7, "perfect": None}


def _vector(table: dict, key: str, where: str, default=None, size: int = 3) -> np.ndarray:
    value = table.get(key, default)
    if value is None:
        raise SceneError(f"{where}: missing '{key}'")
    a = np.asarray(value, dtype=float)
    if a.shape != (size,) or not np.all(np.isfinite(a)):
        raise SceneError(f"{where}.{key}: expected {size} numbers, got {value!r}")
    return a


def rotation_from_degrees(angles) -> np.ndarray:
    """Quaternion of extrinsic rotations about source x, y, z by ``angles`` degrees."""
    return rotations.from_scipy(Rotation.from_euler("xyz", np.asarray(angles, float), degrees=True))


@dataclass
class Conductor:
    """One conducting object: a built-in shape or a mesh file, with pose and material."""

    shape: str
    size: tuple[float, ...] | None
    position: np.ndarray
    quaternion: np.ndarray
    conductivity: float | None  # S/m; None = perfect conductor
    thickness: float  # metres (sheet thickness; closed solids use min(thickness, skin depth))
    resolution: float  # metres, target triangle edge
    path: Path | None = None
    scale: float = 1.0

    def surface_resistivity(self, frequency_hz: float) -> float:
        """1/(σ t) in ohms, with t limited by the skin depth for closed solids."""
        if self.conductivity is None:
            return 0.0
        skin = np.sqrt(2.0 / (2 * np.pi * frequency_hz * 4e-7 * np.pi * self.conductivity))
        t = self.thickness if self.shape == "plate" else min(self.thickness, skin)
        return 1.0 / (self.conductivity * t)

    def mesh(self):
        mesh = meshes.build(self.shape, self.size, self.resolution, self.path, self.scale)
        transform = np.eye(4)
        transform[:3, :3] = rotations.to_matrix(self.quaternion)
        transform[:3, 3] = self.position
        mesh.apply_transform(transform)
        return mesh


@dataclass
class CubeSpec:
    center: np.ndarray = field(default_factory=lambda: np.array([0.5, 0.0, 0.0]))
    quaternion: np.ndarray = field(default_factory=lambda: rotations.IDENTITY.copy())
    edge: float = 0.0508
    mounting_sigma: float = 0.0015
    placement_sigma: float = 0.0015  # error of the declared position, per axis
    placement_sigma_rad: float = 0.002  # error of the declared orientation, per axis


@dataclass
class WandSpec:
    sensors: int = 8
    spacing: float = 0.0254
    lateral_sigma: float = 0.001


@dataclass
class NoiseSpec:
    """Sensor noise. ``signal_relative`` is the white noise on each of the nine signal
    entries relative to the free-space signal level (rms entry of ``f_D``) at
    ``reference_range``; the receiver's noise floor is fixed, so relative noise grows
    with range cubed beyond it. The default, 1e-4 at 0.5 m, gives a static jitter of
    about 0.03 mm and 0.1 mrad RMS there, in line with Liberty-class specifications."""

    signal_relative: float = 1e-4
    reference_range: float = 0.5
    drift_relative_per_sqrt_s: float = 0.0
    dropout_rate: float = 1e-4
    saturation_range: float = 0.05

    @classmethod
    def none(cls) -> NoiseSpec:
        return cls(0.0, 0.5, 0.0, 0.0, 0.0)


@dataclass
class VolumeSpec:
    """The working volume a user wants mapped (scene key ``[volume]``): an axis-aligned box in the
    source frame. ``center`` (3,) m, ``size`` (3,) m. When a scene has one, the check poses are
    uniform in it and the secondary field is tabulated over it (at ``tabulate_spacing`` m)."""

    center: np.ndarray
    size: np.ndarray
    tabulate_spacing: float = 0.01

    @property
    def lower(self) -> np.ndarray:
        return self.center - self.size / 2

    @property
    def upper(self) -> np.ndarray:
        return self.center + self.size / 2

    @property
    def litres(self) -> float:
        return float(np.prod(self.size) * 1000)


#: the hand's paths of the extension sweeps (:func:`ivc.sim.rig.extension_motion`)
EXTENSION_PATTERNS = ("passes", "lissajous")


@dataclass
class ExtensionSpec:
    """Extension sweeps (scene key ``[extension]``): ``sweeps`` recordings of ``frames`` frames each, in
    which a person walks the wand, held at its far end, through the working volume in passes at
    ``speed`` m/s (the hand), the tip pointing back towards the cube within ``wobble_deg``.
    ``pattern``: ``"passes"`` (the hand walks serpentine passes over the faces of nested boxes
    around the cube, the sweeps sharing one pattern) or ``"lissajous"`` (a free Lissajous path
    over the volume, each sweep its own)."""

    sweeps: int = 0
    frames: int = 20_000
    speed: float = 0.15
    wobble_deg: float = 35.0
    pattern: str = "passes"


@dataclass
class Scene:
    name: str = "free space"
    description: str = ""
    frequency_hz: float = 10_000.0
    hemisphere: str = "+x"
    #: the pose solver the simulated tracker reports poses with (ivc.pose.tracker_solver.SOLVERS); scene key
    #: ``solver`` (``tracker``, its old name, is still read)
    solver: str = "closed-form"
    conductors: list[Conductor] = field(default_factory=list)
    spheres: list[FerrousSphere] = field(default_factory=list)
    cube: CubeSpec = field(default_factory=CubeSpec)
    wand: WandSpec = field(default_factory=WandSpec)
    noise: NoiseSpec = field(default_factory=NoiseSpec)
    sweep_rate_hz: float = 240.0
    sweep_angular_speed: float = 0.3  # rad/s
    check_radius: float = 0.16  # metres around the cube centre
    tabulate: bool = True
    volume: VolumeSpec | None = None
    extension: ExtensionSpec = field(default_factory=ExtensionSpec)
    #: every induced moment (the conductors' eddy currents and the ferrous spheres') times this: the same room's
    #: physics made stronger (scene key ``induced_scale``; the ``strong`` scene is the default room at 4)
    induced_scale: float = 1.0

    @property
    def mapped_radius(self) -> float:
        """Radius about the cube centre that the wand's sensors reach (metres)."""
        return (self.wand.sensors - 1) * self.wand.spacing + self.cube.edge

    def secondary_field(self) -> SecondaryField:
        """Solve the eddy currents (once) and return the scene's G(r)."""
        dipoles = None
        if self.conductors:
            parts = [(c.mesh(), c.surface_resistivity(self.frequency_hz)) for c in self.conductors]
            mesh = eddy.ConductorMesh.from_parts(parts)
            dipoles = eddy.FaceDipoles.from_solution(mesh, eddy.solve_stream_function(mesh, self.frequency_hz))
            dipoles = eddy.FaceDipoles(dipoles.centres, self.induced_scale * dipoles.moments)
        reach = self.mapped_radius + 0.02
        lower, upper = self.cube.center - reach, self.cube.center + reach
        spacing = 0.01
        if self.volume is not None:  # the wand walks the whole working volume
            lower = np.minimum(lower, self.volume.lower - 0.02)
            upper = np.maximum(upper, self.volume.upper + 0.02)
            spacing = self.volume.tabulate_spacing
        roi = (lower, upper) if self.tabulate else None
        spheres = [replace(s, gain=s.gain * self.induced_scale) for s in self.spheres]
        return SecondaryField(dipoles, spheres, roi, spacing=spacing)


def _conductor(entry: dict, where: str, base: Path | None) -> Conductor:
    shape = entry.get("shape")
    if shape not in meshes.SHAPES:
        raise SceneError(f"{where}.shape: {shape!r}; the shapes are {', '.join(meshes.SHAPES)}")
    material = entry.get("material", "aluminium")
    if "conductivity" in entry:
        conductivity = float(entry["conductivity"])
    elif material in MATERIALS:
        conductivity = MATERIALS[material]
    else:
        raise SceneError(f"{where}.material: {material!r}; use one of {', '.join(MATERIALS)} or give conductivity")
    path = None
    if shape == "mesh":
        if "path" not in entry:
            raise SceneError(f"{where}: a 'mesh' conductor needs 'path'")
        path = Path(entry["path"])
        if not path.is_absolute() and base is not None:
            path = base / path
    size = entry.get("size")
    if shape != "mesh" and size is None:
        raise SceneError(f"{where}: missing 'size'")
    return Conductor(
        shape=shape,
        size=tuple(float(s) for s in size) if size is not None else None,
        position=_vector(entry, "position", where),
        quaternion=rotation_from_degrees(_vector(entry, "rotation_deg", where, [0, 0, 0])),
        conductivity=conductivity,
        thickness=float(entry.get("thickness_mm", 1.0)) / 1000,
        resolution=float(entry.get("resolution_mm", 30.0)) / 1000,
        path=path,
        scale=float(entry.get("scale", 1.0)),
    )


def scene_from_dict(data: dict, name: str = "scene", base: Path | None = None) -> Scene:
    """Build a :class:`Scene` from parsed TOML, with errors that name the entry."""
    hemisphere = data.get("hemisphere", "+x")
    if hemisphere not in HEMISPHERES:
        raise SceneError(f"{name}: hemisphere {hemisphere!r}; use one of {', '.join(HEMISPHERES)}")
    if "solver" in data and "tracker" in data:
        raise SceneError(f"{name}: give solver (the tracker's pose solver) once; tracker is its old name")
    key = "tracker" if "tracker" in data else "solver"
    solver = data.get(key, "closed-form")
    if solver not in SOLVERS:
        raise SceneError(f"{name}: {key} {solver!r}; use one of {', '.join(SOLVERS)}")
    cube_t, wand_t, noise_t, sweep_t, extension_t = (data.get(k, {}) for k in ("cube", "wand", "noise", "sweep",
                                                                                 "extension"))
    cube = CubeSpec(
        center=_vector(cube_t, "center", f"{name}.cube", [0.5, 0.0, 0.0]),
        quaternion=rotation_from_degrees(_vector(cube_t, "rotation_deg", f"{name}.cube", [0, 0, 0])),
        edge=float(cube_t.get("edge_mm", 50.8)) / 1000,
        mounting_sigma=float(cube_t.get("mounting_sigma_mm", 1.5)) / 1000,
        placement_sigma=float(cube_t.get("placement_sigma_mm", 1.5)) / 1000,
        placement_sigma_rad=float(cube_t.get("placement_sigma_mrad", 2.0)) / 1000,
    )
    wand = WandSpec(
        sensors=int(wand_t.get("sensors", 8)),
        spacing=float(wand_t.get("spacing_mm", 25.4)) / 1000,
        lateral_sigma=float(wand_t.get("lateral_sigma_mm", 1.0)) / 1000,
    )
    if wand.sensors < 2:
        raise SceneError(f"{name}.wand.sensors: a wand needs at least 2 sensors")
    defaults = NoiseSpec()
    noise = NoiseSpec(**{k: float(noise_t.get(k, getattr(defaults, k))) for k in defaults.__dataclass_fields__})
    conductors = [_conductor(c, f"{name}.conductor[{i}]", base) for i, c in enumerate(data.get("conductor", []))]
    spheres = [
        FerrousSphere(
            _vector(s, "position", f"{name}.ferrous[{i}]"),
            float(s.get("radius_mm", 20.0)) / 1000,
            float(s.get("permeability", 1000.0)),
        )
        for i, s in enumerate(data.get("ferrous", []))
    ]
    volume = None
    if "volume" in data:
        volume_t = data["volume"]
        volume = VolumeSpec(_vector(volume_t, "center", f"{name}.volume"), _vector(volume_t, "size", f"{name}.volume"),
                            float(volume_t.get("tabulate_spacing_mm", 10.0)) / 1000)
        if np.any(volume.size <= 0) or not volume.tabulate_spacing > 0:
            raise SceneError(f"{name}.volume: size and tabulate_spacing_mm must be positive")
        if np.any(np.abs(volume.center - cube.center) > volume.size / 2):
            raise SceneError(f"{name}.volume: the cube ({cube.center} m) must be inside the working volume")
    extension = ExtensionSpec(
        sweeps=int(extension_t.get("sweeps", 0)),
        frames=int(extension_t.get("frames", ExtensionSpec.frames)),
        speed=float(extension_t.get("speed", ExtensionSpec.speed)),
        wobble_deg=float(extension_t.get("wobble_deg", ExtensionSpec.wobble_deg)),
        pattern=str(extension_t.get("pattern", ExtensionSpec.pattern)),
    )
    if extension.pattern not in EXTENSION_PATTERNS:
        raise SceneError(f"{name}.extension.pattern: {extension.pattern!r}; use one of "
                         f"{', '.join(EXTENSION_PATTERNS)}")
    if extension.sweeps < 0 or extension.frames < 1 or not extension.speed > 0:
        raise SceneError(f"{name}.extension: sweeps >= 0, frames >= 1 and speed > 0 are needed")
    if extension.sweeps and volume is None:
        raise SceneError(f"{name}.extension: extension sweeps walk the working volume; give [volume] too")
    return Scene(
        name=data.get("name", name),
        description=data.get("description", ""),
        frequency_hz=float(data.get("frequency_hz", 10_000.0)),
        hemisphere=hemisphere,
        solver=solver,
        conductors=conductors,
        spheres=spheres,
        cube=cube,
        wand=wand,
        noise=noise,
        sweep_rate_hz=float(sweep_t.get("rate_hz", 240.0)),
        sweep_angular_speed=float(sweep_t.get("angular_speed", 0.3)),
        check_radius=float(data.get("check_radius_mm", 160.0)) / 1000,
        volume=volume,
        extension=extension,
        induced_scale=_induced_scale(data, name),
    )


def _induced_scale(data: dict, name: str) -> float:
    value = data.get("induced_scale", 1.0)
    try:
        scale = float(value)
    except (TypeError, ValueError):
        scale = float("nan")
    if not (np.isfinite(scale) and scale > 0):
        raise SceneError(f"{name}.induced_scale: {value!r}; give a positive number (1: the room as built)")
    return scale


def builtin_scenes() -> list[str]:
    """Names of the scenes shipped with ivc."""
    return sorted(p.name[:-5] for p in resources.files("ivc.sim.scenes").iterdir() if p.name.endswith(".toml"))


def load_scene(name_or_path: str | Path | None = None) -> Scene:
    """A built-in scene by name (``None`` = ``default``), or a scene TOML file by path.

    Example:
        >>> import ivc
        >>> scene = ivc.load_scene("cockpit")
        >>> scene.name
        'cockpit'
        >>> ivc.load_scene("no such room")
        Traceback (most recent call last):
        ...
        ivc.errors.SceneError: no scene 'no such room': not a file, and the built-in scenes are ...
    """
    if name_or_path is None:
        name_or_path = "default"
    path = Path(name_or_path)
    if path.suffix != ".toml" and str(name_or_path) in builtin_scenes():
        text = resources.files("ivc.sim.scenes").joinpath(f"{name_or_path}.toml").read_text()
        return scene_from_dict(tomllib.loads(text), str(name_or_path))
    if not path.exists():
        raise SceneError(f"no scene {str(name_or_path)!r}: not a file, and the built-in scenes are "
                         f"{', '.join(builtin_scenes())}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as error:  # a mesh (.stl) or other binary file given as the scene
        raise SceneError(f"{path}: not a scene .toml file (byte {error.start} is not UTF-8 text); a mesh is "
                         "named by a scene file's [[conductor]] shape = \"mesh\" (docs/simulator.md)") from None
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML ({error})") from None
    return scene_from_dict(data, path.stem, path.parent)
