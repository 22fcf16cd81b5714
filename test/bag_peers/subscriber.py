"""Test peer: subscribes (use_sim_time) to imu/data_raw, ground_truth and /clock under NAMESPACE and
prints one line per event, flushing: ``imu <frame_id> <stamp_ns> <clock_now_ns>``, ``gt <n_poses>``,
``clock <ns>`` (first and every 50th only); exits after EXPECTED imu messages or TIMEOUT s.

usage: subscriber.py NAMESPACE EXPECTED TIMEOUT_S
"""
from __future__ import annotations

import sys
import time

import rclpy
from nav_msgs.msg import Path
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu


def main() -> int:
    ns, expected, timeout = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    rclpy.init()
    node = rclpy.create_node("bag_test_subscriber", namespace=ns,
                             parameter_overrides=[Parameter("use_sim_time", value=True)])
    state = {"imu": 0, "clock": 0}

    def on_imu(m: Imu) -> None:
        s = m.header.stamp
        print(f"imu {m.header.frame_id} {s.sec * 10**9 + s.nanosec} {node.get_clock().now().nanoseconds}", flush=True)
        state["imu"] += 1

    def on_clock(m: Clock) -> None:
        if state["clock"] % 50 == 0:
            print(f"clock {m.clock.sec * 10**9 + m.clock.nanosec}", flush=True)
        state["clock"] += 1

    node.create_subscription(Imu, "imu/data_raw", on_imu, QoSProfile(depth=1000))
    node.create_subscription(Path, "ground_truth", lambda m: print(f"gt {len(m.poses)}", flush=True), QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    node.create_subscription(Clock, "/clock", on_clock, QoSProfile(depth=10))
    print("ready", flush=True)
    end = time.monotonic() + timeout
    while rclpy.ok() and state["imu"] < expected and time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    print(f"done {state['imu']} clock_msgs {state['clock']}", flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
