"""Reproductions of the source papers' studies, apart from the product's predictors.

``compensator``: Adelstein, Jung & Ellis 2001's predictive-compensator optimisation (the
10-state EKF's process noise tuned by Powell's method, their Table 1), run by
``ivc predict --compensators``. The predictors themselves live in :mod:`ivc.predict`.
"""

from ivc.predict.studies import compensator

__all__ = ["compensator"]
