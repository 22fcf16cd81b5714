"""The time policy recognises a stage's own output coming back on a topic it also takes (``imu_node``'s
``imu/data``) however late DDS delivers it: an echo is never judged, so it can neither move the
topic's watermark nor confirm a clock jump (pipeline/time_policy.py, "echoes")."""
from __future__ import annotations

import numpy as np

from indoor_loc.pipeline.time_policy import OWN_MAX, OwnStamps, TimeParams, TimePolicy
from msg_adapters.imu import imu_to_msg
from test_imu_stage import make_stage, walk

CLOCK = 10**18          # the node's clock, far ahead of the stamps (a replay without use_sim_time)


def _run_with_late_echoes(heading_source: str, lag: int, foreign_at: int | None, rng) -> object:
    """40 s of IMU through an ImuStage whose own ``imu/data`` comes back ``lag`` messages late (a node
    that published a large take at once); ``foreign_at``: after that raw sample, one ``imu/data`` from
    another publisher stamped like a raw sample the node has not taken yet."""
    stamps, acc, gyro, _ = walk(rng, duration_s=40.0)
    st = make_stage(heading_source=heading_source)
    echoes: list = []
    for i, ns in enumerate(int(s) for s in stamps):
        now = CLOCK + ns
        echoes += [m for t, m in st.process("imu/data_raw", imu_to_msg(ns, "imu", acc[i], gyro[i]), now)
                   if t == "imu/data"]
        if i == foreign_at:
            ahead = int(stamps[i + 5])
            st.process("imu/data", imu_to_msg(ahead, "imu", acc[i], None, [0, 0, 0, 1], np.eye(3) * 0.01), now)
        if len(echoes) > lag:
            st.process("imu/data", echoes.pop(0), now)
    return st


def test_late_echoes_behind_a_foreign_message_are_not_a_clock_jump(rng):
    # before: the echoes of more than the last 512 outputs were not recognised; behind the foreign
    # message they were "far back" and in step, three in a row: a jump, and imu_node reset itself
    st = _run_with_late_echoes("aekf", lag=600, foreign_at=1500, rng=rng)
    assert st.diag.time_jumps == 0
    assert sum(st.diag.rejected.values()) == 0
    assert st.heading_mode == "aekf"


def test_late_echoes_never_become_the_heading_source(rng):
    # before: with heading_source auto a late echo was taken for another node's orientation and the
    # node steered by its own delayed output
    st = _run_with_late_echoes("auto", lag=3000, foreign_at=None, rng=rng)
    assert st.heading_mode == "vqf"
    assert "imu/data" not in st.time.user("").marks          # no echo was judged as input
    assert st.diag.time_jumps == 0


def test_own_stamps_bounded_and_exact():
    own = OwnStamps()
    n = OWN_MAX + OWN_MAX // 2 + 7
    for k in range(n):
        own.add(1000 + 10 * k)
    assert len(own) == OWN_MAX
    assert 1000 + 10 * (n - 1) in own and 1000 + 10 * (n - OWN_MAX) in own
    assert 1000 + 10 * (n - OWN_MAX - 1) not in own                  # forgotten, oldest first
    assert 1000 + 10 * (n - 1) + 5 not in own and 1005 + 10 * (n - 100) not in own   # never published
    own.add(1000 + 10 * (n - 50) + 3)                                # a reset: an older stamp again
    assert 1000 + 10 * (n - 50) + 3 in own and len(own) == OWN_MAX
    assert len(own.stamps) <= OWN_MAX + OWN_MAX // 4


def test_echo_is_per_user_and_topic():
    tp = TimePolicy(TimeParams())
    tp.published("alice", "imu/data", 5)
    assert tp.echo("alice", "imu/data", 5)
    assert not tp.echo("bob", "imu/data", 5) and not tp.echo("alice", "imu/data_raw", 5)
    assert not tp.echo("alice", "imu/data", 6)
