"""Stage 6a: a simulated AC tracker in a distorted room (conductors, ferrous objects, noise, fixtures)."""

from ivc.sim.noise_floor import pose_noise_floor
from ivc.sim.protocol import DEFAULT_FRAMES, Simulator
from ivc.sim.scene import Scene, SceneError, builtin_scenes, load_scene
from ivc.sim.stage import stage_pattern, stage_recording
from ivc.sim.tracker import SimulatedTracker

__all__ = ["DEFAULT_FRAMES", "Scene", "SceneError", "SimulatedTracker", "Simulator", "builtin_scenes", "load_scene",
           "pose_noise_floor", "stage_pattern", "stage_recording"]
