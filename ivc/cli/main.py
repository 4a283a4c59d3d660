"""Entry point and shared behaviour of the ``ivc`` command line."""

from __future__ import annotations

import click

from ivc import __version__
from ivc.session import SessionError  # LutError and CsvError are SessionErrors


class IvcGroup(click.Group):
    """A click group that turns the library's data errors into one-line CLI errors."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (SessionError, FileNotFoundError, FileExistsError, ValueError) as error:
            raise click.ClickException(str(error)) from None


@click.group(cls=IvcGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="ivc")
def cli() -> None:
    """Correct AC electromagnetic tracker poses near metal (interpolation-volume calibration).

    The pipeline: `ivc collect` records the protocol into a session file (from the
    built-in simulator or a real tracker's recording); `ivc info` says what a session
    holds and what it still lacks; `ivc fixtures` reports the fixture calibration;
    `ivc fit` builds the secondary-field look-up table; `ivc correct` applies it;
    `ivc evaluate` compares corrected with true poses; `ivc report` draws the
    figures and one HTML page; `ivc export` writes the
    table for firmware, 3D Slicer, ParaView and Vrui; `ivc predict` predicts
    orientations ahead to hide display lag. `ivc demo` runs it all on a
    simulated room.
    """


def _register() -> None:
    from ivc.cli import collect, correct, demo, evaluate, export, fit, fixtures, info, predict, report

    for command in (collect.collect, correct.correct, demo.demo, evaluate.evaluate, export.export, fit.fit,
                    fixtures.fixtures, info.info, predict.predict, report.report):
        cli.add_command(command)


_register()


def main() -> None:
    cli()
