"""A topic's first message leaping ahead of the user's other topics (pipeline/time_policy.py, the leap
rule): with a node clock that cannot vouch for the stamps (a bag replayed without use_sim_time),
fixes stamped an hour ahead reaching the node before the user's first valid fix -- the wrong ones
published at once, the valid one behind the WiFi node's latency -- must not set the fix topic's
watermark an hour ahead. Before: every valid fix after them was held as a jump back that the
hostile fixes between them (same stamps as the valid ones) kept from confirming, then dropped
(``stale_stamp``): the estimators got no fix for the rest of the run (the fault benchmark's
``--ports wifi/fix``: 2 036 of 2 080 fixes refused, ``pdr_kf_node`` 12.8x its clean error)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from indoor_loc.contract import Qos
from indoor_loc.measurements import Fix
from indoor_loc.params import group
from indoor_loc.pipeline.stage import Port, Stage
from indoor_loc.pipeline.time_policy import Order, TimeParams
from msg_adapters.odom import odom_to_msg
from msg_adapters.pose import fix_from_msg, fix_to_msg

SEC = 1_000_000_000
CLOCK_AHEAD = 300 * 86400 * SEC          # the node's clock: ten months after the stamps


@dataclass(frozen=True)
class TwoParams:
    time: TimeParams = group(TimeParams, "stamps")


class TwoStage(Stage):
    """``pdr/odom`` (strict) and ``wifi/fix`` (non-decreasing, adapter-validated); remembers the fix
    stamps it took."""
    NODE_NAME = "two_node"
    PARAMS = TwoParams
    STAMP_ORDER = {"pdr/odom": Order.STRICT, "wifi/fix": Order.NONDECREASING}

    def __init__(self, params=None, *, namespace=""):
        super().__init__(params or TwoParams(), namespace=namespace)
        self.fixes: list[int] = []
        self.on("pdr/odom", lambda msg, recv: [])
        self.on("wifi/fix", self._fix)

    def inputs(self):
        return [Port("pdr/odom", "nav_msgs/msg/Odometry", Qos.RELIABLE),
                Port("wifi/fix", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE)]

    def outputs(self):
        return []

    def _fix(self, msg, recv):
        self.fixes.append(fix_from_msg(msg).stamp_ns)    # nan, bad_covariance, ...
        return []


def _fix(t_ns: int, var: float = 4.0):
    return fix_to_msg(Fix(t_ns, np.array([3.0, 4.0]), np.eye(2) * var))


def _garbage(t_ns: int):
    m = _fix(t_ns)
    m.pose.pose.position.x = float("nan")
    return m


def test_fixes_an_hour_ahead_before_the_first_valid_one_do_not_silence_the_topic():
    st = TwoStage()
    t0 = 1000 * SEC
    valid = [t0 + 4 * SEC * k for k in range(1, 16)]             # a fix every 4 s
    k_fix = 0
    for i in range(0, 64 * 4 + 1):                                # odometry every 0.25 s, 64 s
        t = t0 + i * SEC // 4
        recv = t + CLOCK_AHEAD
        st.process("pdr/odom", odom_to_msg(t, "odom", "base", 0.0, 0.0, 0.0, np.eye(3), 0.0, 0.0), recv)
        while k_fix < len(valid) and valid[k_fix] + SEC <= t:     # the valid fix one second late
            s = valid[k_fix]
            hostile = [_fix(s + 3600 * SEC), _garbage(s), _garbage(s)]
            for m in hostile + [_fix(s)]:                          # the wrong ones first
                st.process("wifi/fix", m, recv)
            k_fix += 1
    assert st.fixes == valid, st.diag.rejected
    assert st.diag.rejected["stale_stamp"] == 0 and st.diag.time_jumps == 0
    assert st.diag.rejected["stamp_leap"] == len(valid)          # each an hour ahead, counted
