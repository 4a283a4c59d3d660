"""The HIGH_RESIDUAL test of a corrected signal, scaled to what the table and the tracker can explain (issue 38).

A corrected pose leaves the residual ``ρ = |M(r) − T S|_F / |S|_F`` (rms over the nine entries relative to the
signal's, ``ivc.linalg.relative_residual``). Two things make it non-zero at a right pose:

- the tracker's white noise ``σ`` per signal entry (absolute, ``ivc.lut.signal_noise``), ``9 σ²`` in all;
- the table's model error. The fit's blocked cross-validation measures it as a pose-equivalent RMS ``ε`` (m,
  ``fit["cv_rms_mm"]``): a field error ``δG`` moves the solved position by ``λ |δG|_F`` with
  ``λ = |r| / (3 |f_D(r)|_F)`` (``ivc.lut.samples``), so the field error behind ``ε`` is
  ``|δG|_F ≈ 3 ε |f_D(r)|_F / |r|``. (The score also holds the samples' own noise: the figure errs on the side
  of trusting.)

The six-parameter solve absorbs six of the nine entries' worth of both, so the expected residual of a right pose
is ``ρ₀ = √(3σ² + |δG|_F² / 3) / |S|_F``, and a pose is flagged when ``ρ > k ρ₀`` with ``k =``
:data:`RESIDUAL_SIGMAS`. The model error is not even over the volume (the cross-validation gives its RMS; at the
ball's edge nearest the metal it is several times that): on the built-in scenes' check poses (seed 0, 20,000-frame
sweeps) right poses reach ``ρ / ρ₀`` of 2 (default scene), 4.4 (cabinet, default fit) and 8.1 (cabinet, adaptive
fit: three poses at the ball's edge 6 cm above the ferrous part, 0.13-0.51 mm off), wrong ones (a solve on the
wrong branch) over 900. In a strong room (large ``ε``)
or far from the source (small ``|S|``) the limit widens by what the model and the noise explain, and a pose whose
residual says it is wrong (a wrong branch of the solve, a room that changed, the wrong hemisphere) still stands
out. A table whose fit record lacks either figure (an older table, a fit without
cross-validation, a session without static steps) keeps the fixed :data:`MAX_RESIDUAL`; an explicit
``max_residual`` is a fixed limit for every pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ivc import dipole
from ivc.errors import InputError
from ivc.table.grid import GridField
from ivc.table.lookup import LookupTable

__all__ = ["MAX_RESIDUAL", "RESIDUAL_SIGMAS", "ResidualGate"]

#: the fixed HIGH_RESIDUAL limit of rms(M − T S)/rms(S): an explicit ``max_residual``'s default, and the limit for
#: tables that record no model error or signal noise
MAX_RESIDUAL = 1e-3
#: how many times its expected residual (noise and model error together) a pose's residual may be
RESIDUAL_SIGMAS = 10.0


@dataclass(frozen=True)
class ResidualGate:
    """The HIGH_RESIDUAL limit of each pose. ``fixed``: one limit for every pose (explicit, or the fallback), or
    None when scaled by ``sigma`` (white noise per signal entry, signal units) and ``model_error`` (m,
    pose-equivalent RMS) with ``k`` = :data:`RESIDUAL_SIGMAS`; ``note`` says which and why."""

    fixed: float | None
    sigma: float | None = None
    model_error: float | None = None
    k: float = RESIDUAL_SIGMAS
    note: str = ""

    @classmethod
    def resolve(cls, table: LookupTable | GridField, max_residual: float | None = None,
                signal_noise: float | None = None) -> ResidualGate:
        """The gate for ``table``: the fixed limit ``max_residual`` when given; else scaled by ``signal_noise``
        (default: the noise the table's fit measured) and the table's cross-validated model error
        (``fit["cv_rms_mm"]``); else the fixed :data:`MAX_RESIDUAL`."""
        if max_residual is not None:
            if not max_residual > 0:  # NaN too; inf: no residual test
                raise InputError(f"max_residual must be a positive number (rms(M − T S)/rms(S)), got {max_residual}")
            return cls(float(max_residual), note=f"residual limit {float(max_residual):g} (max_residual)")
        fit = table.fit if isinstance(table, LookupTable) else {}
        sigma = signal_noise if signal_noise is not None else (
            table.signal_noise if isinstance(table, LookupTable) else None)
        cv = fit.get("cv_rms_mm")
        missing = [what for what, value in (("signal noise", sigma), ("cross-validated model error", cv))
                   if not (isinstance(value, int | float) and np.isfinite(value) and value > 0)]
        if missing:
            return cls(MAX_RESIDUAL, note=f"fixed residual limit {MAX_RESIDUAL:g}: the table records no "
                                          f"{' or '.join(missing)} (fit it again with this ivc)")
        model_error = float(cv) / 1000
        return cls(None, float(sigma), model_error,
                   note=f"residual limit {RESIDUAL_SIGMAS:g}x the expected residual of signal noise {float(sigma):.3g} "
                        f"and model error {1000 * model_error:.3g} mm (the table's cross-validation)")

    @property
    def scaled(self) -> bool:
        return self.fixed is None

    def expected(self, S: np.ndarray, position: np.ndarray) -> np.ndarray:
        """The expected relative residual ``ρ₀`` (N,) of right poses at ``position`` (N, 3) m with signals
        ``S`` (N, 3, 3) (module docstring); NaN where either is not finite."""
        norm_S = np.linalg.norm(S, axis=(1, 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            distance = np.linalg.norm(position, axis=1)
            primary = np.linalg.norm(dipole.field(np.where(np.isfinite(position), position, 1.0)), axis=(1, 2))
            model = 3 * self.model_error * primary / distance
            expected = np.sqrt(3 * self.sigma**2 + model**2 / 3) / norm_S
        return np.where(np.all(np.isfinite(position), axis=1), expected, np.nan)

    def limits(self, S: np.ndarray, position: np.ndarray) -> np.ndarray | float:
        """The residual limit of each pose (N,) (the fixed limit where a pose has none: no position came out)."""
        if self.fixed is not None:
            return self.fixed
        limit = self.k * self.expected(S, position)
        return np.where(np.isfinite(limit), limit, MAX_RESIDUAL)

    def describe(self) -> str:
        return self.note
