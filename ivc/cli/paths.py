"""The commands' input and output checks: :mod:`ivc.app.paths` (the library's words, which the CLI's error
handler turns into its flags: ``overwrite=True`` is ``--force``)."""

from ivc.app.paths import check_output, input_and_output, refuse_inputs_as_outputs, same_file

__all__ = ["check_output", "input_and_output", "refuse_inputs_as_outputs", "same_file"]
