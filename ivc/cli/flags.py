"""The library's keyword arguments in its messages, said as the command line's flags.

A library message names the keyword a Python caller passes (``pass overwrite=True to replace it``); where the
command line shows that message, :func:`cli_words` rewrites each keyword as the flag that sets it (``pass --force
to replace it``). ``KEYWORD=VALUE`` becomes ``--flag VALUE``; a boolean keyword written ``KEYWORD=True``, or a
keyword with no value after its ``=``, becomes the bare flag. The mapping is one table, with the few keywords whose
flag differs between commands.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator

#: keyword -> flag, for every command
FLAGS = {
    "overwrite": "--force",
    "force": "--force",
    "keep": "--keep",
    "tune": "--tune",
    "tune_from": "--tune-from",
    "predictor": "--predict",
    "precision": "--precision",
    "max_precision": "--max-precision",
    "signal_noise": "--signal-noise",
    "max_residual": "--max-residual",
    "max_error": "--max-error-mm",
    "max_refinements": "--max-refinements",
    "max_frames": "--max-frames",
    "hemisphere": "--hemisphere",
    "solver": "--solver",
    "tracker_model": "--tracker-model",
    "unit": "--unit",
    "length_unit": "--unit",
    "sensors": "--sensor",
    "output": "-o",
    "plot": "--plot",
    "allow_corrected": "--allow-corrected",
    "rate_hz": "--rate",
    "sample_rate_hz": "--rate",
}

#: command -> {keyword: flag} where a command names an option otherwise
COMMAND_FLAGS = {
    "correct": {"rate_hz": "--rate-hz"},
    "demo": {"folder": "--keep"},
    "fit": {"spacing": "--grid"},
    "collect": {"sensors": "--sensors"},
    "serve": {"sensors": "--sensors"},
    "predict": {"unit": "--import-unit"},
}

_KEYWORD = re.compile(r"(?<![\w./\\-])([a-z][a-z0-9_]*)=(True\b)?")


def cli_words(text: str, command: str | None = None) -> str:
    """``text`` with each known ``keyword=`` said as the flag of ``command`` (unknown keywords stay as they are)."""
    flags = {**FLAGS, **COMMAND_FLAGS.get(command or "", {})}

    def flag(match: re.Match) -> str:
        name, true = match.group(1), match.group(2)
        if name not in flags:
            return match.group(0)
        bare = true or match.end() == len(text) or text[match.end()] in " ),;:"  # no value follows
        return flags[name] if bare else f"{flags[name]} "

    return _KEYWORD.sub(flag, text)


def echo_report(command: str):
    """The ``report(kind, text)`` of an app function, printed as the command's lines (:mod:`ivc.app.messages`):
    results on stdout, warnings and notes on stderr, each keyword said as the command's flag."""
    import click

    from ivc.app.messages import INFO

    def report(kind: str, text: str) -> None:
        text = cli_words(text, command)
        click.echo(text if kind == INFO else f"{kind}: {text}", err=kind != INFO)

    return report


@contextlib.contextmanager
def usage_errors(command: str) -> Iterator[None]:
    """Options an app function refuses (:class:`~ivc.errors.OptionsError`) as the command's usage error."""
    import click

    from ivc.errors import OptionsError

    try:
        yield
    except OptionsError as error:
        raise click.UsageError(cli_words(str(error), command)) from None
