"""The no-prediction baseline: show the latest measurement (what every predictor is compared with)."""

from __future__ import annotations

import numpy as np

from ivc.predict.base import Predictor, Stream, as_given, check_horizons, check_stream

__all__ = ["LastSample", "NoPrediction"]


class LastSample(Stream):
    """The live baseline: the latest valid measurement of each sensor, NaN where the last one was invalid."""

    def __init__(self, n_sensors: int):
        super().__init__(None, n_sensors)

    def update(self, q, valid=None, time=None):
        qs, ok = self._check_frame(q, valid)
        self.last = np.where(ok[:, None], qs, np.nan)

    def predict(self, horizon):
        return self.last.copy()


class NoPrediction(Predictor):
    """The baseline: show the latest measurement (the display lags by the horizon)."""

    name = "none"

    def __init__(self, rate_hz: float = 120.0):
        self.rate_hz = rate_hz

    def predict(self, q, horizons, valid=None, time=None):
        h = check_horizons(horizons)
        qs, _, single = check_stream(q, valid)  # invalid samples are NaN
        out = np.broadcast_to(qs, (len(h),) + qs.shape).copy()
        return as_given(out, single)

    def stream(self, n_sensors=1):
        return LastSample(n_sensors)
