"""Particle filtering on building graphs (pure numpy): the TLL particle filter and its smoother."""
