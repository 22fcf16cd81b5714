"""A node whose callbacks are long (one message = 3 s of Python work, as a raw IMU take of 2048 messages
is on a loaded machine) still answers parameter reads and keeps publishing ``/diagnostics``
(``indoor_loc/nodes/responsive.py``). Before: a request waited for the callback to end (up to 3 s) and
``/diagnostics`` was silent for the whole busy spell."""
from __future__ import annotations

import sys
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.duration import Duration

from helpers_dds import PEERS, Peer, child_env, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.nodes.qos import qos_profile

pytestmark = pytest.mark.timeout(240)


def test_parameter_reads_and_diagnostics_go_on_during_a_long_callback(ros_domain):
    from nav_msgs.msg import Odometry
    from rcl_interfaces.srv import GetParameters
    from msg_adapters.odom import odom_to_msg
    node_proc = Peer([sys.executable, str(PEERS / "busy_node.py"), "--ros-args", "-p", "users:=[u0]",
                      "-p", "work_ms:=3000.0"], env=child_env())
    try:
        with ros_node("probe") as (node, ex):
            pub = node.create_publisher(Odometry, "/u0/pdr/odom", qos_profile(Qos.RELIABLE))
            cli = node.create_client(GetParameters, "/busy_node/get_parameters")
            diag_at: list[float] = []

            def on_diag(msg: DiagnosticArray) -> None:
                if any(s.name == "/busy_node" for s in msg.status):
                    diag_at.append(time.monotonic())
            node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: cli.service_is_ready() and pub.get_subscription_count() > 0
                              and len(diag_at) >= 2, 150), node_proc.output()

            def ask() -> float:
                t = time.monotonic()
                fut = cli.call_async(GetParameters.Request(names=["work_ms"]))
                assert spin_until(ex, fut.done, 30), node_proc.output()
                assert fut.result().values[0].double_value == 3000.0
                return time.monotonic() - t

            ask()                                          # the first request also sets up the connection
            t0 = time.time_ns()
            for k in range(3):                             # 9 s of work, one long callback after another
                pub.publish(odom_to_msg(t0 + k * 1_000_000, "odom", "base_link", 0.1 * k, 0.0, 0.0, np.eye(3), 0.0, 0.0))
            assert pub.wait_for_all_acked(Duration(seconds=30))
            busy_from = time.monotonic()
            latencies = []
            while time.monotonic() < busy_from + 7.0:      # inside the 9 s of work
                spin_until(ex, lambda: False, 0.1)
                latencies.append(ask())
            lat = np.sort(latencies)
            gaps = np.diff([t for t in diag_at if t >= busy_from - 1.0])
            print(f"{len(lat)} requests: median {np.median(lat) * 1e3:.1f} ms, max {lat[-1] * 1e3:.1f} ms; "
                  f"/diagnostics gaps (s): {np.round(gaps, 2).tolist()}")
            assert len(lat) >= 10
            assert np.median(lat) < 0.1 and lat[-1] < 1.0, (lat.tolist(), node_proc.output()[-2000:])
            assert len(gaps) >= 2 and gaps.max() < 3.5, (gaps.tolist(), node_proc.output()[-2000:])
    finally:
        node_proc.stop()
