"""Head-motion prediction: hide display lag by predicting orientation a horizon ahead (docs/math.md §10-§17).

Every predictor takes an orientation stream (unit quaternions, scalar first) at a known rate
and predicts it any number of seconds ahead, in batch (:meth:`Predictor.predict`) or live
(:meth:`Predictor.stream`). :data:`FILTERS` names them for ``ivc predict --filter``.
"""

from __future__ import annotations

from collections.abc import Callable

from ivc.predict.auto import AutoPredictor
from ivc.predict.base import Predictor, PredictorError, Stream
from ivc.predict.direct import DirectPredictor
from ivc.predict.dq import DQPredictor, dqekf_ca, dqekf_cv, mmdq2, mmdq3
from ivc.predict.hold import NoPrediction
from ivc.predict.linear import LinearPredictor, alpha_beta, kinematic, polynomial
from ivc.predict.mmae import MMAE
from ivc.predict.nasa import NasaEKF
from ivc.predict.qekf import QEKF
from ivc.predict.tuning import Tuning

#: name -> factory(rate_hz) of every orientation predictor
FILTERS: dict[str, Callable[[float], Predictor]] = {
    "auto": AutoPredictor,
    "none": NoPrediction,
    "direct": DirectPredictor,
    "dqekf-cv": dqekf_cv,
    "dqekf-ca": dqekf_ca,
    "mmdq2": mmdq2,
    "mmdq3": mmdq3,
    "q-ekf": QEKF,
    "mmae": MMAE,
    "poly1": lambda rate_hz=120.0: polynomial(rate_hz, 1),
    "poly2": lambda rate_hz=120.0: polynomial(rate_hz, 2),
    "alpha-beta": alpha_beta,
    "kinematic": kinematic,
    "nasa-ekf": NasaEKF,
}


#: the filter used when none is named (``ivc predict``, ``ivc correct --predict``): :mod:`ivc.predict.auto`
DEFAULT_FILTER = "auto"

#: the predictors :func:`ivc.predict.tuning.estimate` tunes (Himberg 2010's): measurement noise, and process noise
#: at the λ each model is defined by (the Q-EKF uses the CV model's, λ = 0.5, as with the thesis's values)
TUNABLE = ("q-ekf", "dqekf-cv", "dqekf-ca", "mmdq2", "mmdq3")


def make(name: str, rate_hz: float = 120.0, tuning: Tuning | None = None, horizon_s: float | None = None) -> Predictor:
    """The predictor called ``name`` (see :data:`FILTERS`) for a stream at ``rate_hz``.

    ``horizon_s`` (s, above 0): the horizon the live form of a predictor that learns from its own errors (``auto``,
    ``direct``) scores and learns at; the others predict any horizon alike and ignore it.

    With ``tuning``, the filters of :data:`TUNABLE` take their measurement and process noise from it
    instead of the thesis's tracker and head (Table 3, eq. 67, Table 10); the other filters have no
    such noise model and are made as without it.
    """
    if name not in FILTERS:
        raise PredictorError(f"unknown filter {name!r}; choose one of {', '.join(FILTERS)}")
    if tuning is None or name not in TUNABLE:
        if horizon_s and name in ("auto", "direct"):
            return FILTERS[name](rate_hz, horizon_s=horizon_s)
        return FILTERS[name](rate_hz)
    if not tuning.matches_rate(rate_hz):
        raise PredictorError(f"the tuning is for {tuning.rate_hz:g} Hz, the stream is at {rate_hz:g} Hz: "
                             "tune from a recording at the stream's rate")
    if name == "q-ekf":
        return QEKF(rate_hz, sigma_w=tuple(tuning.sigma_w("cv", 0.5)), sigma_v=tuple(tuning.sigma_q))
    return FILTERS[name](rate_hz, sigma_w=tuning.sigma_w, sigma_v=tuple(tuning.sigma_v_dq))


__all__ = ["AutoPredictor", "DEFAULT_FILTER", "DQPredictor", "DirectPredictor", "FILTERS", "LinearPredictor", "MMAE",
           "NasaEKF", "NoPrediction", "Predictor", "PredictorError", "QEKF", "Stream", "TUNABLE", "Tuning", "make"]
