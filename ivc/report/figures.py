"""The report's figures (matplotlib, no pyplot state): one function per figure, each returning a Figure.

Positions are drawn in millimetres in the declared cube frame (the table's frame),
errors in mm and mrad.
"""

from __future__ import annotations

import numpy as np
from matplotlib import colormaps
from matplotlib.collections import LineCollection
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from matplotlib.ticker import FuncFormatter, MaxNLocator
from scipy.spatial import ConvexHull

from ivc.report.compute import ReportData, Slices, cube_errors, region_cells

_IVC, _DIPOLE, _CUBE = "tab:blue", "tab:orange", "tab:green"


def _panels(count: int, width: float = 3.6, height: float = 3.4) -> tuple[Figure, list]:
    columns = min(count, 3)
    rows = -(-count // columns)
    fig = Figure(figsize=(width * columns + 1.2, height * rows + 0.8), layout="constrained")
    axes = fig.subplots(rows, columns, squeeze=False, sharex=True, sharey=True)
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    return fig, list(axes.flat[:count])


def _cube_outline(ax, data: ReportData, z: float) -> bool:
    """The cube's footprint on the slice at height z (m), if the slice cuts the cube."""
    vertices = data.cube_vertices
    if vertices is None or not vertices[:, 2].min() <= z <= vertices[:, 2].max():
        return False
    corners = 1000 * vertices[:, :2]
    hull = corners[ConvexHull(corners).vertices]
    ax.fill(hull[:, 0], hull[:, 1], fill=False, edgecolor=_CUBE, linewidth=1.6, linestyle="--")
    return True


def _label_slices(axes: list, s: Slices) -> None:
    for ax, z in zip(axes, s.z, strict=True):
        ax.set_title(f"z = {1000 * z:.0f} mm", fontsize=10)
        ax.set_aspect("equal")
    for ax in axes:
        if ax.get_subplotspec().is_last_row():
            ax.set_xlabel("x (mm)")
        if ax.get_subplotspec().is_first_col():
            ax.set_ylabel("y (mm)")


def secondary_field(data: ReportData) -> Figure:
    """Himberg 2010's Fig. 33: |G| as % of the measured signal on horizontal slices of the mapped volume."""
    s = data.slices
    fig, axes = _panels(len(s.z))
    finite = s.percent[np.isfinite(s.percent)]
    top = float(finite.max()) if finite.size else 1.0
    extent = 1000 * np.array([s.x_edges[0], s.x_edges[-1], s.y_edges[0], s.y_edges[-1]])
    cmap = _cmap("magma_r")
    image = None
    cube_drawn = False
    levels = MaxNLocator(7).tick_values(0.0, top)[1:-1]  # the same contour levels on every slice
    for ax, plane in zip(axes, s.percent, strict=True):
        image = ax.imshow(plane, origin="lower", extent=extent, cmap=cmap, vmin=0.0, vmax=top,
                          interpolation="nearest")
        if np.isfinite(plane).sum() > 4:
            shown = levels[(levels > np.nanmin(plane)) & (levels < np.nanmax(plane))]
            if len(shown):
                lines = ax.contour(1000 * s.x, 1000 * s.y, plane, levels=shown, colors="k", linewidths=0.5)
                for label in ax.clabel(lines, fontsize=7, fmt="%g%%"):
                    label.set_rotation(0)  # upright: inline labels on near-vertical lines read upside down
    for ax, z in zip(axes, s.z, strict=True):
        cube_drawn |= _cube_outline(ax, data, z)
    _label_slices(axes, s)
    fig.colorbar(image, ax=axes, label="|G| / |f_D + G|  (%)", shrink=0.9)
    note = "; dashed green: the cube" if cube_drawn else ""
    fig.suptitle(f"Secondary field as a percentage of the measured signal (grey: outside the mapped volume{note})",
                 fontsize=11)
    return fig


def coverage(data: ReportData) -> Figure:
    """Kept wand samples per grid cell on the same slices; the mapped volume outlined, thin cells marked."""
    s = data.slices
    fig, axes = _panels(len(s.z))
    positive = s.counts[s.counts > 0]
    norm = LogNorm(vmin=1, vmax=max(10, int(positive.max()) if positive.size else 10))
    cmap = _cmap("viridis", (1.0, 1.0, 1.0, 0.0))  # cells without samples stay white
    X, Y = 1000 * s.x_edges, 1000 * s.y_edges
    centres_x, centres_y = (X[:-1] + X[1:]) / 2, (Y[:-1] + Y[1:]) / 2
    mesh = None
    for ax, counts, mapped, z in zip(axes, s.counts, s.mapped, s.z, strict=True):
        mesh = ax.pcolormesh(X, Y, np.ma.masked_equal(counts, 0).T, norm=norm, cmap=cmap)
        ax.add_collection(LineCollection(mapped_boundary(mapped, X, Y), colors="red", linewidths=1.4))
        thin = mapped & (counts < data.thin)
        i, j = np.nonzero(thin)
        ax.plot(centres_x[i], centres_y[j], "x", color="red", markersize=6, markeredgewidth=1.5)
        _cube_outline(ax, data, z)
    _label_slices(axes, s)
    fig.colorbar(mesh, ax=axes, label="kept wand samples per cell", shrink=0.9)
    fig.suptitle(f"Wand coverage: red line = edge of the mapped volume; x = thin (mapped, < {data.thin} samples "
                 "in the cell); white = no samples", fontsize=11)
    return fig


#: the three views of :func:`sweep_regions`: (title, horizontal axis, vertical axis); the third axis is projected
_VIEWS = (("top (x-y)", 0, 1), ("front (x-z)", 0, 2), ("side (y-z)", 1, 2))


def sweep_regions(data: ReportData) -> Figure:
    """The region each sweep's kept samples reach, projected along each axis: one colour per sweep, the mapped
    volume's outline in black, the declared working volume as a grey box, the cube in green."""
    g = data.table.grid
    centres = [1000 * (g.origin[a] + g.spacing * (np.arange(g.shape[a] - 1) + 0.5)) for a in range(3)]
    reached = [region_cells(data.table, r.positions) & data.mapped_cells for r in data.regions]
    # green is the cube's colour, grey the box's
    colours = [c for n, c in enumerate(colormaps["tab10"].colors) if n not in (2, 7)]
    fig = Figure(figsize=(15, 4.6), layout="constrained")
    axes = list(fig.subplots(1, 3))
    for ax, (title, h, v) in zip(axes, _VIEWS, strict=True):
        axis = 3 - h - v  # the one projected away
        for n, (region, cells) in enumerate(zip(data.regions, reached, strict=True)):
            shown = cells.any(axis=axis).T.astype(float)
            if shown.any():
                colour = colours[n % len(colours)]
                ax.contourf(centres[h], centres[v], shown, levels=[0.5, 1.5], colors=[colour], alpha=0.18)
                ax.contour(centres[h], centres[v], shown, levels=[0.5], colors=[colour], linewidths=1.4)
            if ax is axes[0]:
                ax.plot([], [], color=colours[n % len(colours)], linewidth=3, label=region.name)
        mapped = data.mapped_cells.any(axis=axis).T.astype(float)
        if mapped.any():
            ax.contour(centres[h], centres[v], mapped, levels=[0.5], colors="black", linewidths=1.0,
                       linestyles="--")
        if data.volume is not None:
            low, size = 1000 * (data.volume[0] - data.volume[1] / 2), 1000 * data.volume[1]
            ax.add_patch(Rectangle((low[h], low[v]), size[h], size[v], fill=False, edgecolor="0.45", linewidth=1.6))
        if data.cube_vertices is not None:
            corners = 1000 * data.cube_vertices[:, [h, v]]
            hull = corners[ConvexHull(corners).vertices]
            ax.fill(hull[:, 0], hull[:, 1], fill=False, edgecolor=_CUBE, linewidth=1.6)
        names = "xyz"
        ax.set(title=title, xlabel=f"{names[h]} (mm)", ylabel=f"{names[v]} (mm)", aspect="equal")
    fig.legend(loc="outside right upper", fontsize=9)
    fig.suptitle("Region each sweep's kept samples reach (projected); black dashed: the mapped volume; "
                 "grey: the declared working volume; green: the cube", fontsize=11)
    return fig


def cube_residuals(data: ReportData) -> Figure:
    """Himberg 2010's Tables 20-21: each cube sensor's calibrated position minus the ideal and the optimised cube."""
    cube = data.model.cube
    minus_ideal, minus_optimised = cube_errors(data.model)
    tables = (("calibrated − ideal cube (Table 20)", minus_ideal),
              ("calibrated − optimised cube (Table 21)", minus_optimised))
    fig = Figure(figsize=(10, 3.8), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True)
    sensors = np.arange(8)
    for ax, (title, values) in zip(axes, tables, strict=True):
        for a, (axis, colour) in enumerate(zip("xyz", ("tab:red", "tab:green", "tab:blue"), strict=True)):
            ax.bar(sensors + (a - 1) * 0.27, values[:, a], width=0.27, color=colour, label=axis)
        ax.axhline(0, color="k", linewidth=0.6)
        ax.set_xticks(sensors)
        ax.set_xlabel("cube sensor")
        ax.set_title(f"{title}; rms {np.sqrt(np.mean(values**2)):.2f} mm", fontsize=10)
        ax.grid(True, axis="y", alpha=0.3)
    axes[0].set_ylabel("position error (mm, fixture frame)")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Interpolation cube sensor positions (fitted edge {1000 * cube.fit.edge:.2f} mm)", fontsize=11)
    return fig


def lambda_vs_error(data: ReportData) -> Figure:
    """Himberg 2010's Fig. 35: sensor 0's pose error against rms(Λ)/rms(S); without truth, the distribution of Λ."""
    mapping, errors, gate = data.sweep.mapping, data.sweep.errors, data.sweep.gates.max_residual
    solved = mapping.sensor0.converged & mapping.inside
    residual = mapping.sensor0.residual[solved]
    if errors is None:
        fig = Figure(figsize=(6, 4), layout="constrained")
        ax = fig.subplots()
        bins = np.geomspace(max(residual.min(), 1e-9), max(residual.max(), gate) * 1.01, 60)
        ax.hist(residual, bins=bins, color=_IVC)
        ax.set_xscale("log")
        ax.axvline(gate, color="red", linestyle="--", label=f"gate {gate:g}")
        ax.set_xlabel("rms(Λ) / rms(S), sensor 0")
        ax.set_ylabel("sweep frames")
        ax.legend()
        fig.suptitle("Sensor 0 signal residual in the cube (no truth: errors cannot be drawn)", fontsize=11)
        return fig
    fig = Figure(figsize=(11, 4.2), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True)
    pairs = ((1000 * errors.position[solved, 0], "position error (mm)"),
             (1000 * errors.angle[solved, 0], "orientation error (mrad)"))
    for ax, (values, label) in zip(axes, pairs, strict=True):
        good = (values > 0) & (residual > 0)
        hexes = ax.hexbin(residual[good], values[good], xscale="log", yscale="log", bins="log", gridsize=60,
                          cmap=_cmap("viridis"), mincnt=1)
        ax.axvline(gate, color="red", linestyle="--", label=f"gate {gate:g}")
        ax.set_xlabel("rms(Λ) / rms(S), sensor 0")
        ax.set_ylabel(f"sensor 0 {label}")
        fig.colorbar(hexes, ax=ax, label="frames")
        coefficient = np.corrcoef(np.log(residual[good]), np.log(values[good]))[0, 1]
        ax.set_title(f"log-log correlation {coefficient:.2f}", fontsize=10)
    axes[0].legend(fontsize=8, loc="upper left")
    fig.suptitle(f"Interpolation (pose in the cube) error against the signal residual Λ, {int(solved.sum()):,} sweep "
                 "frames", fontsize=11)
    return fig


def error_histograms(data: ReportData) -> Figure:
    """Himberg 2010's Figs. 38-39: check-pose position and orientation errors, IVC against the uncorrected dipole."""
    e = data.check.errors
    fig = Figure(figsize=(11, 4.2), layout="constrained")
    axes = fig.subplots(1, 2)
    pairs = ((e.ivc_position_mm[e.ok], e.dipole_position_mm[e.valid], "position error (mm)"),
             (e.ivc_orientation_mrad[e.ok], e.dipole_orientation_mrad[e.valid], "orientation error (mrad)"))
    for ax, (ivc, dip, label) in zip(axes, pairs, strict=True):
        both = np.concatenate([ivc, dip])
        both = both[both > 0]
        bins = np.geomspace(both.min(), both.max() * 1.001, 80)
        for values, name, colour in ((ivc, "IVC corrected", _IVC), (dip, "dipole (uncorrected)", _DIPOLE)):
            weights = np.full(len(values), 100.0 / max(len(values), 1))
            ax.hist(values, bins=bins, weights=weights, color=colour, alpha=0.6,
                    label=f"{name}: median {np.median(values):.3g}")
            ax.axvline(np.median(values), color=colour, linestyle="--", linewidth=1)
        ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("% of check poses")
        ax.legend(fontsize=8)
        ax.grid(True, which="major", alpha=0.3)
    fig.suptitle(f"Check poses: {int(e.ok.sum()):,} corrected by IVC, {int(e.valid.sum()):,} dipole solutions "
                 f"({data.check.source})", fontsize=11)
    return fig


def error_vs_distance(data: ReportData) -> Figure:
    """Errors against distance from the cube centre: check poses (IVC and dipole) and wand samples,
    whichever the report has."""
    with_check = data.check is not None and data.check.distance is not None
    panels = 2 * with_check + (data.sweep is not None)
    fig = Figure(figsize=(max(4.4 * panels + 0.6, 8.0), 4.2), layout="constrained")
    axes = list(np.atleast_1d(fig.subplots(1, panels)))
    if with_check:
        e, distance = data.check.errors, 1000 * data.check.distance
        for ax, (ivc, dip, label) in zip(axes[:2], (
                (e.ivc_position_mm, e.dipole_position_mm, "position error (mm)"),
                (e.ivc_orientation_mrad, e.dipole_orientation_mrad, "orientation error (mrad)")), strict=True):
            alpha = float(np.clip(2000 / max(int(e.ok.sum()), 1), 0.15, 0.7))  # visible when few, not a blot when many
            ax.plot(distance[e.ok], ivc[e.ok], ".", color=_IVC, markersize=2, alpha=alpha)
            _binned(ax, distance[e.ok], ivc[e.ok], _IVC, "IVC")
            _binned(ax, distance[e.valid], dip[e.valid], _DIPOLE, "dipole")
            ax.set_ylabel(f"check pose {label}")
            ax.set_title("check poses", fontsize=10)
    if data.sweep is not None:
        mapping, errors = data.sweep.mapping, data.sweep.errors
        keep = mapping.keep
        distance = 1000 * data.sweep.distance[keep]
        ax = axes[-1]
        _binned(ax, distance, 1000 * mapping.error_estimate[keep], "tab:purple", "estimated (eq. 101)")
        if errors is not None:
            _binned(ax, distance, 1000 * errors.position[keep], "tab:gray", "true")
        ax.set_ylabel("wand sample position error (mm)")
        ax.set_title(f"kept wand samples ({int(keep.sum()):,})", fontsize=10)
    cube = "cube (to its half-diagonal)" if data.model is not None else "ideal cube at the declared pose"
    for ax in axes:
        ax.axvspan(0, 1000 * data.cube_half_diagonal, color=_CUBE, alpha=0.12, label=cube)
        ax.set_yscale("log")
        _plain_log_labels(ax)
        ax.set_xlim(left=0)
        ax.set_xlabel("distance from the cube centre (mm)")
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7)
    subject = "Error" if with_check else "Wand sample error"
    fig.suptitle(f"{subject} against distance from the cube (lines: median; dotted: 95th percentile)", fontsize=11)
    return fig


