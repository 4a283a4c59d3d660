"""The ``ivc`` command line: one sub-command per pipeline stage."""

from ivc.cli.main import cli, main

__all__ = ["cli", "main"]
