"""``ivc report``: what a look-up table is worth, as PNG figures and one self-contained HTML page.

:func:`build_report` solves the sweep in the cube again (the first pass, as ``ivc fit``
does before refining), corrects the check poses, draws the figures of
:mod:`ivc.report.figures`, and writes ``report.html`` (figures embedded), ``report.json``
(every number on the page) and one PNG per figure into a directory.

A report replaces an earlier one in the same directory as a whole or not at all: the new files are written
into a hidden folder beside them first, and only then swapped in (the old report's files moved aside, the new
ones moved in, the old ones deleted); an interruption or a full disk at any point leaves the old report as it
was, and no new file beside it.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from ivc import __version__
from ivc.fixtures.cube import NOMINAL_EDGE
from ivc.report import html
from ivc.report.compute import (
    THIN_SAMPLES,
    Progress,
    ReportData,
    figures_missing,
    gather,
    lacks_sentence,
    no_progress,
    summary,
)
from ivc.report.figures import FIGURES
from ivc.session import Session
from ivc.table.lookup import LookupTable

__all__ = ["FIGURES", "REPORT_FILES", "Report", "box_section", "build_report", "gather", "summary"]

REPORT_FILES = ("report.html", "report.json", *(f"{name}.png" for name in FIGURES))

_CAPTIONS = {
    "secondary_field": "The room's secondary field |G| as a percentage of the signal the tracker measures there "
                       "(|f_D + G|), on horizontal slices through the mapped volume. Where it is large, uncorrected "
                       "poses are far off; grey is outside the mapped volume, where ivc flags corrections.",
    "error_histograms": "Check-pose errors after IVC correction and of the uncorrected dipole solution (log axis; "
                        "dashed: medians). Only trusted (unflagged) corrections are counted for IVC.",
    "error_vs_distance": "Errors against the distance from the cube centre (green band: inside the cube).",
    "lambda_vs_error": "Sensor 0's pose error inside the cube against the rms of the signal residual Λ (eq. 99) "
                       "relative to rms(S), with the gate the table was fitted with (Himberg's Fig. 35). Frames right "
                       "of the gate were dropped.",
    "cube_residuals": "Each cube sensor's calibrated position minus the ideal cube vertex (Table 20) and minus the "
                      "optimised cube's vertex (eq. 108, Table 21), in the fixture frame. The fixture frame is built "
                      "from sensors 0, 4 and 2 (origin, x axis, xy plane), so those errors are partly zero by "
                      "construction, as in Himberg 2010's Table 20.",
    "sweep_regions": "Where each sweep's kept wand samples lie, projected along each axis: the cube sweep solved in "
                     "the cube, each extension sweep solved as a rigid wand against this table from its sensors the "
                     "table maps (with the gates the table was fitted with). A region outside every sweep's colour "
                     "but inside the dashed line is mapped by the field model's reach alone.",
    "coverage": "Kept wand samples (every sweep's) per grid cell on the same slices as the field. Inside the red line "
                "every node is valid and corrections are trusted; a red x marks a thin cell: mapped, but with few "
                "samples of its own, so its values come from the neighbours.",
}


@dataclass
class Report:
    directory: Path
    files: list[Path]
    numbers: dict
    missing: dict[str, str] = field(default_factory=dict)

    @property
    def html(self) -> Path:
        return self.directory / "report.html"


def _png(figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    return buffer.getvalue()


def _check_writable(directory: Path) -> None:
    """Refuse, before any work, a directory the report could not be written into."""
    folder = directory
    while not folder.exists() and folder.parent != folder:
        folder = folder.parent
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(f"{directory}: cannot write the report there ({folder} is not a writable folder); "
                              "choose another directory")


def _install(directory: Path, contents: dict[str, bytes]) -> list[Path]:
    """Write ``contents`` (file name -> bytes) into ``directory`` as one report, replacing the report files
    already there all together or not at all (module docstring). Files that are not a report's are left alone."""
    directory.mkdir(parents=True, exist_ok=True)
    staged = Path(tempfile.mkdtemp(prefix=".report-new-", dir=directory))
    backup = None
    try:
        for name, content in contents.items():
            (staged / name).write_bytes(content)
        backup = Path(tempfile.mkdtemp(prefix=".report-old-", dir=directory))
        moved_old, moved_new = [], []
        try:
            for name in REPORT_FILES:
                if (directory / name).exists():
                    os.replace(directory / name, backup / name)
                    moved_old.append(name)
            for name in contents:
                os.replace(staged / name, directory / name)
                moved_new.append(name)
        except BaseException:
            for name in moved_new:
                (directory / name).unlink(missing_ok=True)
            for name in moved_old:
                os.replace(backup / name, directory / name)
            raise
    finally:
        shutil.rmtree(staged, ignore_errors=True)
        if backup is not None:
            shutil.rmtree(backup, ignore_errors=True)
    return [directory / name for name in contents]


