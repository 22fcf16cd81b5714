"""map -> odom over DDS: tll_pf in a namespace, fed a simulated walker's odometry (its own drifting
``alice/odom`` frame) and WiFi-like fixes, broadcasts the correction on /tf (tf2_msgs/TFMessage,
future-dated by transform_tolerance) and on pf/map_odom (latched); a tf user's chain
map -> alice/odom -> alice/base_link matches the ground truth within the filter's error."""
from __future__ import annotations

import sys

import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy

from helpers_dds import Peer, child_env, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.nodes.base import qos_profile
from indoor_loc.pipeline.map_odom import OdomTrack, compose
from msg_adapters.tf import pose_yaw_var, transform_from_msg
from robot_walk import RobotWalk

TOLERANCE_S = 0.5


@pytest.mark.timeout(240)
def test_tf_chain_matches_ground_truth(ros_domain, tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
    from nav_msgs.msg import Odometry
    from tf2_msgs.msg import TFMessage

    w = RobotWalk(duration_s=30.0)
    gf = w.save_graph(tmp_path / "g.graph.yaml")
    proc = Peer([sys.executable, "-m", "indoor_loc.nodes.tll_pf_node", "--ros-args", "-r", "__ns:=/alice",
                 "-p", f"graph_file:={gf}", "-p", "n_particles:=500", "-p", f"transform_tolerance:={TOLERANCE_S}"],
                env=child_env())
    try:
        with ros_node("tf_user") as (node, ex):
            tfs: list = []
            poses: list = []
            latched: list = []
            node.create_subscription(TFMessage, "/tf", tfs.append, QoSProfile(depth=500,
                                                                                reliability=ReliabilityPolicy.RELIABLE))
            node.create_subscription(PoseWithCovarianceStamped, "/alice/pf/pose", poses.append,
                                     QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE))
            pubs = {"pdr/odom": node.create_publisher(Odometry, "/alice/pdr/odom", qos_profile(Qos.RELIABLE)),
                    "wifi/fix": node.create_publisher(PoseWithCovarianceStamped, "/alice/wifi/fix",
                                                      qos_profile(Qos.RELIABLE))}
            assert spin_until(ex, lambda: all(p.get_subscription_count() > 0 for p in pubs.values())
                              and node.count_publishers("/tf") > 0, 60), proc.output()
            fixed = False
            for _, topic, msg in w.messages():
                before = len(poses)
                pubs[topic].publish(msg)
                fixed = fixed or topic == "wifi/fix"
                if topic == "pdr/odom" and fixed:     # paced by the filter (a loaded machine): each hop, a pose
                    spin_until(ex, lambda n=before: len(poses) > n, 5.0)
                else:
                    spin_until(ex, lambda: False, 0.01)
            n_odom = len(w.odom)
            assert spin_until(ex, lambda: len(tfs) >= n_odom - 5, 90), (len(tfs), proc.output())
            # a late joiner gets the newest correction from the latched topic
            node.create_subscription(TransformStamped, "/alice/pf/map_odom", latched.append, qos_profile(Qos.LATCHED))
            assert spin_until(ex, lambda: bool(latched), 20), proc.output()
            newest = transform_from_msg(latched[-1])[0] + int(TOLERANCE_S * 1e9)
            assert spin_until(ex, lambda: newest in {transform_from_msg(m.transforms[0])[0] for m in tfs}, 20)
    finally:
        proc.stop()
    track = OdomTrack()
    for s, p in w.odom:
        track.add(s, p, "alice/odom")
    pose_at = {pose_yaw_var(m)[0]: pose_yaw_var(m)[2] for m in poses}
    errs, est_errs = [], []
    for m in tfs:
        assert len(m.transforms) == 1
        stamp, parent, child, c = transform_from_msg(m.transforms[0])
        assert (parent, child) == ("map", "alice/odom")
        t = stamp - int(TOLERANCE_S * 1e9)                       # future-dated as nav2_amcl does
        assert t in pose_at, "each /tf correction is at an estimate's stamp"
        chain = compose(c, track.at(t))                          # map -> odom -> base_link at t
        truth = w.truth_at(t)
        errs.append(float(np.hypot(*(np.array(chain[:2]) - truth))))
        est_errs.append(float(np.hypot(*(np.array(pose_at[t][:2]) - truth))))
    bad = [(i, e, f) for i, (e, f) in enumerate(zip(errs, est_errs)) if abs(e - f) > 1e-6]
    assert not bad, (bad, len(errs))                             # the chain is exactly the estimate ...
    assert np.mean(errs) < 1.5 and np.percentile(errs, 95) < 4.0  # ... whose error the filter's is
    assert newest == max(transform_from_msg(m.transforms[0])[0] for m in tfs)   # the topic's: the newest
