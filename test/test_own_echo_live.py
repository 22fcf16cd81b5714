"""A node that publishes one of its own inputs (imu_node: imu/data, the filter's orientation, is also an
input for a phone's OS orientation) over DDS: its own messages coming back are not input — not counted
as taken, not watched for liveness, their sequence numbers never counted as losses — so what it books
(taken + lost) never exceeds what was sent to it."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from helpers_dds import Peer, child_env, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.nodes.base import qos_profile
from msg_adapters.diagnostics import diagnostics_from_msg
from msg_adapters.imu import imu_to_msg


@pytest.mark.timeout(180)
def test_imu_node_does_not_book_its_own_imu_data(ros_domain):
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import Imu

    proc = Peer([sys.executable, "-m", "indoor_loc.nodes.imu_node", "--ros-args", "-r", "__ns:=/echo",
                 "-p", "sensor_reliability:=reliable"], env=child_env())
    try:
        with ros_node("bench") as (node, ex):
            status: dict = {}

            def on_diag(arr) -> None:
                for name, st in diagnostics_from_msg(arr).items():
                    if name.startswith("/echo/imu_node"):
                        status.update(st.values)
            node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 50)
            out: list = []
            node.create_subscription(Imu, "/echo/imu/data", out.append, qos_profile(Qos.SENSOR))
            pub = node.create_publisher(Imu, "/echo/imu/data_raw", qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: pub.get_subscription_count() > 0, 60), proc.output()
            rng = np.random.default_rng(4)
            sent = 400
            for i in range(sent):                     # 4 s of a phone lying still, at 100 Hz
                acc = np.array([0.0, 0.0, 9.81]) + rng.normal(0, 0.05, 3)
                pub.publish(imu_to_msg(10_000_000_000 + i * 10_000_000, "echo/imu", acc, rng.normal(0, 0.01, 3)))
                spin_until(ex, lambda: False, 0.004)

            def booked() -> int:            # taken or counted lost (a loaded node may lose some, counted)
                return int(status.get("in.imu/data_raw.count", 0)) + int(status.get("lost.total", 0))
            assert spin_until(ex, lambda: booked() >= sent and len(out) > 100, 60), \
                ({k: v for k, v in status.items() if k.startswith(("in.imu/data_raw.", "lost.", "out."))},
                 proc.output()[-3000:])
            spin_until(ex, lambda: False, 3.0)         # its later statuses: the echoes have come back by now
            taken = sum(int(v) for k, v in status.items() if k.startswith("in.") and k.endswith(".count"))
            assert int(status["out.imu/data.count"]) > 100              # it does publish imu/data ...
            assert int(status.get("in.imu/data.count", 0)) == 0         # ... and takes none of it back
            assert taken + int(status["lost.total"]) <= sent, status
            assert status.get("in.imu/data.state") == "waiting", status  # no other publisher: no input there
    finally:
        proc.stop()
