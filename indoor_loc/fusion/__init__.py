"""Fusion filters (seed 004 linear PDR Kalman filter, RTS smoother, EKF/UKF models). Pure numpy."""
