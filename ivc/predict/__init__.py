"""Head-motion prediction (issue: prediction filters). So far: the generic discrete KF and EKF."""

from ivc.predict.kalman import ExtendedKalmanFilter, KalmanFilter

__all__ = ["ExtendedKalmanFilter", "KalmanFilter"]
