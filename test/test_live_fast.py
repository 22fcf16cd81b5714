"""Live fast path: a node's raw sensor inputs, taken in runs and decoded in bulk, give the same
outputs and rejection counts as the stage fed one deserialised message at a time."""
from __future__ import annotations

import math

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu

from helpers_dds import ros_node, spin_until
from indoor_loc.nodes.base import StageNode, _cdr_stamp_ns
from indoor_loc.pipeline.imu_stage import ImuStage
from msg_adapters.imu import imu_to_msg

S = 1_000_000_000
NS = "/fast"


def _walk(n: int) -> list[Imu]:
    """A phone's orientation stream at 200 Hz while walking (2 Hz steps, slow turn), seeded noise,
    with one NaN acceleration and one repeated stamp in it."""
    rng = np.random.default_rng(7)
    msgs = []
    for k in range(n):
        t = k / 200.0
        acc = np.array([0.3 * math.sin(2 * math.pi * t), 0.2, 9.81 + 2.5 * math.sin(2 * math.pi * 2.0 * t)])
        acc += rng.normal(0.0, 0.05, 3)
        yaw = 0.05 * t
        q = np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
        msgs.append(imu_to_msg(S + k * S // 200, "fast/imu", acc, rng.normal(0.0, 0.01, 3), q,
                               np.diag([0.01, 0.01, 0.05])))
    msgs[1500].linear_acceleration.x = math.nan                      # rejected: nan
    msgs[2200].header.stamp = msgs[2199].header.stamp                # rejected: non_monotonic_stamp
    return msgs


def test_raw_runs_equal_message_by_message(ros_domain):
    msgs = _walk(3000)
    reference = ImuStage(ImuStage.PARAMS(), namespace=NS)
    want = []
    for m in msgs:            # the clock at reception: the sample's time (the node's is later still)
        recv = m.header.stamp.sec * S + m.header.stamp.nanosec
        want += [o for t, o in reference.process("imu/data", m, recv) if t == "pdr/odom"]
    assert len(want) >= 5

    with ros_node("probe") as (probe, ex):
        node = StageNode(ImuStage, context=probe.context, namespace=NS,
                         parameter_overrides=[Parameter("sensor_reliability", value="reliable")])
        try:
            assert set(node._raw) == {"imu/data_raw", "imu/mag", "imu/data"}     # all taken raw
            runs: list[int] = []
            batch = node.stage.process_batch

            def spy(topic, items, recv):
                runs.append(len(items))
                return batch(topic, items, recv)
            node.stage.process_batch = spy                                    # type: ignore[method-assign]
            ex.add_node(node)
            got: list[Odometry] = []
            probe.create_subscription(Odometry, f"{NS}/pdr/odom", got.append,
                                      QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
            pub = probe.create_publisher(Imu, f"{NS}/imu/data",
                                         QoSProfile(depth=len(msgs), reliability=ReliabilityPolicy.RELIABLE))
            assert spin_until(ex, lambda: pub.get_subscription_count() > 0
                              and probe.count_publishers(f"{NS}/pdr/odom") > 0, 40)
            for m in msgs:                       # all queued before the node runs: it takes them in runs
                pub.publish(m)
            assert spin_until(ex, lambda: node.taken == len(msgs) and len(got) >= len(want), 60), \
                (node.taken, len(got), len(want))
            assert got == want
            assert max(runs) > 100, runs                                      # the batch path did the work
            assert dict(node.stage.diag.rejected) == dict(reference.diag.rejected) \
                == {"nan": 1, "non_monotonic_stamp": 1}
            assert node.stage.diag.received["imu/data"].count == len(msgs)
            ex.remove_node(node)
        finally:
            node.destroy_node()


def test_cdr_stamp_of_a_header():
    from rclpy.serialization import serialize_message
    m = imu_to_msg(12 * S + 345, "f", [0.0, 0.0, 9.8])
    assert _cdr_stamp_ns(serialize_message(m)) == 12 * S + 345
    assert _cdr_stamp_ns(b"\x00\x00\x00") == 0
