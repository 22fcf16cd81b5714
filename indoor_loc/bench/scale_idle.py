"""What a multi-user node costs per user before any message: users that publish nothing (only their input
publishers exist) added to a multi-user ``pdr_kf_node`` (default parameters), the process's CPU measured
at each step, optionally with a part of the node's own work switched off (docs/scaling.md, third pass).

``python -m indoor_loc.bench.scale_idle [--users 0,60] [--off poll|diag|disc|watch] [--window 20]``

``--off`` patches the node process (never an option of the node): ``poll`` no polling of the users'
subscriptions, ``diag`` no per-user ``/diagnostics`` status, ``disc`` no discovery once the users are
followed, ``watch`` no watching of the inputs' publishers. Run it with a ``ROS_DOMAIN_ID`` of its own.
"""
from __future__ import annotations

import argparse
import os
import runpy
import subprocess
import sys
import time


def _patched_node(off: str, users: int) -> None:
    """Run ``pdr_kf_node`` with one part of the multi-user node's own work switched off."""
    from indoor_loc.nodes import multi_user_node as m
    from msg_adapters.diagnostics import stage_diagnostics
    cls = m.MultiUserStageNode
    if off == "watch":
        cls._watch_inputs = lambda self, now_ns: None     # type: ignore[method-assign]
    elif off == "diag":
        cls.diagnostics_msg = lambda self, now_ns: stage_diagnostics(  # type: ignore[method-assign]
            self.get_fully_qualified_name(), self.stage, now_ns)
    elif off == "poll":
        cls._poll = lambda self, only=None: None          # type: ignore[method-assign]
    elif off == "disc":
        discover = cls._discover_users

        def until_followed(self) -> None:                 # type: ignore[no-untyped-def]
            if len(self.user_subs) < users:
                discover(self)
        cls._discover_users = until_followed              # type: ignore[method-assign]
    sys.argv = ["pdr_kf_node", "--multi-user", "--ros-args", "-p", "user_timeout_s:=600.0"]
    runpy.run_module("indoor_loc.nodes.pdr_kf_node", run_name="__main__", alter_sys=True)


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        s = f.read().rsplit(")", 1)[1].split()
    return (int(s[11]) + int(s[12])) / os.sysconf("SC_CLK_TCK")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--users", default="0,60")
    ap.add_argument("--off", default="", choices=["", "poll", "diag", "disc", "watch"])
    ap.add_argument("--window", type=float, default=20.0)
    ap.add_argument("--node", nargs=2, metavar=("OFF", "USERS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.node:
        _patched_node(args.node[0], int(args.node[1]))
        return 0
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from rclpy.node import Node

    from indoor_loc.contract import Qos
    from indoor_loc.nodes.qos import publisher_qos
    steps = [int(u) for u in args.users.split(",")]
    rclpy.init()
    node = Node("scale_idle")
    proc = subprocess.Popen([sys.executable, "-m", "indoor_loc.bench.scale_idle", "--node", args.off or "-",
                             str(max(steps))], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    pubs = []
    try:
        time.sleep(8.0)
        have = 0
        for want in steps:
            for k in range(have, want):
                for cls, rel in ((Odometry, "pdr/odom"), (PoseWithCovarianceStamped, "wifi/fix")):
                    pubs.append(node.create_publisher(cls, f"/i{k:03d}/{rel}", publisher_qos(Qos.RELIABLE)))
            have = want
            for window in (12.0, args.window):            # the users followed first, then measured
                c0, t0 = _cpu_s(proc.pid), time.monotonic()
                while time.monotonic() < t0 + window:
                    rclpy.spin_once(node, timeout_sec=0.1)
            print(f"{want} idle users (off: {args.off or 'nothing'}): pdr_kf_node {1e3 * (_cpu_s(proc.pid) - c0) / window:.1f} "
                  f"ms/s of CPU; load average {open('/proc/loadavg').read().split()[0]}", flush=True)
    finally:
        proc.send_signal(2)
        proc.wait(timeout=30)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
