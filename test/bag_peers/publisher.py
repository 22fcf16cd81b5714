"""Test peer: publishes N Imu messages on imu/data_raw (numbered in header.frame_id) and one latched
nav_msgs/Path on ground_truth, then keeps spinning (so a recorder started later still matches).

usage: publisher.py NAMESPACE COUNT RATE_HZ [--best-effort]
"""
from __future__ import annotations

import sys

import rclpy
from nav_msgs.msg import Path
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu


def main() -> int:
    ns, count, rate = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    best_effort = "--best-effort" in sys.argv
    rclpy.init()
    node = rclpy.create_node("bag_test_publisher", namespace=ns)
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE)
    imu_pub = node.create_publisher(Imu, "imu/data_raw", qos)
    gt_pub = node.create_publisher(Path, "ground_truth", QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    gt = Path()
    gt.header.frame_id = "map"
    gt_pub.publish(gt)
    state = {"i": 0, "waited": 0}

    def tick() -> None:
        # wait until something subscribes to imu/data_raw, then publish COUNT messages
        if imu_pub.get_subscription_count() == 0 and state["i"] == 0:
            return
        if state["i"] == 0 and state["waited"] < 5:       # let discovery settle both ways
            state["waited"] += 1
            return
        if state["i"] < count:
            m = Imu()
            m.header.stamp = node.get_clock().now().to_msg()
            m.header.frame_id = str(state["i"])
            m.linear_acceleration.z = 9.81 + state["i"]
            imu_pub.publish(m)
            state["i"] += 1
            if state["i"] == count:
                print("published", count, flush=True)

    node.create_timer(1.0 / rate, tick)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
