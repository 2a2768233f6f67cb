"""The paper's baseline: EKF update-error minimisation (Quraishi & Martinoli, §III)."""
from aqfg.ekf.estimator import UpdateErrorEstimator, fit_update_error

__all__ = ["UpdateErrorEstimator", "fit_update_error"]
