"""What every orientation predictor offers: batch prediction of a recorded stream and a streaming form.

Shapes: a stream of orientations is ``(frames, 4)`` or ``(frames, sensors, 4)`` unit
quaternions (scalar first) sampled at ``rate_hz``; ``valid`` (same leading shape) marks the
samples to use (missing or bad samples are skipped and their predictions are NaN). A horizon
is in seconds and need not be a whole number of frames.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ivc.errors import PredictorError

FloatArray = NDArray[np.float64]

#: the longest horizon accepted (s); the thesis evaluates up to 117 ms, displays lag 50-100 ms
MAX_HORIZON = 1.0


@numba.njit(cache=True)
def _normalise_samples(q, ok, out):
    """out = q normalised where ok, NaN elsewhere; NaN samples become not ok (in place).

    Returns −1, or the flat index (frame · sensors + sensor) of the first usable sample whose
    norm is off 1 by more than 1e-3.
    """
    F, S = ok.shape
    for f in range(F):
        for s in range(S):
            n2 = q[f, s, 0] ** 2 + q[f, s, 1] ** 2 + q[f, s, 2] ** 2 + q[f, s, 3] ** 2
            if ok[f, s] and np.isfinite(n2):
                n = np.sqrt(n2)
                if abs(n - 1.0) > 1e-3:
                    return f * S + s
                for i in range(4):
                    out[f, s, i] = q[f, s, i] / n
            else:
                ok[f, s] = False
                out[f, s, :] = np.nan
    return -1


def check_stream(q: ArrayLike, valid: ArrayLike | None) -> tuple[FloatArray, NDArray[np.bool_], bool]:
    """(q as (F, S, 4), valid (F, S), whether the input had no sensor axis); NaN samples become invalid."""
    q = np.asarray(q, dtype=float)
    single = q.ndim == 2
    if single:
        q = q[:, None, :]
    if q.ndim != 3 or q.shape[-1] != 4:
        raise PredictorError(f"orientations must have shape (frames, 4) or (frames, sensors, 4), got {q.shape}")
    ok = np.ones(q.shape[:2], bool)
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if single and valid.ndim == 1:
            valid = valid[:, None]
        if valid.shape != q.shape[:2]:
            raise PredictorError(f"valid has shape {valid.shape}, expected {q.shape[:2]}")
        ok[:] = valid
    out = np.empty(q.shape)
    bad = _normalise_samples(np.ascontiguousarray(q), ok, out)
    if bad >= 0:
        f, s = divmod(bad, q.shape[1])
        raise PredictorError(f"orientation at frame {f}, sensor {s} is not a unit quaternion "
                             f"(norm {np.linalg.norm(q[f, s]):.6g}); pass unit quaternions [w, x, y, z]")
    q = out
    return q, ok, single


def as_given(out: FloatArray, single: bool) -> FloatArray:
    """``out`` (..., S, k) without its sensor axis when the input stream had none (frames, 4)."""
    return out[..., 0, :] if single else out


def check_horizons(horizons: float | Sequence[float]) -> FloatArray:
    """Horizons (s) as a 1-D array, each in [0, MAX_HORIZON]."""
    h = np.atleast_1d(np.asarray(horizons, dtype=float))
    if h.ndim != 1 or not np.all(np.isfinite(h)) or np.any(h < 0.0) or np.any(h > MAX_HORIZON):
        raise PredictorError(f"horizons must be finite, in [0, {MAX_HORIZON}] s; got {horizons}")
    return h


def check_rate(rate_hz: float) -> float:
    if not np.isfinite(rate_hz) or rate_hz <= 0.0:
        raise PredictorError(f"the sample rate must be a positive number of Hz, got {rate_hz}")
    return float(rate_hz)


class Stream(ABC):
    """A predictor running live on ``n_sensors`` sensors: feed each frame, ask for the pose at any horizon."""

    n_sensors: int

    def __init__(self, predictor: Predictor | None, n_sensors: int):
        self.predictor, self.n_sensors = predictor, int(n_sensors)
        self.last = np.full((self.n_sensors, 4), np.nan)  # the latest frame fed

    @abstractmethod
    def update(self, q: ArrayLike, valid: ArrayLike | None = None) -> None:
        """Feed one frame: q (sensors, 4); valid (sensors,) marks the samples to use."""

    @abstractmethod
    def predict(self, horizon: float) -> FloatArray:
        """Predicted orientations (sensors, 4) ``horizon`` s after the last frame; NaN where nothing is known."""

    def _check_frame(self, q: ArrayLike, valid: ArrayLike | None) -> tuple[FloatArray, NDArray[np.bool_]]:
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n_sensors, 4):
            raise PredictorError(f"a frame has shape ({self.n_sensors}, 4), got {q.shape}")
        qs, ok, _ = check_stream(q[None], None if valid is None else np.asarray(valid, dtype=bool)[None])
        return qs[0], ok[0]


class Predictor(ABC):
    """An orientation predictor for streams sampled at ``rate_hz``."""

    #: the name used by ``ivc predict --filter``
    name: str = ""
    rate_hz: float

    @property
    def tau(self) -> float:
        """Frame period (s)."""
        return 1.0 / self.rate_hz

    @abstractmethod
    def predict(self, q: ArrayLike, horizons: float | Sequence[float], valid: ArrayLike | None = None) -> FloatArray:
        """Predictions (H, F, [S,] 4): entry [h, k] is the orientation expected ``horizons[h]`` s after frame k,
        from frames 0..k only. NaN where the filter has no estimate yet or the frame is invalid."""

    @abstractmethod
    def stream(self, n_sensors: int = 1) -> Stream:
        """A fresh streaming instance for ``n_sensors`` sensors."""

    def rates(self, q: ArrayLike, valid: ArrayLike | None = None) -> FloatArray | None:
        """Estimated angular velocity (F, [S,] 3) rad/s per frame, or None if the predictor has none."""
        return None
