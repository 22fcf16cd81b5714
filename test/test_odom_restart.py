"""A restarted odometry producer (``imu_node`` killed and started again: a new publisher, its
sequence numbers from 1, its poses from the origin) is a new odometry frame for its consumers at
once: no ``odom_jump`` refusals while the stamps "allow the distance", no walk across the restart.
The rule (the node's input watch sees the restart, :meth:`Stage.upstream_restarted`) without DDS,
then live: ``pdr_kf_node`` with one odometry publisher process after another."""
from __future__ import annotations

import sys

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from helpers_dds import PEERS, Peer, child_env, follow_diagnostics, python_peer, ros_node, spin_until
from indoor_loc.nodes.liveness import InputWatch
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage, PdrKfStageParams
from msg_adapters.odom import odom_to_msg

sys.path.insert(0, str(PEERS))
from raw_sender import write_samples  # noqa: E402

S = 1_000_000_000
HOP = S // 5                 # a hop every 0.2 s of stamps
STEP = 0.3                   # m per hop along x


def _odom(k: int, x: float) -> object:
    return odom_to_msg(S + k * HOP, "rs/odom", "rs/base_link", x, 0.0, 0.0, np.diag([0.01, 0.01, 0.01]), 1.5, 0.0)


def _streams(n_first: int = 150, n_second: int = 40) -> tuple[list, list]:
    """The first producer walks 45 m along x; the restarted one starts at its origin again, its stamps
    going on from the first's (one hop later)."""
    first = [_odom(k, STEP * k) for k in range(1, n_first + 1)]
    second = [_odom(n_first + k, STEP * k) for k in range(1, n_second + 1)]
    return first, second


def test_watch_says_which_message_is_a_restarted_publishers_first():
    w = InputWatch("pdr/odom")
    w.publishers_seen(frozenset({b"g1"}), 100 * S)
    fresh = []
    for k, seq in enumerate(list(range(1, 11)) + list(range(1, 6))):
        now = 100 * S + k * HOP + (5 * S if k >= 10 else 0)      # the new publisher after 5 s of silence
        w.message({"publication_sequence_number": seq}, now, lambda: frozenset({b"g2"}))
        fresh.append(w.fresh)
    assert fresh == [False] * 10 + [True] + [False] * 4 and w.restarts == 1


def test_pdr_kf_takes_a_restarted_odometry_as_a_new_frame():
    first, second = _streams()
    st = PdrKfStage(params_from_dict(PdrKfStageParams, {}), namespace="/rs")
    for m in first:
        st.process("pdr/odom", m, 0)
    st.run_upstream_restarted("pdr/odom")
    for m in second:
        st.process("pdr/odom", m, 0)
    assert st.diag.rejected["odom_jump"] == 0 and sum(st.diag.rejected.values()) == 0
    assert st._odom.decoder.last_stamp_ns == S + (len(first) + len(second)) * HOP
    assert any("restarted" in n for n in st.take_notices())


@pytest.mark.timeout(240)
def test_live_pdr_kf_node_takes_a_restarted_producers_odometry_at_once(ros_domain, tmp_path):
    """Before: the restarted producer's first poses (45 m from the last one) were refused as
    ``odom_jump`` until their stamps allowed the distance (15 of them here)."""
    first, second = _streams()
    f1, f2 = tmp_path / "first.bin", tmp_path / "second.bin"
    write_samples(f1, [serialize_message(m) for m in first])
    write_samples(f2, [serialize_message(m) for m in second])
    node = Peer([sys.executable, "-m", "indoor_loc.nodes.pdr_kf_node", "--ros-args", "-r", "__ns:=/rs"],
                env=child_env())
    sender = python_peer("raw_sender.py", str(f1), "/rs/pdr/odom", "nav_msgs/msg/Odometry", "0.02")
    again = None
    try:
        with ros_node("monitor") as (mon, ex):
            got, value = follow_diagnostics(mon, "/rs/pdr_kf_node")
            assert spin_until(ex, lambda: value("in.pdr/odom.count") == str(len(first)), 150), \
                (got[-1:], node.output()[-2000:])
            assert sender.proc.wait(timeout=20) == 0
            again = python_peer("raw_sender.py", str(f2), "/rs/pdr/odom", "nav_msgs/msg/Odometry", "0.02")
            assert spin_until(ex, lambda: value("in.pdr/odom.count") == str(len(first) + len(second)), 40), \
                (got[-1:], node.output()[-2000:])
            assert value("in.pdr/odom.upstream_restarts") == "1"
            assert value("rejected.odom_jump") in ("", "0"), got[-1]
            assert value("rejected.total") == "0", got[-1]
    finally:
        for p in (sender, again, node):
            if p is not None:
                p.stop()
