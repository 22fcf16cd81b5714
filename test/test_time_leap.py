"""Leaps ahead (pipeline/time_policy.py, ``time.leap_s``): one message stamped far ahead of its
topic's stream, with a node clock that cannot vouch for it (a bag replayed without use_sim_time, a
device clock that is not the node's), must not move the topic's watermark there — or every valid
message after it would be refused. A source that really resumes after a pause loses nothing."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from indoor_loc.contract import Qos
from indoor_loc.params import group
from indoor_loc.pipeline.stage import Port, Stage
from indoor_loc.pipeline.time_policy import Order, TimeParams
from msg_adapters.odom import odom_to_msg

SEC = 1_000_000_000
#: The node's clock: ten months after the stamps (a bag replayed without use_sim_time).
CLOCK_AHEAD = 300 * 86400 * SEC


@dataclass(frozen=True)
class TickParams:
    time: TimeParams = group(TimeParams, "stamps")


class TickStage(Stage):
    """Takes ``pdr/odom`` (strict order) and ``wifi/fix``-like ``scan`` topic (non-decreasing);
    remembers the stamps it handled."""
    NODE_NAME = "tick_node"
    PARAMS = TickParams
    STAMP_ORDER = {"pdr/odom": Order.STRICT}

    def __init__(self, params=None, *, namespace=""):
        super().__init__(params or TickParams(), namespace=namespace)
        self.handled: list[int] = []
        self.on("pdr/odom", self._take)

    def inputs(self):
        return [Port("pdr/odom", "nav_msgs/msg/Odometry", Qos.RELIABLE)]

    def outputs(self):
        return []

    def _take(self, msg, recv_ns):
        self.handled.append(msg.header.stamp.sec * SEC + msg.header.stamp.nanosec)
        return []


def _odom(t_ns: int):
    return odom_to_msg(t_ns, "odom", "base", 0.0, 0.0, 0.0, np.eye(3), 0.0, 0.0)


def _run(stage: TickStage, stamps: list[int], clock_ahead: int = CLOCK_AHEAD, rate: float = 1.0) -> None:
    """Feed the stamps in order; the node's clock runs from the first stamp + ``clock_ahead`` in step."""
    t0 = stamps[0]
    for i, s in enumerate(stamps):
        recv = t0 + clock_ahead + int(i * 0.5 * SEC / rate)
        stage.process("pdr/odom", _odom(s), recv)


def test_one_stamp_an_hour_ahead_does_not_silence_the_topic():
    st = TickStage()
    valid = [1000 * SEC + k * SEC // 2 for k in range(40)]
    bad = valid[10] + 3600 * SEC
    _run(st, valid[:11] + [bad] + valid[11:])
    assert st.handled == valid                                # every valid message taken, in order
    assert st.diag.rejected["stamp_leap"] == 1                 # the wrong one counted, nothing silent
    assert st.diag.time_jumps == 0


def test_a_source_resuming_after_a_pause_loses_nothing():
    st = TickStage()
    before = [1000 * SEC + k * SEC // 2 for k in range(10)]
    after = [before[-1] + 600 * SEC + k * SEC // 2 for k in range(10)]     # ten minutes of silence
    _run(st, before + after)
    assert st.handled == before + after
    assert sum(st.diag.rejected.values()) == 0


def test_the_node_clock_vouches_for_a_leap_at_once():
    st = TickStage()
    before = [1000 * SEC + k * SEC // 2 for k in range(10)]
    after = before[-1] + 600 * SEC
    for s in before:
        st.process("pdr/odom", _odom(s), s)                    # stamps are the node's clock (live)
    st.process("pdr/odom", _odom(after), after)
    assert st.handled == before + [after]                     # taken at once, not held


def test_a_leap_still_held_at_the_end_of_input_is_counted():
    st = TickStage()
    valid = [1000 * SEC + k * SEC // 2 for k in range(10)]
    _run(st, valid + [valid[-1] + 3600 * SEC])
    st.run_finish()
    assert st.handled == valid
    assert st.diag.rejected["stamp_leap"] == 1


def test_leaps_and_far_back_stamps_mixed_among_valid_messages_leave_the_stream_whole():
    rng = np.random.default_rng(5)
    st = TickStage()
    valid = [10_000 * SEC + k * SEC // 2 for k in range(200)]
    stream, wrong = [], 0
    for s in valid:
        stream.append(s)
        for _ in range(int(rng.integers(0, 3))):     # wrong stamps made from the valid one, as a bad driver does
            stream.append(int(s + rng.choice([3600, 86400, -30, -3600]) * SEC))
            wrong += 1
    _run(st, stream)
    st.run_finish()
    assert st.handled == valid
    assert st.diag.rejected["stamp_leap"] + st.diag.rejected["stale_stamp"] == wrong
    assert st.diag.time_jumps == 0
