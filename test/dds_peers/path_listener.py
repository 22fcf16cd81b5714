"""A subscriber of every user's back-end outputs (``/backend/u<i>/{path,pose}``, reliable) that a test
freezes with SIGSTOP: a subscriber that never acknowledges. ``python path_listener.py N``"""
from __future__ import annotations

import sys

import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Path

from indoor_loc.contract import Qos
from indoor_loc.nodes.qos import qos_profile


def main() -> None:
    n = int(sys.argv[1])
    rclpy.init()
    node = rclpy.create_node("path_listener")
    for u in range(n):
        node.create_subscription(Path, f"/backend/u{u}/path", lambda m: None, qos_profile(Qos.LATCHED))
        node.create_subscription(PoseWithCovarianceStamped, f"/backend/u{u}/pose", lambda m: None,
                                 qos_profile(Qos.RELIABLE))
    print("ready", flush=True)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
