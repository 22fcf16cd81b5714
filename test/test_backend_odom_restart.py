"""``backend_node`` takes a restarted odometry producer (``imu_node`` killed and started again: a new
publisher, its poses from its own origin and heading) as a new odometry frame, as ``pdr_kf_node`` and
``tll_pf`` do (``test_odom_restart.py``): its first pose is taken at once (no ``odom_jump``), walks
nothing across the restart and turns nothing; the hops after it go on from the user's track.
The rule without DDS, then live: ``backend_node`` with one odometry publisher process after another."""
from __future__ import annotations

import math
import sys

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from helpers_dds import PEERS, Peer, child_env, follow_diagnostics, python_peer, ros_node, spin_until
from indoor_loc.measurements import Fix
from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
from msg_adapters.odom import odom_to_msg
from msg_adapters.pose import fix_to_msg, pose_from_msg

sys.path.insert(0, str(PEERS))
from raw_sender import write_samples  # noqa: E402

S = 1_000_000_000
HOP = S // 5                 # a hop every 0.2 s of stamps
STEP = 0.3                   # m per hop: the user walks along the map's x at 1.5 m/s
N1, N2 = 150, 60             # hops of the first producer (45 m), of the restarted one (18 m)
TURN = math.pi / 2           # the restarted producer's heading frame, turned from the first's


def _odom(k: int, d: float, frame_yaw: float) -> object:
    """Hop ``k`` (its stamp), ``d`` m along the walk from the producer's origin, in a frame whose x
    is the walk's direction turned by ``frame_yaw``."""
    c, s = math.cos(frame_yaw), math.sin(frame_yaw)
    return odom_to_msg(S + k * HOP, "rs/odom", "rs/base_link", d * c, d * s, frame_yaw,
                       np.diag([0.01, 0.01, 0.01]), 1.5, 0.0)


def _streams() -> tuple[list, list]:
    first = [_odom(k, STEP * k, 0.0) for k in range(1, N1 + 1)]
    second = [_odom(N1 + k, STEP * k, TURN) for k in range(1, N2 + 1)]
    return first, second


def _fixes() -> list:
    """The truth every 2 s of the first producer's stretch (none after the restart: the track there
    is the odometry's alone)."""
    return [fix_to_msg(Fix(S + k * HOP, np.array([STEP * k, 0.0]), np.eye(2))) for k in range(10, N1 + 1, 10)]


def _params() -> BackendParams:
    return BackendParams(window_poses=0, wifi_source="fix", joint=False, wifi_info=1.0)


def _last_xy(outs: list) -> np.ndarray:
    return pose_from_msg([m for t, m in outs if t == "backend/rs/pose"][-1]).xy


def test_backend_takes_a_restarted_odometry_as_a_new_frame():
    """Before: the restarted producer's poses (45 m from the last one) were refused as ``odom_jump``
    until their stamps allowed the distance, then the hop across the restart walked the user 45 m
    back and turned it by the frames' difference: the track ended tens of metres off."""
    first, second = _streams()
    fixes = {S + k * HOP: m for k, m in zip(range(10, N1 + 1, 10), _fixes())}
    st = BackendStage(_params())
    outs: list = []
    for m in first:
        outs += st.process("pdr/odom", m, 0, "rs")
        stamp = m.header.stamp.sec * S + m.header.stamp.nanosec
        if stamp in fixes:
            outs += st.process("wifi/fix", fixes[stamp], 0, "rs")
    st.run_upstream_restarted("pdr/odom", "rs")
    for m in second:
        outs += st.process("pdr/odom", m, 0, "rs")
    assert st.diag.rejected["odom_jump"] == 0 and sum(st.diag.rejected.values()) == 0, dict(st.diag.rejected)
    assert any("restarted" in n for n in st.take_notices())
    truth = np.array([STEP * (N1 + N2), 0.0])
    err = float(np.linalg.norm(_last_xy(outs) - truth))
    assert err < 3.0, (_last_xy(outs), truth)


def test_a_restart_before_any_odometry_changes_nothing():
    """A restart seen before the user's first pose (the node joined a producer that restarted) is no
    new frame: nothing to start afresh."""
    st = BackendStage(_params())
    st.run_upstream_restarted("pdr/odom", "rs")
    assert "rs" not in st.inputs_by_user and not st.take_notices()


@pytest.mark.timeout(240)
def test_live_backend_node_takes_a_restarted_producers_odometry_at_once(ros_domain, tmp_path):
    """Before: ``rejected.odom_jump`` counted the restarted producer's first poses."""
    first, second = _streams()
    f1, f2 = tmp_path / "first.bin", tmp_path / "second.bin"
    write_samples(f1, [serialize_message(m) for m in first])
    write_samples(f2, [serialize_message(m) for m in second])
    params = tmp_path / "params.yaml"
    params.write_text("/**/backend_node:\n  ros__parameters:\n    wifi_source: fix\n    joint: false\n"
                      "    users: [rs]\n    user_timeout_s: 120.0\n")
    node = Peer([sys.executable, "-m", "indoor_loc.nodes.backend_node", "--ros-args", "--params-file",
                 str(params)], env=child_env())
    sender = python_peer("raw_sender.py", str(f1), "/rs/pdr/odom", "nav_msgs/msg/Odometry", "0.02")
    again = None
    try:
        with ros_node("monitor") as (mon, ex):
            got, value = follow_diagnostics(mon, "/backend_node")
            assert spin_until(ex, lambda: value("in.rs/pdr/odom.count") == str(len(first)), 150), \
                (got[-1:], node.output()[-2000:])
            assert sender.proc.wait(timeout=20) == 0
            again = python_peer("raw_sender.py", str(f2), "/rs/pdr/odom", "nav_msgs/msg/Odometry", "0.02")
            assert spin_until(ex, lambda: value("in.rs/pdr/odom.count") == str(len(first) + len(second)), 40), \
                (got[-1:], node.output()[-2000:])
            assert value("in.rs/pdr/odom.upstream_restarts") == "1", got[-1]
            assert value("rejected.odom_jump") in ("", "0"), got[-1]
            assert value("rejected.total") == "0", got[-1]
    finally:
        for p in (sender, again, node):
            if p is not None:
                p.stop()