def build_report(session: Session, table: LookupTable, directory: str | os.PathLike, *, check: Session | None = None,
                 step: str = "check", thin: int = THIN_SAMPLES, max_frames: int | None = None,
                 overwrite: bool = False, names: dict[str, str] | None = None,
                 progress: Progress = no_progress) -> Report:
    """Write the report into ``directory``; refuse to replace an earlier one unless ``overwrite``.

    ``names``: file names to print on the page (``session``, ``lut``, ``check``) and the
    session's SHA-256 (``session_sha256``) to compare with the table's provenance.
    """
    directory = Path(directory)
    existing = [directory / name for name in REPORT_FILES if (directory / name).exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{existing[0]} exists; pass overwrite=True to replace the report, or choose another "
                              "directory")
    _check_writable(directory)
    names = names or {}
    data = gather(session, table, check, step, thin, max_frames,
                  names.get("check", "the session") if check is not None else "the session", progress)
    numbers = summary(data)
    images, missing = {}, figures_missing(data)
    update = progress("drawing figures", len(FIGURES))
    for name, (draw, _) in FIGURES.items():
        if name not in missing:
            images[name] = _png(draw(data))
        update(1)
    warnings = _warnings(data, names)
    numbers["warnings"] = warnings
    numbers["figures_missing"] = missing
    numbers["inputs"] = dict(names)
    contents = {f"{name}.png": png for name, png in images.items()}
    contents["report.json"] = (json.dumps(numbers, indent=2) + "\n").encode()
    contents["report.html"] = _page(data, numbers, images, missing, warnings, names).encode()
    return Report(directory, _install(directory, contents), numbers, missing)


def _warnings(data: ReportData, names: dict[str, str]) -> list[str]:
    out = []
    if data.mapping_missing:
        lacks = lacks_sentence(data.mapping_missing)
        out.append(f"{lacks[0].upper()}{lacks[1:]}, so the report covers the table's field and the check poses "
                   "only; the cube, coverage and sweep sections need the session the table was fitted from.")
    recorded = data.table.provenance.get("input_sha256")
    if (not data.mapping_missing and recorded and names.get("session_sha256")
            and recorded != names["session_sha256"]):
        out.append(f"The table was fitted from {data.table.provenance.get('input', 'another file')}, whose contents "
                   "differ from this session's: the sweep and cube figures describe this session, not the table's.")
    if data.check is not None:
        e = data.check.errors
        flagged = 1 - e.ok.sum() / max(int(e.valid.sum()), 1)
        if flagged > 0.1:
            out.append(f"{100 * flagged:.0f}% of the valid check poses were flagged (not trusted); the accuracy "
                       "figures count the trusted ones only.")
    return out


