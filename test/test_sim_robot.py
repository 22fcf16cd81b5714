"""Simulated differential-drive robots (indoor_loc/sim/robot.py): their odometry drifts like wheel
odometry, adding them changes nothing of the walkers, and they reach the bag and params."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.sim.building import sample_building
from indoor_loc.sim.robot import RobotParams
from indoor_loc.sim.scenario import SimConfig, simulate


@pytest.fixture(scope="module")
def runs():
    b = sample_building()
    return (simulate(b, SimConfig(walkers=1, robots=0, duration_s=120.0, seed=5)),
            simulate(b, SimConfig(walkers=1, robots=2, duration_s=120.0, seed=5)))


def _aligned_error(r) -> np.ndarray:
    m, o = r.motion, r.odom
    th0 = float(m.heading[0])
    c, s = np.cos(th0), np.sin(th0)
    x = m.body_xyz[0, 0] + c * o.pose[:, 0] - s * o.pose[:, 1]
    y = m.body_xyz[0, 1] + s * o.pose[:, 0] + c * o.pose[:, 1]
    return np.hypot(x - m.body_xyz[:, 0], y - m.body_xyz[:, 1])


def test_robots_drive_with_drifting_odometry_and_leave_the_walkers_alone(runs):
    alone, with_robots = runs
    w0, w1 = alone.walkers[0], with_robots.walkers[0]
    assert np.array_equal(w0.imu.acc, w1.imu.acc) and len(w0.scans) == len(w1.scans)
    assert [r.name for r in with_robots.robots] == ["robot1", "robot2"]
    for r in with_robots.robots:
        err = _aligned_error(r)
        assert err[0] == 0.0 and 0.02 < err[-1] < 10.0           # drifts, as wheel odometry does
        assert len(r.scans) > 20 and np.all(r.motion.floor == 0)
        assert np.all(np.diff(np.diagonal(r.odom.cov, axis1=1, axis2=2)[:, 2]) >= 0)   # growing covariance
    ideal = simulate(sample_building(), SimConfig(walkers=1, robots=1, duration_s=120.0, seed=5, robot=RobotParams(
        wheel_scale_std=0.0, wheel_base_err_std=0.0, slip_std=0.0, drift_walk=0.0))).robots[0]
    assert _aligned_error(ideal)[-1] < 0.6                          # error-free wheels: only the unseen lateral


def test_kidnapping_is_a_blind_jump(runs):
    r = simulate(sample_building(), SimConfig(walkers=1, robots=1, duration_s=120.0, seed=5,
                                              robot=RobotParams(kidnap_at_s=60.0))).robots[0]
    k = int(np.searchsorted(r.motion.t_ns, r.kidnap_ns))
    assert np.hypot(*(r.motion.body_xyz[k, :2] - r.motion.body_xyz[k - 1, :2])) >= 15.0
    assert np.hypot(*(r.odom.pose[k, :2] - r.odom.pose[k - 1, :2])) < 0.1   # the odometry saw nothing


def test_robots_reach_the_bag_and_their_params(runs, tmp_path):
    from indoor_loc.bag import bag_topics
    from indoor_loc.sim.write import node_params, write_bag
    _, run = runs
    topics = bag_topics([write_bag(run, tmp_path / "s.mcap") and tmp_path / "s.mcap"])
    assert {"/robot1/odom", "/robot1/imu", "/robot1/wifi/scan", "/robot1/ground_truth"} <= set(topics)
    assert "/robot1/imu/data_raw" not in topics                    # no stepometer input for a robot
    p = node_params(run, tmp_path, tmp_path / "g.yaml")
    assert p["/robot1/tll_pf"]["ros__parameters"]["motion_source"] == "odom"
    assert p["/**/backend_node"]["ros__parameters"]["motion_source"] == "any"
