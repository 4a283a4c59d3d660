"""The interface every LUT fitter implements, and the registry ``ivc fit --method`` chooses from.

A fitter is an estimator in the style of verde's gridders (docs/lut.md, "Adding a fitter"):

- it is configured in ``__init__`` (keyword parameters stored under the same names, one of them
  ``cv``, the :class:`~ivc.lut.cross_validation.BlockedKFold` it is scored, and may choose its
  own hyper-parameters, by);
- ``fit(samples, grid)`` learns the secondary field ``G`` (source frame, per unit of the
  source's excitation) from :class:`~ivc.lut.samples.FieldSamples` and returns ``self``;
  ``grid`` is the table's grid, which a grid-free fitter may ignore;
- ``predict(r)`` gives ``G`` (..., 3, 3) at positions ``r`` (..., 3) in metres, NaN where the
  fitter says nothing; ``tabulate(grid)`` gives the table's node values (nx, ny, nz, 3, 3);
- what it learned is in attributes with a trailing underscore, ``report_`` (a JSON-able dict
  for the fit report) among them; ``cross_validate(samples, grid)`` is its blocked
  cross-validation score (m), by :func:`~ivc.lut.cross_validation.cross_validate` unless the
  fitter has an exact shortcut.
"""

from __future__ import annotations

import inspect
from abc import ABC, abstractmethod
from collections.abc import Callable

import numpy as np

from ivc.errors import InputError
from ivc.lut.cross_validation import BlockedKFold, cross_validate
from ivc.lut.samples import FieldSamples
from ivc.table.grid import Grid

__all__ = ["FITTERS", "Fitter", "fit_table", "make_fitter", "register"]


class Fitter(ABC):
    """Base class of the LUT fitters. Subclasses set ``name`` and implement ``__init__`` and ``fit``, and ``predict``
    unless their fit leaves a callable model in ``model_``."""

    #: the method's name (``ivc fit --method NAME``)
    name: str = ""

    cv: BlockedKFold

    @classmethod
    def _parameter_names(cls) -> list[str]:
        parameters = inspect.signature(cls.__init__).parameters.values()
        return [p.name for p in parameters if p.name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]

    def get_params(self) -> dict:
        """The configuration: ``__init__``'s parameters and their values."""
        return {name: getattr(self, name) for name in self._parameter_names()}

    def describe(self) -> dict:
        """:meth:`get_params` as JSON-able values, with the method's name (recorded in the table's provenance)."""
        params = {}
        for key, value in self.get_params().items():
            params[key] = {"k": value.k, "block_frames": value.block_frames} if isinstance(value, BlockedKFold) \
                else value
        return {"method": self.name, **params}

    def clone(self) -> Fitter:
        """An unfitted fitter with the same configuration."""
        return type(self)(**self.get_params())

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.get_params().items())})"

    @abstractmethod
    def fit(self, samples: FieldSamples, grid: Grid, progress: Callable[[int], None] | None = None) -> Fitter:
        """Learn ``G`` from ``samples`` for a table on ``grid``; ``progress(n)`` is told of the work done
        (in :meth:`progress_units`). Returns ``self``."""

    def predict(self, positions: np.ndarray) -> np.ndarray:
        """``G`` (..., 3, 3) at ``positions`` (..., 3) m, NaN where the fit says nothing: by default the fitted
        model ``model_`` (a callable of positions) there."""
        self._check_fitted("model_")
        return self.model_(positions)

    def tabulate(self, grid: Grid) -> np.ndarray:
        """Node values (nx, ny, nz, 3, 3) of a table on ``grid``: by default the prediction at its nodes."""
        return self.predict(grid.nodes())

    def cross_validate(self, samples: FieldSamples, grid: Grid) -> float:
        """Blocked cross-validation score (m) of this configuration on ``samples``
        (:func:`ivc.lut.cross_validation.cross_validate`)."""
        return cross_validate(self, samples, grid, self.cv)

    @property
    def progress_label(self) -> str:
        """What a progress bar of :meth:`fit` says."""
        return f"fitting ({self.name})"

    def progress_units(self, samples: FieldSamples) -> int:
        """The total a progress bar of :meth:`fit` counts to (0: unknown)."""
        return 0

    def _check_fitted(self, attribute: str) -> None:
        if not hasattr(self, attribute):
            raise InputError(f"this {type(self).__name__} is not fitted yet: call fit(samples, grid) first")


#: fitters by method name
FITTERS: dict[str, type[Fitter]] = {}


def register(cls: type[Fitter]) -> type[Fitter]:
    """Class decorator: make a fitter available by its ``name`` (``make_fitter``, ``ivc fit --method``)."""
    if not cls.name:
        raise TypeError(f"{cls.__name__} needs a name")
    FITTERS[cls.name] = cls
    return cls


def make_fitter(method: str | Fitter, **params) -> Fitter:
    """A fitter from a method name and its parameters (a ready :class:`Fitter` is returned as it is)."""
    if isinstance(method, Fitter):
        if params:
            raise InputError("pass either a configured fitter or a method name with parameters, not both")
        return method
    _load_builtin()
    if method not in FITTERS:
        raise InputError(f"unknown fit method {method!r}; use one of {', '.join(FITTERS)}")
    return FITTERS[method](**params)


def _load_builtin() -> None:
    """Register the built-in fitters (their modules register on import)."""
    import ivc.lut.fit_adaptive
    import ivc.lut.fit_harmonic
    import ivc.lut.fit_poly
    import ivc.lut.fit_sources  # noqa: F401


def fit_table(fitter: Fitter, samples: FieldSamples, grid: Grid,
              progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, dict]:
    """Fit ``fitter`` to ``samples`` and tabulate it on ``grid``: node values (nx, ny, nz, 3, 3) and the fit
    report (the fitter's ``report_`` with its cross-validation score ``cv_rms_mm`` and ``cv_folds``)."""
    fitter.fit(samples, grid, progress=progress)
    report = dict(fitter.report_)
    report.update(cv_folds=fitter.cv.k, cv_rms_mm=1000 * fitter.cross_validate(samples, grid))
    return fitter.tabulate(grid), report
