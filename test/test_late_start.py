"""A node that joins a replay late says how many messages it missed: WARN in its log, and
``missed_at_start.<topic>`` (and ``lost.<topic>``, a WARN) in ``/diagnostics``."""
from __future__ import annotations

import sys
import time

import pytest

from helpers_dds import Peer, child_env, ros_node, spin_until


@pytest.mark.timeout(120)
def test_a_replay_started_before_the_node_matched_is_counted_and_warned(ros_domain):
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu

    from indoor_loc.contract import Qos
    from indoor_loc.nodes.qos import qos_profile
    from msg_adapters.diagnostics import diagnostics_from_msg
    from msg_adapters.time import stamp_from_ns

    with ros_node("late_player") as (node, ex):
        pub = node.create_publisher(Imu, "/late/imu/data_raw", QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        got: list = []
        node.create_subscription(DiagnosticArray, "/diagnostics",
                                 lambda m: got.extend(s for n, s in diagnostics_from_msg(m).items()
                                                      if n == "/late/imu_node"), qos_profile(Qos.RELIABLE))

        def imu() -> Imu:
            m = Imu()
            m.header.stamp = stamp_from_ns(time.time_ns())
            m.header.frame_id = "late/imu_link"
            m.linear_acceleration.z = 9.81
            m.orientation_covariance[0] = -1.0
            return m
        for _ in range(30):                  # nobody listens yet: a replay started too early
            pub.publish(imu())
        proc = Peer([sys.executable, "-m", "indoor_loc.nodes.imu_node", "--ros-args", "-r", "__ns:=/late",
                     "-p", "sensor_reliability:=reliable"], env=child_env())
        try:
            assert spin_until(ex, lambda: pub.get_subscription_count() > 0, 60), proc.output()
            spin_until(ex, lambda: False, 1.0)
            for _ in range(40):
                pub.publish(imu())
                spin_until(ex, lambda: False, 0.01)
            assert spin_until(ex, lambda: any(s.values.get("missed_at_start.imu/data_raw") for s in got), 30), \
                proc.output()[-2000:]
            st = next(s for s in got if s.values.get("missed_at_start.imu/data_raw"))
            assert st.values["missed_at_start.imu/data_raw"] == "30" and st.values["lost.imu/data_raw"] == "30"
            assert st.level == 1 and "30 input messages lost" in st.message
            assert proc.wait_seen(r"WARN.*the first message received is its publisher's #31: 30 were published", 5)
        finally:
            proc.stop()
