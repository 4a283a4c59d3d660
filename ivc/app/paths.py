"""Input and output paths of the app functions and commands: an output is never one of their inputs.

"The same file" means the same file on disk: the same path, a symbolic link to it, or a
hard link (the same device and inode), so ``overwrite=True`` (the CLI's ``--force``) can
never replace a recording or a table that is being read.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import BinaryIO

from ivc.errors import InputError
from ivc.files import atomic_path, check_writable


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether paths ``a`` and ``b`` name one file: equal once resolved (symlinks followed), or hard links."""
    a, b = Path(a), Path(b)
    try:
        if os.path.samefile(a, b):  # hard links and symlinks: one device and inode
            return True
    except OSError:  # one of them does not exist (yet)
        pass
    return a.resolve() == b.resolve()


def refuse_inputs_as_outputs(outputs: Mapping[str, str | os.PathLike | None],
                             inputs: Mapping[str, str | os.PathLike | None]) -> None:
    """Raise :class:`InputError` when an output names the same file as an input (``overwrite`` or not).

    ``outputs`` and ``inputs``: {what the user called it (a keyword, option or argument name): path};
    None entries are skipped."""
    for out_name, out_path in outputs.items():
        if out_path is None:
            continue
        for in_name, in_path in inputs.items():
            if in_path is not None and same_file(out_path, in_path):
                how = "" if Path(out_path) == Path(in_path) else f" (the same file as {in_path})"
                raise InputError(f"{out_name} {out_path} is {in_name}{how}: a command's inputs are never "
                                 "overwritten, even with overwrite=True; choose another output file")


def check_output(output: str | os.PathLike, overwrite: bool, inputs: Mapping[str, str | os.PathLike | None],
                 name: str = "OUTPUT") -> Path:
    """The output path after the checks: not one of ``inputs``; absent unless ``overwrite``; in a folder it can be
    written to (:func:`ivc.files.check_writable`), all before any work."""
    refuse_inputs_as_outputs({name: output}, inputs)
    path = Path(output)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    check_writable(path)
    return path


def input_and_output(input_file: str | os.PathLike, output: str | os.PathLike, overwrite: bool,
                     other_inputs: Iterable[tuple[str, str | os.PathLike | None]] = ()) -> tuple[Path, Path]:
    """(input, output) paths after the checks: the input exists, the output is none of the inputs (raw
    recordings are never overwritten) and does not exist unless ``overwrite``."""
    input_path = Path(input_file)
    if not input_path.exists():
        raise FileNotFoundError(f"{input_path}: no such file")
    output_path = check_output(output, overwrite, {"the input": input_file, **dict(other_inputs)})
    return input_path, output_path


def plot_format(path: str | os.PathLike) -> str:
    """The figure format matplotlib writes ``path`` in, from its extension; :class:`InputError` naming the formats
    it can write when it cannot (so a plot is refused before the work that draws it, not after)."""
    from matplotlib.figure import Figure

    formats = sorted(Figure().canvas.get_supported_filetypes())
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in formats:
        found = f"'.{suffix}'" if suffix else "no extension"
        raise InputError(f"plot={path}: a figure is written in the format of its extension ({', '.join(formats)}); "
                         f"this has {found}: name it e.g. {Path(path).with_suffix('.png').name}")
    return suffix


def check_plot(path: str | os.PathLike, overwrite: bool, inputs: Mapping[str, str | os.PathLike | None]) -> Path:
    """A figure's path after the checks of :func:`check_output` and :func:`plot_format`, before any work."""
    plot_format(path)
    return check_output(path, overwrite, inputs, "plot")


@contextlib.contextmanager
def atomic_figure(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """A binary file to ``savefig`` into, renamed over ``path`` only once the figure is whole; matplotlib writes it
    in ``path``'s format (:func:`plot_format`), though the temporary file beside it has another extension."""
    import matplotlib

    fmt = plot_format(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as handle, matplotlib.rc_context({"savefig.format": fmt}):
        yield handle
