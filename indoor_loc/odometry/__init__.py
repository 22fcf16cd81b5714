"""A robot's own odometry as the motion input of the estimators (:mod:`indoor_loc.odometry.increments`)."""
