"""Fusion filters (Raitoharju et al. 2015 linear PDR Kalman filter, RTS smoother, EKF/UKF models). Pure numpy."""
