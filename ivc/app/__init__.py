"""The app layer: what each command does, as a function a script calls with an options object.

:func:`ivc.correct_file` (``ivc correct``) and :func:`ivc.predict_file` (``ivc predict``) read a file, run the
pipeline's stages on it and write the result in the input's format; they print nothing and report as they go
through a callback (:mod:`ivc.app.messages`). The command line only parses its options into
:class:`~ivc.app.correct.CorrectOptions` / :class:`~ivc.app.predict.PredictOptions`, calls them and prints.

Stage: above ``live``/``export``/``report`` (it reads ``collect``'s recording formats and sets up ``live``'s loop),
below ``cli``. Nothing is imported here, so that :mod:`ivc.app.paths` stays cheap for every command.
"""
