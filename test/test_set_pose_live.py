"""initialpose and ~/set_pose (nav_msgs/srv/SetMap) on every estimator over DDS: each restarts at the
pose with its covariance honoured; a request carrying a map is refused."""
from __future__ import annotations

import sys

import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy

from helpers_dds import Peer, child_env, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.nodes.base import qos_profile
from msg_adapters.pose import pose_from_msg, pose_to_msg
from robot_walk import RobotWalk

CASES = {
    "pf": ("indoor_loc.nodes.tll_pf_node", "/alice/tll_pf/set_pose", "/alice/pf/pose", []),
    "pdr_kf": ("indoor_loc.nodes.pdr_kf_node", "/alice/pdr_kf_node/set_pose", "/alice/pdr_kf/pose", []),
    "backend": ("indoor_loc.nodes.backend_node", "/backend_node/alice/set_pose", "/backend/alice/pose",
                ["-p", "users:=[alice]", "-p", "wifi_source:=fix"]),
}


@pytest.mark.timeout(240)
@pytest.mark.parametrize("which", sorted(CASES))
def test_initialpose_and_set_pose(which, ros_domain, tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.srv import SetMap

    module, service, pose_topic, extra = CASES[which]
    args = ["-r", "__ns:=/alice"] if which != "backend" else []
    if which == "pf":
        gf = RobotWalk(duration_s=10.0).save_graph(tmp_path / "g.graph.yaml")
        extra = ["-p", f"graph_file:={gf}", "-p", "n_particles:=2000"]
    proc = Peer([sys.executable, "-m", module, "--ros-args", *args, *extra], env=child_env())
    # points on the sample building's ground-floor corridor (the pf keeps its particles on the graph)
    p1, p2 = np.array([8.0, 10.0]), np.array([32.0, 10.0])
    try:
        with ros_node("pose_setter") as (node, ex):
            poses: list = []
            node.create_subscription(PoseWithCovarianceStamped, pose_topic, poses.append,
                                     QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                                durability=DurabilityPolicy.VOLATILE))
            init = node.create_publisher(PoseWithCovarianceStamped, "/alice/initialpose", qos_profile(Qos.RELIABLE))
            cli = node.create_client(SetMap, service)
            assert cli.wait_for_service(timeout_sec=60), proc.output()
            assert spin_until(ex, lambda: init.get_subscription_count() > 0 and node.count_publishers(pose_topic) > 0,
                              60), proc.output()
            # 1. the initialpose topic, a wide covariance
            init.publish(pose_to_msg(5_000_000_000, p1, 0.0, np.diag([2.0, 2.0]), yaw_var=0.1))
            assert spin_until(ex, lambda: bool(poses), 30), proc.output()
            a = pose_from_msg(poses[-1])
            # 2. the service, a narrow covariance
            req = SetMap.Request()
            req.initial_pose = pose_to_msg(6_000_000_000, p2, 0.0, np.diag([0.04, 0.04]), yaw_var=0.1)
            n = len(poses)
            fut = cli.call_async(req)
            assert spin_until(ex, fut.done, 30) and fut.result().success, proc.output()
            assert spin_until(ex, lambda: len(poses) > n, 30), proc.output()
            b = pose_from_msg(poses[-1])
            # 3. a map in the request: refused, nothing restarts
            bad = SetMap.Request()
            bad.initial_pose = pose_to_msg(7_000_000_000, p1, 0.0, np.diag([0.04, 0.04]), yaw_var=0.1)
            bad.map.info.width = bad.map.info.height = 2
            bad.map.data = [0, 0, 0, 0]
            n = len(poses)
            fut = cli.call_async(bad)
            assert spin_until(ex, fut.done, 30) and not fut.result().success, proc.output()
            assert not spin_until(ex, lambda: len(poses) > n, 1.0)
    finally:
        proc.stop()
    tol = 1.0 if which == "pf" else 0.05               # the pf keeps its particles on the graph's links
    assert np.linalg.norm(a.xy - p1) < tol and np.linalg.norm(b.xy - p2) < tol, (a.xy, b.xy)
    # the covariance is honoured: the wide start is wider than the narrow one, by about their ratio
    va, vb = np.trace(a.cov_xy), np.trace(b.cov_xy)
    assert va > 5 * vb, (va, vb)
