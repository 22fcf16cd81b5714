"""Simulator: a building with access points, walkers with phones (IMU, magnetometer, WiFi scans),
ground truth, written as MCAP bags in the message contract plus a radio map, the building graph
and a params.yaml (``indoor-loc sim``).

Pure core: :mod:`~indoor_loc.sim.building`, :mod:`~indoor_loc.sim.rf`, :mod:`~indoor_loc.sim.walker`,
:mod:`~indoor_loc.sim.scenario`; files and bags: :mod:`~indoor_loc.sim.write`.
"""
