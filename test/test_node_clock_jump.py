"""StageNode follows the node's clock going back (``/clock`` under ``use_sim_time``) for every stage:
the stage's ``run_clock_jump`` is called when the jump is at least its ``clock_jump_threshold_ns``
(never when that is 0), its outputs are published and its notices logged."""
from __future__ import annotations

import sys

import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock

from helpers_dds import PEERS, ros_node, spin_for, spin_until
from indoor_loc.contract import Qos
from indoor_loc.nodes.qos import qos_profile
from indoor_loc.nodes.stage_node import StageNode
from msg_adapters.pose import pose_from_msg, pose_to_msg

sys.path.insert(0, str(PEERS))
from dummy_node import DummyStage  # noqa: E402

pytestmark = pytest.mark.timeout(120)


class _JumpStage(DummyStage):
    """Follows jumps back of 10 s or more: publishes a pose stamped with the new clock, x = the jump."""
    NODE_NAME = "jump_node"
    THRESHOLD_NS = 10_000_000_000

    def __init__(self, params, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        self.jumps: list[tuple[int, int]] = []

    def clock_jump_threshold_ns(self) -> int:
        return self.THRESHOLD_NS

    def clock_jump(self, back_ns: int, now_ns: int):
        self.jumps.append((back_ns, now_ns))
        self.notice(f"clock back {back_ns} ns")
        return [("dummy/pose", pose_to_msg(now_ns, [back_ns * 1e-9, 0.0]))]


class _NoJumpStage(_JumpStage):
    NODE_NAME = "nojump_node"
    THRESHOLD_NS = 0


def _clock(sec: int) -> Clock:
    return Clock(clock=Time(sec=sec, nanosec=0))


@pytest.mark.parametrize("stage_cls", [_JumpStage, _NoJumpStage])
def test_a_clock_jump_back_reaches_the_stage(ros_domain, stage_cls):
    with ros_node("probe") as (probe, ex):
        node = StageNode(stage_cls, context=probe.context,
                         parameter_overrides=[Parameter("use_sim_time", value=True)])
        ex.add_node(node)
        try:
            poses: list[PoseWithCovarianceStamped] = []
            clock = probe.create_publisher(Clock, "/clock", 10)
            probe.create_subscription(PoseWithCovarianceStamped, "dummy/pose", poses.append, qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: clock.get_subscription_count() > 0
                              and probe.count_publishers("dummy/pose") > 0, 20)

            def at(sec: int) -> bool:
                clock.publish(_clock(sec))
                return spin_until(ex, lambda: node.get_clock().now().nanoseconds == sec * 1_000_000_000, 10)
            assert at(100) and at(105)
            assert at(98)                     # 7 s back: under the threshold
            assert at(40)                     # 58 s back
            spin_for(ex, 0.5)
            if stage_cls.THRESHOLD_NS == 0:
                assert node.stage.jumps == [] and poses == []
                return
            assert node.stage.jumps == [(58_000_000_000, 40_000_000_000)]
            assert spin_until(ex, lambda: len(poses) == 1, 10)
            p = pose_from_msg(poses[0])
            assert p.stamp_ns == 40_000_000_000 and p.xy[0] == pytest.approx(58.0)
            assert node.stage.notices == []                  # taken (and logged) by the node
            assert node.stage.diag.published["dummy/pose"] == 1
        finally:
            ex.remove_node(node)
            node.destroy_node()