def _page(data: ReportData, numbers: dict, images: dict, missing: dict, warnings: list[str],
          names: dict[str, str]) -> str:
    def fig(name: str) -> str:
        if name in images:
            return html.figure(name, images[name], FIGURES[name][1], _caption(name, data))
        return html.missing(f"{FIGURES[name][1]}: {missing[name]}")

    t, c, s, cube, cov = (numbers[k] for k in ("table", "check", "sweep", "cube", "coverage"))
    meta = [f"session: {names.get('session', '(in memory)')}", f"table: {names.get('lut', '(in memory)')}",
            f"check poses: {c.get('source', names.get('check', 'the session'))}",
            f"ivc {__version__}, {datetime.now(UTC).isoformat(timespec='seconds')}"]
    summary_rows = [
        ["grid", f"{t['shape'][0]} x {t['shape'][1]} x {t['shape'][2]} nodes, {t['spacing_mm']:.1f} mm apart, "
                 f"origin {t['origin_mm']} mm"],
        ["mapped", f"{t['valid_nodes']} of {t['nodes']} nodes valid; {t['mapped_cells']} of {t['cells']} cells "
                   "mapped"],
        ["fit", f"{t['method']}" + (f" (degree {t['degree']})" if t.get("degree") is not None else "")
         + f", cross-validated rms {t['cv_rms_mm']:.3g} mm" if t["cv_rms_mm"] is not None else str(t["method"])],
    ]
    if "missing" not in s:
        summary_rows.append(["wand samples", f"{s['samples']['kept']:,} of {s['samples']['total']:,} kept"])
    if "missing" not in c:
        ivc, dipole = c["ivc"], c["dipole"]
        summary_rows.append(["check poses", f"IVC median {ivc['position_mm']['p50']:.3g} mm / "
                             f"{ivc['orientation_mrad']['p50']:.3g} mrad against the uncorrected "
                             f"{dipole['position_mm']['p50']:.3g} mm / {dipole['orientation_mrad']['p50']:.3g} "
                             f"mrad ({c['corrected']:,} of {c['samples']:,} corrected)"])
    sections = [("summary", "Summary", html.table(None, summary_rows))]
    if "missing" in c:
        accuracy = html.missing(c["missing"])
    else:
        flagged = ", ".join(f"{n} {k}" for k, n in c["flagged"].items() if n) or "none"
        placement = (f"; the declared cube pose is off by {c['placement_error_mm']:.2f} mm at the check poses"
                     if "placement_error_mm" in c else "")
        rows = [("IVC position", c["ivc"]["position_mm"], "mm"),
                ("IVC orientation", c["ivc"]["orientation_mrad"], "mrad"),
                ("dipole position (uncorrected)", c["dipole"]["position_mm"], "mm"),
                ("dipole orientation", c["dipole"]["orientation_mrad"], "mrad")]
        if "distance_from_cube_mm" in c:
            rows.append(("distance from the cube centre", c["distance_from_cube_mm"], "mm"))
        accuracy = (f"<p>IVC judged against {html.escape(c['frame'])}{placement}. Flagged: {flagged}.</p>"
                    + html.percentile_table(rows))
    regions = _regions(numbers["sweep_regions"]) + fig("sweep_regions") if "sweep_regions" in numbers else ""
    whole_volume = "volume" in numbers or "box" in numbers
    if whole_volume:
        sections.append(("volume", "Whole working volume (extension sweeps)",
                         box_section(numbers.get("box")) + (_volume(numbers["volume"]) if "volume" in numbers else "")
                         + regions))
    sections.append(("accuracy", "Accuracy on the check poses", accuracy + fig("error_histograms")
                     + fig("error_vs_distance")))
    field_numbers = numbers["secondary_field"]["percent_of_measured_at_valid_nodes"]
    sections.append(("field", "Secondary field", html.percentile_table(
        [("|G| / |f_D + G| at valid nodes", field_numbers, "%")]) + fig("secondary_field")))
    sections.append(("coverage", "Wand coverage", _coverage(cov) + fig("coverage")
                     + ("" if whole_volume else regions or fig("sweep_regions"))))
    sections.append(("sweep", "Pose in the cube and the residual Λ", _sweep(s) + fig("lambda_vs_error")))
    sections.append(("cube", "Interpolation cube", _cube(cube) + fig("cube_residuals")))
    title = f"ivc report: {Path(names['lut']).name}" if "lut" in names else "ivc report"
    return html.page(title, meta, warnings, sections)


def box_section(box: dict | None) -> str:
    """The declared working volume's coverage: the share mapped, and per face the share of its 5 cm layer."""
    if box is None:
        return "<p>The session declares no working volume (working_volume_center, working_volume_size).</p>"
    centre = ", ".join(f"{1000 * v:.0f}" for v in box["center_m"])
    size = " x ".join(f"{1000 * v:.0f}" for v in box["size_m"])
    faces = [[name, f"{100 * share:.1f}"] for name, share in box["faces"].items()]
    return (f"<p>Declared working volume: {size} mm centred at ({centre}) mm, {box['box_litres']:.0f} litres; "
            f"<b>{100 * box['fraction']:.1f} %</b> of it mapped ({box['mapped_litres']:.1f} litres).</p>"
            + html.table(["face", "mapped share of the 5 cm layer inside it (%)"], faces))


def _volume(volume: dict) -> str:
    """The joint solve's rounds (mapped litres, frames solved per sweep, map change) and the estimated
    sample error against distance from the cube."""
    sweeps = list(volume.get("extension_sweeps", {}))
    rows = [[step["iteration"], f"{step['mapped_litres']:.1f}",
             "-" if step["map_change_mm"] is None else f"{step['map_change_mm']:.4f}",
             *[step["frames_solved"].get(name, 0) for name in sweeps]] for step in volume.get("rounds", [])]
    out = (f"<p>{volume.get('mapped_litres', 0):.1f} litres mapped; {html.escape(volume.get('stopped', ''))}.</p>"
           + html.table(["round", "mapped litres", "map change (mm)", *[f"{n} frames solved" for n in sweeps]], rows))
    never = volume.get("never_touched_mapped_region") or []
    if never:
        out += f"<p>Never touched the mapped region: {html.escape(', '.join(never))}.</p>"
    distance = [[f"{r['from_mm']:.0f}-{r['to_mm']:.0f}", r["samples"], f"{r['error_p50_mm']:.3f}",
                 f"{r['error_p95_mm']:.3f}"] for r in volume.get("error_by_distance", [])]
    return out + html.table(["distance from the cube (mm)", "samples", "estimated error p50 (mm)", "p95 (mm)"],
                            distance)


