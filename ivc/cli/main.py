"""Entry point and shared behaviour of the ``ivc`` command line."""

from __future__ import annotations

import importlib

import click

from ivc import __version__
from ivc.cli.flags import cli_words
from ivc.errors import IvcError


class IvcGroup(click.Group):
    """A click group that turns the library's deliberate errors into one-line CLI errors.

    ``IvcError`` (bad input, a malformed file, a missing step) and ``OSError`` (a file
    that cannot be opened or written) are the user's to fix and print as one line.
    Anything else is a bug in ivc and keeps its traceback; ``--debug`` shows the
    traceback of the one-line errors too. The library's messages name its keyword
    arguments; the line says the command's flags instead (:func:`ivc.cli.flags.cli_words`).
    """

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(COMMANDS) | set(self.commands))

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        """A sub-command, its module imported on first use (see COMMANDS)."""
        if name in COMMANDS and name not in self.commands:
            self.add_command(getattr(importlib.import_module(f"ivc.cli.{COMMANDS[name]}"), name))
        return self.commands.get(name)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (IvcError, OSError) as error:
            if ctx.meta.get("ivc.debug"):
                raise
            raise click.ClickException(cli_words(_one_line(error), ctx.invoked_subcommand)) from None


def _one_line(error: BaseException) -> str:
    if isinstance(error, OSError) and error.filename is not None and error.strerror:
        return f"{error.filename}: {error.strerror}"
    return str(error)


@click.group(cls=IvcGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="ivc")
@click.option("--debug", is_flag=True, help="Show the traceback of every error, not only of internal ones.")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """Correct AC electromagnetic tracker poses near metal (interpolation-volume calibration).

    The pipeline: `ivc collect` records the protocol into a session file (from the
    built-in simulator or a real tracker's recording); `ivc info` says what a session
    holds and what it still lacks; `ivc fixtures` reports the fixture calibration;
    `ivc fit` builds the secondary-field look-up table; `ivc correct` applies it;
    `ivc evaluate` compares corrected with true poses; `ivc report` draws the
    figures and one HTML page; `ivc export` writes the
    table for firmware, 3D Slicer, ParaView and Vrui; `ivc predict` predicts
    orientations ahead to hide display lag. `ivc tracker` calibrates a
    research tracker's own coil model. `ivc demo` runs it all on a
    simulated room.
    """
    ctx.meta["ivc.debug"] = debug


#: every sub-command and the module that defines it, imported only when the command runs (or
#: ``ivc --help`` lists it): ``ivc correct`` need not load matplotlib, the simulator or the report
COMMANDS = {"collect": "collect", "correct": "correct", "demo": "demo", "evaluate": "evaluate", "export": "export",
            "fit": "fit", "fixtures": "fixtures", "info": "info", "predict": "predict", "report": "report",
            "serve": "serve", "tracker": "tracker", "warmup": "warmup"}


def main() -> None:
    cli()
