"""What every orientation predictor offers: batch prediction of a recorded stream and a streaming form.

Shapes: a stream of orientations is ``(frames, 4)`` or ``(frames, sensors, 4)`` unit
quaternions (scalar first) at times ``time`` (frames,) s, or sampled at ``rate_hz`` when no
times are given; ``valid`` (same leading shape) marks the samples to use (missing or bad samples
are skipped and their predictions are NaN). A horizon is in seconds and need not be a whole number
of frames. Repeated samples and gaps follow :mod:`ivc.predict.timing`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ivc.errors import PredictorError
from ivc.predict.timing import MAX_GAP_S, check_stream, check_time, repeats, restarts

FloatArray = NDArray[np.float64]

#: the longest horizon accepted (s); the thesis evaluates up to 117 ms, displays lag 50-100 ms
MAX_HORIZON = 1.0


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
    #: restarts at gaps so far (summed over the sensors; every sensor at once for a fixed-rate design)
    restarts: int = 0

    def __init__(self, predictor: Predictor | None, n_sensors: int):
        self.predictor, self.n_sensors = predictor, int(n_sensors)
        self.last = np.full((self.n_sensors, 4), np.nan)  # the latest frame fed

    @abstractmethod
    def update(self, q: ArrayLike, valid: ArrayLike | None = None, time: float | None = None) -> None:
        """Feed one frame: q (sensors, 4); valid (sensors,) marks the samples to use; ``time`` (s) its time stamp
        (None: one nominal frame period after the previous frame)."""

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
    def predict(self, q: ArrayLike, horizons: float | Sequence[float], valid: ArrayLike | None = None,
                time: ArrayLike | None = None) -> FloatArray:
        """Predictions (H, F, [S,] 4): entry [h, k] is the orientation expected ``horizons[h]`` s after frame k,
        from frames 0..k only. NaN where the filter has no estimate yet or the frame is invalid. ``time`` (F,) s:
        the frames' time stamps (None: 1 / rate_hz apart)."""

    #: the live form's class, which :meth:`stream` makes (a subclass sets it or overrides :meth:`stream`)
    stream_type: ClassVar[type[Stream]]

    def stream(self, n_sensors: int = 1) -> Stream:
        """A fresh streaming instance for ``n_sensors`` sensors."""
        return self.stream_type(self, n_sensors)

    def rates(self, q: ArrayLike, valid: ArrayLike | None = None) -> FloatArray | None:
        """Estimated angular velocity (F, [S,] 3) rad/s per frame, or None if the predictor has none."""
        return None


class StreamClock:
    """A live stream's time keeping: the frame's dt, and the last time each sensor had a valid sample."""

    def __init__(self, rate_hz: float, n_sensors: int):
        self.rate_hz, self.now, self.frames = rate_hz, None, 0
        self.last_valid = np.full(n_sensors, -np.inf)

    def tick(self, time: float | None) -> float:
        """dt (s) since the previous frame; refuses a time that does not move forward. Without a time stamp,
        frame n is at n / rate_hz, as :func:`ivc.predict.timing.check_time` has it for a batch."""
        self.frames += 1
        if time is None:
            before = self.now
            self.now = (self.frames - 1) / self.rate_hz
            return 0.0 if before is None else self.now - before
        t = float(time)
        if not np.isfinite(t) or (self.now is not None and t <= self.now):
            raise PredictorError(f"frame time {t!r} s does not come after the previous frame's ({self.now!r} s): "
                                 "feed frames in time order, without repeated time stamps")
        dt = 0.0 if self.now is None else t - self.now
        self.now = t
        return dt

    def advance(self, time: float | None, ok: NDArray[np.bool_], max_gap_s: float) -> NDArray[np.bool_]:
        """Tick to the frame at ``time`` and return the sensors (S,) whose valid sample ends a gap longer
        than ``max_gap_s`` since their last valid one (they restart); ``last_valid`` moves to now for the
        sensors valid in this frame (``ok``)."""
        self.tick(time)
        gap = ok & (self.now - self.last_valid > max_gap_s) & np.isfinite(self.last_valid)
        self.last_valid = np.where(ok, self.now, self.last_valid)
        return gap