def _regions(rows: list[dict]) -> str:
    """Per sweep: frames solved and kept, samples, and the mapped region its samples reach."""
    box = any("box_share_reached" in row for row in rows)
    body = [[row["name"], f"{row['frames_solved']:,} of {row['frames_recorded']:,}", f"{row['frames_kept']:,}",
             f"{row['samples']:,}", f"{row['mapped_litres_reached']:.1f}",
             f"{row['mapped_litres_reached_by_it_alone']:.1f}",
             *([f"{100 * row['box_share_reached']:.1f}"] if box else [])] for row in rows]
    head = ["sweep", "frames solved", "frames kept", "samples", "mapped litres its samples reach",
            "reached by it alone (litres)", *(["share of the working volume reached (%)"] if box else [])]
    return "<p>The region each sweep maps (grid cells holding its kept samples):</p>" + html.table(head, body)


def _caption(name: str, data: ReportData) -> str:
    if name != "error_vs_distance":
        return _CAPTIONS[name]
    check = "check poses, IVC and dipole"
    wand = ("wand samples, the error eq. 101 estimates from sensor 0's solve and the lever arm, and the true error "
            "when the session has truth")
    if data.sweep is None:
        panels = (f"{check[0].upper()}{check[1:]}. The cube is the ideal one at the declared pose (the session "
                  "does not calibrate it).")
    elif data.check is None or data.check.distance is None:
        panels = f"{wand[0].upper()}{wand[1:]}."
    else:
        panels = f"Left: {check}; right: {wand}."
    return f"{_CAPTIONS[name]} {panels}"


def _coverage(cov: dict) -> str:
    if "missing" in cov:
        return ""
    return html.table(None, [
        ["samples per mapped cell (median)", f"{cov['samples_per_mapped_cell'].get('p50', 0):.0f}"],
        [f"thin mapped cells (< {cov['thin_threshold_samples']} samples)", cov["thin_mapped_cells"]],
        ["mapped cells with no sample", cov["empty_mapped_cells"]],
        ["sampled cells outside the mapped volume", cov["sampled_cells_outside_mapped_volume"]],
    ])


def _sweep(s: dict) -> str:
    if "missing" in s:
        return ""
    rows = [("rms(Λ)/rms(S), sensor 0", s["residual_relative"], ""),
            ("estimated error of kept samples (eq. 101)", s["estimated_error_mm"], "mm")]
    for key, label, unit in (("sensor0_position_mm", "sensor 0 position error", "mm"),
                             ("sensor0_orientation_mrad", "sensor 0 orientation error", "mrad"),
                             ("kept_samples_position_mm", "true error of kept samples", "mm")):
        if key in s:
            rows.append((label, s[key], unit))
    dropped = ", ".join(f"{n:,} {k}" for k, n in s["samples"]["dropped"].items() if n) or "none"
    every = "all" if s["stride"] == 1 else f"one in {s['stride']}"
    return (f"<p>{s['frames_solved']:,} of {s['frames_recorded']:,} sweep frames solved ({every}, as the table was "
            f"fitted); gates rms(Λ)/rms(S) ≤ {s['gate_residual']:g}, estimated error ≤ {s['gate_error_mm']:g} mm. "
            f"Dropped samples: {html.escape(dropped)}.</p>" + html.percentile_table(rows))


def _cube(cube: dict) -> str:
    if "missing" in cube:
        if "centre_mm" not in cube:
            return ""
        return (f"<p>Not calibrated in this session: distances are measured from the centre of the ideal "
                f"{1000 * NOMINAL_EDGE:.1f} mm cube at the declared pose, {cube['centre_mm']} mm.</p>")
    out = f"<p>Fitted cube edge {cube['fitted_edge_mm']:.3f} mm (nominal {cube['nominal_edge_mm']:.1f} mm).</p>"
    for key, title in (("minus_ideal_mm", "Table 20: calibrated minus ideal cube (mm)"),
                       ("minus_optimised_mm", "Table 21: calibrated minus optimised cube (mm)")):
        rows = [[axis, *[v[a] for v in cube[key]]] for a, axis in enumerate("XYZ")]
        out += f"<h3>{html.escape(title)}</h3>" + html.table(["sensor", *map(str, range(8))], rows)
    return out
