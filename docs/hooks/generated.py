"""mkdocs hooks: the pages the docs build makes itself.

- ``api.md``: the API reference of the front door, one entry per public name of ``import ivc`` (read from
  ``ivc._EXPORTS``, so a new export appears without editing the docs), rendered by mkdocstrings.
- ``gallery/*.png``: the figures of ``ivc report``, drawn by this build from a simulated protocol (default
  scene, seed 0, a 20,000-frame wand sweep and 2,000 check poses). ``IVC_DOCS_GALLERY=DIR`` reuses the figures
  of an earlier build in DIR instead of simulating again (DIR is filled when empty).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from mkdocs.structure.files import File

#: the report's figures shown in the gallery, in the report's order, with what each shows
GALLERY = {
    "secondary_field.png": "The fitted secondary field as a percentage of the measured signal, in slices "
                           "through the mapped volume.",
    "error_histograms.png": "Position and orientation errors of the check poses against truth: uncorrected "
                            "dipole solution and ivc's correction.",
    "lambda_vs_error.png": "The sweep's estimated error of each mapped sample against its mapping "
                           "lever (how far the wand's far end is from the cube).",
    "cube_residuals.png": "The calibrated cube: each sensor's offset from the ideal and from the optimised "
                          "geometry.",
    "coverage.png": "Samples per mapped cell of the table: where the sweep was thin.",
    "error_vs_distance.png": "Check-pose error against distance from the cube.",
    "sweep_regions.png": "The region each sweep mapped.",
}


def _api_page() -> str:
    import ivc

    lines = ["# API reference", "",
             "The names `import ivc` gives (`ivc.NAME`), each documented where it is defined. Subpackages a "
             "script uses by name (`ivc.predict`, `ivc.collect`, ...) are listed last.", ""]
    modules = []
    for name, (module, attribute) in ivc._EXPORTS.items():
        if attribute is None:
            modules.append((name, module))
            continue
        lines += [f"## `ivc.{name}`", "", f"::: {module}.{attribute}", "    options:",
                  "      show_root_heading: false", "      heading_level: 3", ""]
    lines += ["## Errors", "", "::: ivc.errors", "    options:", "      show_root_heading: false",
              "      heading_level: 3", ""]
    lines += ["## Subpackages", "", "| name | module |", "|---|---|"]
    lines += [f"| `ivc.{name}` | `{module}` |" for name, module in modules]
    return "\n".join(lines) + "\n"


def _gallery_figures() -> Path:
    folder = os.environ.get("IVC_DOCS_GALLERY")
    target = Path(folder) if folder else Path(tempfile.mkdtemp(prefix="ivc-docs-gallery-"))
    if all((target / name).is_file() for name in GALLERY):
        return target
    import ivc
    from ivc.report import build_report

    session = ivc.Simulator(ivc.load_scene("default"), seed=0).protocol({"wand_sweep": 20_000, "check": 2_000})
    table = ivc.fit_lut(session)
    build_report(session, table, target, overwrite=True)
    return target


def _gallery_page() -> str:
    lines = ["# Gallery", "",
             "The figures of `ivc report`, drawn by the documentation build itself from a simulated protocol "
             "(default scene, seed 0, a 20,000-frame wand sweep and 2,000 check poses; "
             "`ivc collect protocol --source sim`, `ivc fit`, `ivc report`). What each figure means: "
             "[the report](report.md).", ""]
    for name, caption in GALLERY.items():
        lines += [f"## {name[:-4].replace('_', ' ').capitalize()}", "", caption, "",
                  f"![{caption}](gallery/{name})", ""]
    return "\n".join(lines)


def on_files(files, config):
    files.append(File.generated(config, "api.md", content=_api_page()))
    files.append(File.generated(config, "gallery.md", content=_gallery_page()))
    figures = _gallery_figures()
    for name in GALLERY:
        files.append(File.generated(config, f"gallery/{name}", abs_src_path=str(figures / name)))
    return files
