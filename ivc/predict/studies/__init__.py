"""Reproductions of the source papers' studies, apart from the product's predictors.

``compensator``: Adelstein, Jung & Ellis 2001's predictive-compensator optimisation (the
10-state EKF's process noise tuned by Powell's method, their Table 1), run by
``ivc predict --compensators``. ``evaluate``: the thesis's prediction-error metrics and
tables (docs/math.md §14), run by ``ivc predict``. ``frequency``: Azuma & Bishop 1995's
frequency-domain analysis of the linear predictors (docs/math.md §16). The predictors
themselves live in :mod:`ivc.predict`, which imports none of these.
"""

from ivc.predict.studies import compensator, evaluate, frequency

__all__ = ["compensator", "evaluate", "frequency"]
