"""Publishes one tf2_msgs/TFMessage on /tf (reliable, volatile, as tf2's broadcaster does) once a
subscription matches, then prints ``sent`` and waits to be stopped: ``tf_sender.py CHILD_FRAME``."""
from __future__ import annotations

import sys
import time

import rclpy
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from tf2_msgs.msg import TFMessage


def main() -> None:
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Node("tf_sender")
    pub = node.create_publisher(TFMessage, "/tf", 100)
    deadline = time.monotonic() + 15.0
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    t = TransformStamped(child_frame_id=sys.argv[1])
    t.header.frame_id = "map"
    t.header.stamp.sec = 42
    t.transform.translation.x = 1.5
    t.transform.rotation.w = 1.0
    pub.publish(TFMessage(transforms=[t]))
    print("sent", flush=True)
    try:
        while True:
            time.sleep(0.1)
    except KeyboardInterrupt:
        pass
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
