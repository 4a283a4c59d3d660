"""Input and output paths of the commands that write a new file from a recording."""

from __future__ import annotations

from pathlib import Path

import click


def input_and_output(input_file: str, output: str, force: bool) -> tuple[Path, Path]:
    """(input, output) paths after the checks: the input exists, the output is not the input (raw
    recordings are never overwritten) and does not exist unless ``force``."""
    input_path, output_path = Path(input_file), Path(output)
    if not input_path.exists():
        raise FileNotFoundError(f"{input_path}: no such file")
    if output_path.resolve() == input_path.resolve():
        raise click.UsageError("OUTPUT must not be the input: raw recordings are never overwritten")
    if output_path.exists() and not force:
        raise FileExistsError(f"{output_path} exists; pass --force to replace it")
    return input_path, output_path
