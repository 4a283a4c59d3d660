"""What a fit did, typed: :class:`FitReport`, read from the ``fit`` record every fit path stores in its table.

Every fit path (the single sweep fitted by the harmonic, polynomial or equivalent-sources method, the joint
solve of extension sweeps, and the fit from reported poses alone) records what it did in the table's ``fit``
dict, which the table file keeps as JSON (``/fit``, docs/lut.md, "The table file"). :class:`FitReport` is that
record with its fields named and typed, the same for every path: a field a path does not produce is None or
empty, so a reader asks ``report.degree is None`` rather than which keys a path happened to write.
:meth:`FitReport.to_dict` gives the record back as stored, key for key.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

__all__ = ["FitReport", "FrameUse", "RefinementStep", "ReportedPoseInput", "Round", "SampleUse"]


@dataclass(frozen=True)
class FrameUse:
    """Frames of the cube sweep: ``recorded``, ``used`` after decimation to every ``stride``-th."""

    recorded: int
    used: int
    stride: int


@dataclass(frozen=True)
class SampleUse:
    """Wand samples: ``total`` solved, ``kept`` by the gates, ``used`` by the fit, ``outside_grid``, the
    ``dropped`` count per gate, and the joint solve's ``anchor`` samples (those of the cube sweep; None elsewhere)."""

    total: int
    kept: int
    used: int
    outside_grid: int
    dropped: dict[str, int]
    anchor: int | None = None


@dataclass(frozen=True)
class RefinementStep:
    """One refinement (:mod:`ivc.lut.refine`): frames re-solved as rigid wands, sensor 0's median move (mm),
    the map's change (mm, pose-equivalent), its cross-validation score (mm) and whether it was the map kept."""

    iteration: int
    frames_converged: int
    sensor0_moved_median_mm: float
    map_change_mm: float
    cv_rms_mm: float
    kept: bool


@dataclass(frozen=True)
class Round:
    """One round of the joint solve (:mod:`ivc.lut.joint`): samples, litres mapped, the map's change (mm; None
    in round 0) and the frames solved per extension sweep."""

    iteration: int
    samples: int
    mapped_litres: float
    map_change_mm: float | None
    frames_solved: dict[str, int]


@dataclass(frozen=True)
class ReportedPoseInput:
    """A fit from reported poses alone: the tracker's own ``tracker_solver`` it was fitted through, and the
    cube's field fitted from the survey's vertex poses (degree, vertex residuals in mm and mrad RMS)."""

    tracker_solver: str
    cube_degree: int
    vertex_position_rms_mm: float
    vertex_orientation_rms_mrad: float


@dataclass(frozen=True)
class FitReport:
    """The fit record of a table, typed (lengths in mm as named, litres, counts).

    ``method``: the fit method (``harmonic``, ``poly``, ``sources``, ``equivalent sources, joint``);
    ``degree``/``degree_chosen_by`` (harmonic, poly) or ``sources``/``damping``/``damping_chosen_by``
    (equivalent sources); ``cv_folds`` and ``cv_rms_mm``, the blocked cross-validation score (None when the
    fit had none to choose); ``refinement`` (single sweep), ``rounds`` with ``never_touched_mapped_region`` and
    ``error_by_distance`` (joint solve); ``reported_poses`` (a fit from reported poses, else None);
    ``extension_sweeps_ignored``: the extension sweeps a fit from reported poses left out (it maps the cube's reach);
    ``signal_noise``: the tracker's noise measured on the static steps (:mod:`ivc.lut.signal_noise`), or None;
    ``map_error``: the map's own error in the reported pose (``position_mm``, ``orientation_mrad``;
    :mod:`ivc.lut.map_error`), or None (fits from signals).
    """

    method: str
    frames: FrameUse
    samples: SampleUse
    grid_from: str
    min_support: int
    valid_nodes: int
    cv_folds: int | None = None
    cv_rms_mm: float | None = None
    degree: int | None = None
    degree_chosen_by: str | None = None
    sources: int | None = None
    damping: float | None = None
    damping_chosen_by: str | None = None
    outliers_downweighted: int = 0
    refinement: tuple[RefinementStep, ...] = ()
    refinement_stopped: str | None = None
    rounds: tuple[Round, ...] = ()
    never_touched_mapped_region: tuple[str, ...] = ()
    extension_sweeps_ignored: tuple[str, ...] = ()
    error_by_distance: tuple[dict, ...] = ()
    reported_poses: ReportedPoseInput | None = None
    signal_noise: dict | None = None
    map_error: dict | None = None
    stored: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def input(self) -> str:
        """What the fit was made from: ``signals`` or ``reported poses``."""
        return "signals" if self.reported_poses is None else "reported poses"

    @property
    def kept_refinement(self) -> int:
        """The refinement whose map was kept (0: the first fit)."""
        return next((step.iteration for step in self.refinement if step.kept), 0)

    def model_text(self) -> str:
        """The model's size and how it was chosen, in words: ``degree 10 (cross-validation)`` or
        ``400 dipoles, damping 1e-06 (cross-validation)``."""
        if self.degree is not None:
            return f"degree {self.degree} ({self.degree_chosen_by})"
        return f"{self.sources} dipoles, damping {self.damping:g} ({self.damping_chosen_by})"

    def to_dict(self) -> dict:
        """The record as the fit stored it (what the table file holds as JSON), a copy."""
        return copy.deepcopy(self.stored)

    @classmethod
    def from_dict(cls, fit: dict) -> FitReport:
        """The typed report of a stored fit record; a KeyError names a field the record lacks."""
        samples = dict(fit["samples"])
        cube = fit.get("cube")
        reported = None
        if fit.get("input") == "reported poses":
            reported = ReportedPoseInput(fit["tracker_solver"], cube["degree"], cube["vertex_position_rms_mm"],
                                         cube["vertex_orientation_rms_mrad"])
        return cls(
            method=fit["method"],
            frames=FrameUse(**fit["frames"]),
            samples=SampleUse(samples["total"], samples["kept"], samples["used"], samples["outside_grid"],
                              dict(samples["dropped"]), samples.get("anchor")),
            grid_from=fit["grid_from"],
            min_support=fit["min_support"],
            valid_nodes=fit["valid_nodes"],
            cv_folds=fit.get("cv_folds"),
            cv_rms_mm=fit.get("cv_rms_mm"),
            degree=fit.get("degree"),
            degree_chosen_by=fit.get("degree_chosen_by"),
            sources=fit.get("sources"),
            damping=fit.get("damping"),
            damping_chosen_by=fit.get("damping_chosen_by"),
            outliers_downweighted=int(fit.get("outliers_downweighted") or 0),
            refinement=tuple(RefinementStep(**step) for step in fit.get("refinement", [])),
            refinement_stopped=fit.get("refinement_stopped"),
            rounds=tuple(Round(**step) for step in fit.get("rounds", [])),
            never_touched_mapped_region=tuple(fit.get("never_touched_mapped_region", [])),
            extension_sweeps_ignored=tuple(fit.get("extension_sweeps_ignored", [])),
            error_by_distance=tuple(fit.get("error_by_distance", [])),
            reported_poses=reported,
            signal_noise=fit.get("signal_noise"),
            map_error=fit.get("map_error"),
            stored=copy.deepcopy(fit),
        )
