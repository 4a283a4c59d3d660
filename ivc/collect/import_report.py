"""What an importer did to a file (:class:`ImportReport`), and which foreign format a file is in (:func:`sniff`).

The readers of other programs' formats (:mod:`ivc.collect.head_trace`, :mod:`ivc.collect.polhemus`) and of
ivc's recording CSV (:mod:`ivc.collect.replay`) report through these; :mod:`ivc.collect.imports` dispatches
a file to its reader.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ivc.errors import CsvError

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
