"""Publishes many users' walks to the back-end's inputs as fast as it can, once its subscriptions
have matched and a line comes on stdin: a burst of load. ``python backend_burst.py N_USERS SEED
LENGTH_M`` prints ``matched`` when every publisher has a subscriber, ``sent K`` when it has
published, ``acked`` when the back-end's DDS has every message (queued for the node, maybe not
handled yet), then ends (with a fifth argument ``stay``: waits to be stopped, its publishers staying
in the graph)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import rclpy
from rclpy.duration import Duration
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from indoor_loc.contract import Qos  # noqa: E402
from indoor_loc.nodes.qos import qos_profile  # noqa: E402
from test_shutdown_bound import burst  # noqa: E402


def main() -> None:
    n, seed, length_m = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
    rclpy.init()
    node = rclpy.create_node("backend_burst")
    pubs = {(f"u{u}", t): node.create_publisher(Odometry if t == "pdr/odom" else DiagnosticArray, f"/u{u}/{t}",
                                                qos_profile(Qos.RELIABLE))
            for u in range(n) for t in ("pdr/odom", "wifi/scan")}
    msgs = burst(n, seed, length_m)
    while not all(p.get_subscription_count() > 0 for p in pubs.values()):
        time.sleep(0.05)
    print("matched", flush=True)
    sys.stdin.readline()                      # go
    for user, topic, msg in msgs:
        pubs[(user, topic)].publish(msg)
    print(f"sent {len(msgs)}", flush=True)
    if all(p.wait_for_all_acked(Duration(seconds=60)) for p in pubs.values()):
        print("acked", flush=True)
    if len(sys.argv) > 4 and sys.argv[4] == "stay":
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