class FixedRateStream(Stream):
    """The live form of a :class:`FixedRatePredictor`: drops repeats, restarts after a gap (every sensor)."""

    def __init__(self, predictor: FixedRatePredictor, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.inner = predictor._stream_uniform(n_sensors)
        self.clock = StreamClock(predictor.rate_hz, n_sensors)
        self.previous = np.full((self.n_sensors, 4), np.nan)  # each sensor's last valid sample
        self.restarts = 0

    def update(self, q, valid=None, time=None):
        qs, ok = self._check_frame(q, valid)
        if np.any(self.clock.advance(time, ok, self.predictor.max_gap_s)):
            self.inner = self.predictor._stream_uniform(self.n_sensors)
            self.restarts += 1
        same = ok & np.all(qs == self.previous, axis=1)
        self.previous = np.where(ok[:, None], qs, self.previous)
        self.inner.update(qs, ok & ~same)
        self.last = self.inner.last

    def predict(self, horizon):
        return self.inner.predict(horizon)


class FixedRatePredictor(Predictor):
    """A predictor designed for one sample rate (its gains or transition matrices are fixed at ``rate_hz``).

    On a stream with time stamps it follows :mod:`ivc.predict.timing` as far as a fixed-rate design can:
    exact repeats are dropped (treated as missing frames: no prediction there), and a gap longer than
    ``max_gap_s`` restarts the filter; the steps in between are taken as 1 / rate_hz. Subclasses implement
    :meth:`_predict_uniform` and :meth:`_stream_uniform`.
    """

    max_gap_s: float = MAX_GAP_S

    @abstractmethod
    def _predict_uniform(self, q: FloatArray, horizons, valid: NDArray[np.bool_]) -> FloatArray:
        """Predictions (H, F, S, 4) of a stream (F, S, 4) sampled at rate_hz."""

    @abstractmethod
    def _stream_uniform(self, n_sensors: int) -> Stream:
        """The live form at rate_hz."""

    def predict(self, q, horizons, valid=None, time=None):
        check_horizons(horizons)
        qs, ok, single = check_stream(q, valid)
        t = check_time(time, qs.shape[0], self.rate_hz)
        use = ok & ~repeats(qs, ok)
        cuts = np.flatnonzero(np.any(restarts(t, ok, self.max_gap_s), axis=1))
        bounds = [0, *cuts.tolist(), qs.shape[0]]
        parts = [self._predict_uniform(qs[a:b], horizons, use[a:b]) for a, b in zip(bounds[:-1], bounds[1:],
                                                                                     strict=True) if b > a]
        return as_given(np.concatenate(parts, axis=1), single)

    #: the live form: repeats dropped, a restart after a gap
    stream_type = FixedRateStream


class TimedStepStream(Stream):
    """The live form of a :class:`FixedRatePredictor` that can also step over the actual time between frames: fed
    time stamps, :meth:`_step` per frame over them; fed none (decided at the first frame), the fixed-rate stream
    (:class:`FixedRateStream`, in ``inner``), as the batch without times. Subclasses set up their state in
    ``__init__`` and implement :meth:`_step` and :meth:`_show`."""

    def __init__(self, predictor: FixedRatePredictor, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.inner: Stream | None = None
        self.clock = StreamClock(predictor.rate_hz, n_sensors)
        self.previous = np.full((self.n_sensors, 4), np.nan)  # each sensor's last valid sample
        self.ok = np.zeros(self.n_sensors, bool)
        self._restarts = 0

    @property
    def restarts(self) -> int:
        return self.inner.restarts if self.inner is not None else self._restarts

    @abstractmethod
    def _step(self, qs: FloatArray, ok: NDArray[np.bool_], new: NDArray[np.bool_], gap: NDArray[np.bool_],
              now: float) -> None:
        """Take the frame qs (S, 4) at time ``now`` s: ``ok`` its valid samples, ``new`` those that are not a
        repeat of the sensor's last, ``gap`` the sensors that restart after a gap."""

    @abstractmethod
    def _show(self, horizon: float) -> FloatArray:
        """Predicted orientations (S, 4) ``horizon`` s after the last frame (checked), NaN where not ``ok``."""

    def update(self, q, valid=None, time=None):
        if self.inner is None and time is None and self.clock.now is None:
            self.inner = FixedRateStream(self.predictor, self.n_sensors)
        if self.inner is not None:
            self.inner.update(q, valid, time)
            self.last = self.inner.last
            return
        qs, ok = self._check_frame(q, valid)
        gap = self.clock.advance(time, ok, self.predictor.max_gap_s)
        self._restarts += int(gap.sum())
        new = ok & ~np.all(qs == self.previous, axis=1)
        self.previous = np.where(ok[:, None], qs, self.previous)
        self._step(qs, ok, new, gap, self.clock.now)
        self.ok, self.last = ok, qs

    def predict(self, horizon):
        if self.inner is not None:
            return self.inner.predict(horizon)
        return self._show(float(check_horizons(horizon)[0]))
