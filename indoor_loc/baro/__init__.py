"""The barometer: pressure -> relative height, floor-change events, floors as a discrete state."""
