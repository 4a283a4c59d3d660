"""The precision part of the trust test, shared by the signal and the pose-only correction.

Every corrected pose carries its predicted precision (RMS position error, m, and orientation error, rad,
of that single frame, from the tracker's white signal noise; :mod:`ivc.pose.precision`) wherever ivc
knows the noise: the table's fit measures it on the session's static steps (``ivc.lut.signal_noise``,
from the signals, or from the reported poses of a pose-only session), or the user gives it.

A pose predicted less precise than the limit is flagged LOW_PRECISION. The default limit,
:data:`MAX_PRECISION` = 0.8 mm RMS, is what makes the trusted flag a bound whatever the error's shape:
a single-frame error that is Gaussian with 3-D RMS ``p ≤ 0.8 mm`` is, even in the worst case where all
of its variance lies along one direction (far from the source the range is much less certain than the
bearing), more than 2 mm off with probability 1.2 % (2.5 deviations) and more than 5 mm off with
4e-10 (6.25 deviations); isotropic, 0.03 % and 3e-25. Most trusted poses sit far below the limit
(docs/trust.md measures both). ``max_precision=None`` turns the gate off; a number replaces the limit.

The noise is not all that moves a signal's pose: where the table is off (beside metal it cannot follow, close
to the source where a tiny noise meets its error), the pose is off by more than the noise predicts. A pose solved
from a signal says so itself, through the part of its residual the solve cannot absorb (three of the nine
entries' worth): :func:`residual_widening` widens its predicted precision where that residual's variance is more
than :data:`RESIDUAL_EXCESS` times what the noise explains. A reported pose has no such residual (the map is
inverted exactly); its prediction holds the table's measured error instead (``PoseCorrector.map_error``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ivc.correct.flags import LOW_PRECISION
from ivc.errors import InputError
from ivc.table.grid import GridField
from ivc.table.lookup import LookupTable

#: the default limit (m) of a trusted pose's predicted RMS position error
MAX_PRECISION = 0.8e-3
#: a signal noise per entry at or above this (normalised dipole units: the signal's own size 1 m from the
#: source) is no tracker's
MAX_SIGNAL_NOISE = 1.0
#: ``max_precision`` of a corrector that uses :data:`MAX_PRECISION` where the noise is known (no gate elsewhere)
DEFAULT = "default"
#: how many times the noise's share the variance of a signal pose's residual must be before its predicted precision
#: is widened (:func:`residual_widening`). Noise alone passes 2 with probability 0.11 (three degrees of freedom)
RESIDUAL_EXCESS = 2.0


def residual_widening(residual: np.ndarray, S: np.ndarray, sigma: float) -> np.ndarray:
    """The factor (N,) ≥ 1 by which the noise-only precision of poses solved from signal matrices ``S`` (N, 3, 3)
    widens, from their relative residuals ``residual`` (N,) = rms(M − T S)/rms(S) and the white noise ``sigma`` per
    entry: with ``χ² = (ρ |S|_F)² / (3 σ²)``, the residual's variance over what the noise leaves once the
    six-parameter solve has absorbed its part, the factor is ``√(χ² / RESIDUAL_EXCESS)`` where that exceeds 1 (the
    a-posteriori variance factor of a least-squares fit, taken only where the residual says the model is off
    by more than the noise), else 1. NaN residuals give 1."""
    scale = np.linalg.norm(np.asarray(S, float).reshape(-1, 9), axis=1)
    with np.errstate(invalid="ignore"):
        excess = (np.asarray(residual, float) * scale) ** 2 / (3.0 * sigma ** 2 * RESIDUAL_EXCESS)
    return np.sqrt(np.where(excess > 1.0, excess, 1.0))


def _positive(name: str, value: float) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a positive number (or None), got {value!r}") from None
    if not (np.isfinite(number) and number > 0):
        raise InputError(f"{name} must be a positive number (or None), got {value}")
    return number


@dataclass(frozen=True)
class PrecisionGate:
    """How a corrector predicts and gates precision.

    ``sigma``: the tracker's white noise per signal entry (signal units; None: precision is not predicted);
    ``limit`` (m): poses predicted less precise are flagged LOW_PRECISION (None: no gate); ``note``: why
    precision is not predicted or not gated, in words for the output (None when both are on by default)."""

    sigma: float | None
    limit: float | None
    note: str | None = None

    @classmethod
    def resolve(cls, table: LookupTable | GridField, precision: bool = True,
                max_precision: float | str | None = DEFAULT, signal_noise: float | None = None) -> PrecisionGate:
        """The gate for ``table``: noise ``signal_noise`` (default: the one the table's fit measured), limit
        ``max_precision`` (m; :data:`DEFAULT`: :data:`MAX_PRECISION` where the noise is known; None: no gate).
        ``precision`` False predicts nothing unless a limit is given. A numeric limit without a known noise is
        refused (:class:`~ivc.errors.InputError`)."""
        explicit = max_precision is not None and not (isinstance(max_precision, str) and max_precision == DEFAULT)
        limit = _positive("max_precision", max_precision) if explicit else None
        sigma = None if signal_noise is None else _positive("signal_noise", signal_noise)
        if sigma is not None and sigma >= MAX_SIGNAL_NOISE:
            raise InputError(f"signal_noise={sigma:g} is not a tracker's noise: signals are in normalised dipole "
                             f"units (the field 1 m from the source is about 1), where trackers' noise per entry is "
                             f"1e-5 to 1e-2; give the noise in those units (the table's fit measures it)")
        if not (precision or explicit or sigma is not None):
            return cls(None, None, "precision not predicted (precision=False)")
        if sigma is None:
            sigma = table.signal_noise if isinstance(table, LookupTable) else None
        if sigma is None:
            if explicit:
                raise InputError("the table records no signal noise (fitted by an older ivc, or from a session "
                                 "without static steps): give the tracker's noise per signal entry "
                                 "(signal_noise=NOISE) to gate on precision")
            return cls(None, None, "precision not predicted: the table records no signal noise (fit it again "
                                   "with this ivc, or give signal_noise=NOISE)")
        if max_precision is None:
            return cls(sigma, None, "no precision gate (max_precision=None): trusted poses may be as imprecise as "
                                    "the tracker's noise makes them")
        return cls(sigma, limit if explicit else MAX_PRECISION)

    @property
    def predicts(self) -> bool:
        return self.sigma is not None

    def apply(self, precision: np.ndarray, flags: np.ndarray, usable: np.ndarray) -> None:
        """Flag (LOW_PRECISION, in place) the ``usable`` samples whose predicted position precision (m) is over
        the limit or unknown (NaN, inf: the measurement does not fix the pose)."""
        if self.limit is not None:
            flags[~(precision <= self.limit) & usable] |= LOW_PRECISION

    def describe(self) -> str:
        """One line for the output: the limit, or why there is none."""
        if self.note:
            return self.note
        default = " (the default)" if self.limit == MAX_PRECISION else ""
        return (f"precision gate: poses predicted less precise than {1000 * self.limit:g} mm RMS are flagged (16)"
                f"{default}")
