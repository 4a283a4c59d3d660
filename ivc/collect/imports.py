"""Recordings in other programs' formats, read into a :class:`~ivc.session.Step` with their quirks reported.

Two formats are recognised by their first line:

* a head-orientation trace (:mod:`ivc.collect.head_trace`): ``timestamp viewpoint w x y z``;
* a Polhemus Liberty logger CSV (:mod:`ivc.collect.polhemus`): ``Time,w1,x1,y1,z1,w2,...,loc1_x,...``.

Every importer returns the step and an :class:`ImportReport` that says what was read, dropped
and flagged; the report's text is also kept in ``step.attrs["import_report"]``. Nothing is dropped
or flagged without a line in the report.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ivc.errors import CsvError
from ivc.session import Step

#: the formats :func:`sniff` recognises by their first line
FORMATS = ("head-trace", "polhemus-liberty")


@dataclass
class ImportReport:
    """What an importer did to a file: rows read, rows dropped and samples flagged invalid, with reasons."""

    path: str
    format: str
    rows: int = 0
    frames: int = 0
    notes: list[str] = field(default_factory=list)

    def add(self, note: str) -> None:
        self.notes.append(note)

    def text(self) -> str:
        head = f"{Path(self.path).name}: {self.format}, {self.rows} rows -> {self.frames} frames"
        return "\n".join([head, *(f"  {n}" for n in self.notes)])


#: malformed rows named in one refusal, at most
MAX_REPORTED = 10


def refuse_malformed(path: str | Path, errors: list[str]) -> None:
    """Raise a CsvError naming the first :data:`MAX_REPORTED` malformed rows, if there are any (nothing is imported).

    Readers stop collecting once they hold more than MAX_REPORTED errors.
    """
    if errors:
        more = " (and more)" if len(errors) > MAX_REPORTED else ""
        raise CsvError(f"{path}: malformed rows, nothing imported{more}:\n  " + "\n  ".join(errors[:MAX_REPORTED]))


def _first_line(path: Path) -> str:
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as handle:
            return handle.readline().strip()
    except IsADirectoryError:
        return ""


def sniff(path: str | Path) -> str | None:
    """The name of the foreign format of ``path`` (one of :data:`FORMATS`), or None for ivc's own files."""
    path = Path(path)
    if not path.is_file():
        return None
    line = _first_line(path)
    if line.split() == ["timestamp", "viewpoint", "w", "x", "y", "z"]:
        return "head-trace"
    cells = [c.strip() for c in line.split(",")]
    if cells[:5] == ["Time", "w1", "x1", "y1", "z1"] and "loc1_x" in cells:
        return "polhemus-liberty"
    return None


def read_import(path: str | Path, unit: str | None = None) -> tuple[Step, ImportReport]:
    """Read a file in one of :data:`FORMATS`; ``unit``: the position unit of a Polhemus CSV (default inches)."""
    kind = sniff(path)
    if kind == "head-trace":
        from ivc.collect.head_trace import read_head_trace

        return read_head_trace(path)
    if kind == "polhemus-liberty":
        from ivc.collect.polhemus import read_liberty_csv

        return read_liberty_csv(path, unit="in" if unit is None else unit)
    raise CsvError(f"{path}: not a head-orientation trace (header 'timestamp viewpoint w x y z') nor a Polhemus "
                   "Liberty CSV (header 'Time,w1,x1,y1,z1,...'); for ivc's own recording CSV see "
                   "docs/session-format.md")


def read_recording(path: str | Path, sample_rate_hz: float | None = None, unit: str | None = None
                   ) -> tuple[Step, ImportReport | None]:
    """Any single-step recording: a foreign format (:func:`read_import`) or ivc's recording CSV (no report)."""
    if sniff(path) is not None:
        step, report = read_import(path, unit)
        if sample_rate_hz is not None:
            step.sample_rate_hz = float(sample_rate_hz)
        return step, report
    from ivc.collect.replay import read_csv

    return read_csv(path, sample_rate_hz), None