def _binned(ax, x: np.ndarray, y: np.ndarray, colour: str, label: str, bins: int = 14) -> None:
    """Median (solid) and 95th percentile (dotted) of y in equal-width bins of x (5 points or more)."""
    if len(x) == 0:
        return
    edges = np.linspace(x.min(), x.max(), bins + 1)
    which = np.clip(np.digitize(x, edges) - 1, 0, bins - 1)
    centres, median, p95 = [], [], []
    for b in range(bins):
        values = y[which == b]
        if len(values) >= 5:
            centres.append((edges[b] + edges[b + 1]) / 2)
            median.append(np.median(values))
            p95.append(np.percentile(values, 95))
    ax.plot(centres, median, "-o", color=colour, markersize=3, label=f"{label} median")
    ax.plot(centres, p95, ":", color=colour, label=f"{label} 95%")


def mapped_boundary(mapped: np.ndarray, X: np.ndarray, Y: np.ndarray) -> list:
    """Line segments along the cell edges between mapped and unmapped cells (and the grid's edge)."""
    padded = np.pad(mapped, 1)
    segments = []
    i, j = np.nonzero(padded[1:, 1:-1] != padded[:-1, 1:-1])  # edge at x = X[i] between cells i-1 and i
    segments += [((X[a], Y[b]), (X[a], Y[b + 1])) for a, b in zip(i, j, strict=True)]
    i, j = np.nonzero(padded[1:-1, 1:] != padded[1:-1, :-1])
    segments += [((X[a], Y[b]), (X[a + 1], Y[b])) for a, b in zip(i, j, strict=True)]
    return segments


def _cmap(name: str, bad: str | tuple = "0.88"):
    return colormaps[name].with_extremes(bad=bad)


def _plain_log_labels(ax) -> None:
    """Tick labels of a log y axis as plain numbers (0.05, not 5×10⁻²)."""
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if str(f"{v:.0e}")[0] in "25" else ""))


FIGURES = {
    "secondary_field": (secondary_field, "Secondary field as % of the measured signal (Himberg 2010's Fig. 33)"),
    "error_histograms": (error_histograms, "IVC against uncorrected errors (Himberg 2010's Figs. 38-39)"),
    "lambda_vs_error": (lambda_vs_error, "Pose-in-cube error against Λ (Himberg 2010's Fig. 35)"),
    "cube_residuals": (cube_residuals, "Cube sensor position errors (Himberg 2010's Tables 20-21)"),
    "coverage": (coverage, "Wand coverage of the mapped volume"),
    "error_vs_distance": (error_vs_distance, "Error against distance from the cube"),
    "sweep_regions": (sweep_regions, "Region mapped by each sweep"),
}
