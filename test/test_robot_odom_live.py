"""tll_pf live over DDS with a robot's own odometry: the node in the robot's namespace with
``motion_source:=odom``, fed nav_msgs/Odometry at 20 Hz in the robot's own (rotated, shifted) odom
frame and WiFi fixes, publishes pf/pose on the robot's true path."""
from __future__ import annotations

import math
import sys

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from helpers_dds import Peer, child_env, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.graph import build_graph, save_graph
from indoor_loc.measurements import Fix
from indoor_loc.nodes.base import qos_profile
from msg_adapters.odom import odom_to_msg
from msg_adapters.pose import fix_to_msg, pose_from_msg

T0 = 10_000_000_000
SPEED = 0.8
RATE_HZ = 20


def truth(t_s: np.ndarray) -> np.ndarray:
    """The robot's true position at t_s (s): east along (0,0)-(30,0), then north to (30,20)."""
    d = np.minimum(SPEED * t_s, 50.0)
    return np.column_stack([np.minimum(d, 30.0), np.maximum(d - 30.0, 0.0)])


@pytest.mark.timeout(240)      # above the sum of the condition deadlines, not an expected duration
def test_tll_pf_on_robot_odometry_over_dds(ros_domain, tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry

    g = build_graph([0, 1, 2, 3], np.array([[0, 0], [30, 0], [30, 20], [0, 20]], float), [(0, 1), (1, 2), (2, 3)])
    gf = save_graph(g, tmp_path / "g.graph.yaml")
    proc = Peer([sys.executable, "-m", "indoor_loc.nodes.tll_pf_node", "--ros-args", "-r", "__ns:=/robot1",
                 "-p", f"graph_file:={gf}", "-p", "n_particles:=500", "-p", "motion_source:=odom"], env=child_env())
    try:
        with ros_node("probe") as (node, ex):
            poses: list = []
            node.create_subscription(PoseWithCovarianceStamped, "/robot1/pf/pose", poses.append,
                                     QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                                                durability=DurabilityPolicy.TRANSIENT_LOCAL))
            odom = node.create_publisher(Odometry, "/robot1/odom", qos_profile(Qos.RELIABLE))
            fix = node.create_publisher(PoseWithCovarianceStamped, "/robot1/wifi/fix", qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: odom.get_subscription_count() > 0 and fix.get_subscription_count() > 0,
                              60), proc.output()
            rng = np.random.default_rng(4)
            n = int(60 * RATE_HZ)
            t_s = np.arange(n) / RATE_HZ
            xy = truth(t_s)
            # the wheel odometry: 1 % scale error, in its own frame (rotated 0.8 rad, shifted), unknown covariance
            step = np.diff(xy, axis=0, prepend=xy[:1]) * 1.01
            heading = np.where(SPEED * t_s < 30.0, 0.0, math.pi / 2) + 0.8
            c, s = np.cos(0.8), np.sin(0.8)
            oxy = np.cumsum(step @ np.array([[c, s], [-s, c]]), axis=0) + [5.0, -3.0]
            for k in range(n):
                stamp = T0 + k * (1_000_000_000 // RATE_HZ)
                msg = odom_to_msg(stamp, "robot1/odom", "robot1/base_link", oxy[k, 0], oxy[k, 1], heading[k],
                                  np.zeros((3, 3)), SPEED, 0.0)
                msg.pose.covariance[0] = -1.0                  # "not given": the documented model is used
                odom.publish(msg)
                if k % (2 * RATE_HZ) == 0:                     # a WiFi fix every 2 s, 1 m per axis
                    f = xy[k] + rng.normal(0.0, 1.0, 2)
                    fix.publish(fix_to_msg(Fix(stamp, f, np.eye(2))))
                spin_until(ex, lambda: False, 0.25 / RATE_HZ)    # 4x real time, as a replay would
            end = T0 + (n - 1) * (1_000_000_000 // RATE_HZ)
            assert spin_until(ex, lambda: any(pose_from_msg(p).stamp_ns >= end - 2_000_000_000 for p in poses), 60), \
                proc.output()
        est = [pose_from_msg(p) for p in poses]
        st = np.array([e.stamp_ns for e in est])
        exy = np.array([e.xy for e in est])
        late = st >= T0 + 10_000_000_000                        # after the first 10 s (the start-up)
        err = np.hypot(*(exy[late] - truth((st[late] - T0) * 1e-9)).T)
        assert len(est) > 3 * 30                                # a pose per increment, not only per fix
        assert err.mean() < 1.0 and np.percentile(err, 95) < 2.5, (err.mean(), np.percentile(err, 95))
    finally:
        proc.stop()
