"""Managed mode over DDS: ``pdr_kf_node --managed`` (and ``tll_pf``) driven by a lifecycle client (configure, activate,
deactivate, activate, deactivate, cleanup, configure, activate) publishes only while active, and a
cleanup drops the filter's state."""
from __future__ import annotations

import sys

import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy

from helpers_dds import Peer, child_env, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.measurements import Fix
from indoor_loc.nodes.base import qos_profile
from msg_adapters.pose import fix_to_msg, pose_from_msg
from robot_walk import RobotWalk


CASES = {"pdr_kf": ("indoor_loc.nodes.pdr_kf_node", "pdr_kf_node", "pdr_kf/pose"),
         "pf": ("indoor_loc.nodes.tll_pf_node", "tll_pf", "pf/pose")}


@pytest.mark.timeout(240)
@pytest.mark.parametrize("which", sorted(CASES))
def test_outputs_only_while_active(which, ros_domain, tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from lifecycle_msgs.msg import State, Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    module, name, pose_topic = CASES[which]
    extra = [] if which == "pdr_kf" else ["-p", f"graph_file:={RobotWalk(10.0).save_graph(tmp_path / 'g.graph.yaml')}"]
    proc = Peer([sys.executable, "-m", module, "--managed", "--ros-args", "-r", "__ns:=/alice",
                 "-p", "max_fix_delay_s:=0.0", *extra], env=child_env())   # each fix out at once
    try:
        with ros_node("lifecycle_manager") as (node, ex):
            poses: list = []
            node.create_subscription(PoseWithCovarianceStamped, f"/alice/{pose_topic}", poses.append,
                                     QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
            fix = node.create_publisher(PoseWithCovarianceStamped, "/alice/wifi/fix", qos_profile(Qos.RELIABLE))
            change = node.create_client(ChangeState, f"/alice/{name}/change_state")
            get = node.create_client(GetState, f"/alice/{name}/get_state")
            assert change.wait_for_service(timeout_sec=60) and get.wait_for_service(timeout_sec=10), proc.output()
            assert spin_until(ex, lambda: fix.get_subscription_count() > 0, 30), proc.output()
            stamp = [10_000_000_000]

            def state() -> int:
                fut = get.call_async(GetState.Request())
                assert spin_until(ex, fut.done, 20)
                return fut.result().current_state.id

            def transition(tid: int) -> None:
                fut = change.call_async(ChangeState.Request(transition=Transition(id=tid)))
                assert spin_until(ex, fut.done, 20) and fut.result().success, proc.output()

            def outputs_for_a_fix(xy=(8.0, 10.0)) -> list:     # on the sample building's corridor
                n = len(poses)
                stamp[0] += 1_000_000_000
                fix.publish(fix_to_msg(Fix(stamp[0], np.array(xy, float), np.eye(2))))
                spin_until(ex, lambda: len(poses) > n, 3.0)
                return poses[n:]

            assert state() == State.PRIMARY_STATE_UNCONFIGURED
            assert not outputs_for_a_fix()
            transition(Transition.TRANSITION_CONFIGURE)
            assert state() == State.PRIMARY_STATE_INACTIVE
            assert not outputs_for_a_fix()
            transition(Transition.TRANSITION_ACTIVATE)
            assert state() == State.PRIMARY_STATE_ACTIVE
            assert outputs_for_a_fix()
            transition(Transition.TRANSITION_DEACTIVATE)
            assert not outputs_for_a_fix()
            transition(Transition.TRANSITION_ACTIVATE)
            kept = outputs_for_a_fix((8.5, 10.0))
            assert kept
            if which == "pdr_kf":
                assert pose_from_msg(kept[-1]).xy[0] != 8.5        # the filter went on from its state
            transition(Transition.TRANSITION_DEACTIVATE)
            transition(Transition.TRANSITION_CLEANUP)
            assert state() == State.PRIMARY_STATE_UNCONFIGURED
            assert not outputs_for_a_fix()
            transition(Transition.TRANSITION_CONFIGURE)
            transition(Transition.TRANSITION_ACTIVATE)
            fresh = outputs_for_a_fix((30.0, 10.0))
            assert fresh
            if which == "pdr_kf":
                assert np.allclose(pose_from_msg(fresh[-1]).xy, (30.0, 10.0))   # a fresh filter starts at it
    finally:
        proc.stop()
