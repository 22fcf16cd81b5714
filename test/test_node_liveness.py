"""Input liveness: per input, waiting / flowing / stalled on the node's clock, upstream restarts (its
sequence numbers anew, or another publisher in the graph), the gap; in ``/diagnostics`` as
``in.<topic>.*``, WARN for a stalled input (ERROR if required) and for a recent restart. The rules
without DDS, then a publisher process killed and started again under a live node."""
from __future__ import annotations

import signal
import sys

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.serialization import serialize_message

from helpers_dds import PEERS, python_peer, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.nodes.liveness import FLOWING, RECEIVED, STALLED, WAITING, InputWatch
from indoor_loc.nodes.qos import qos_profile
from msg_adapters.diagnostics import diagnostics_from_msg, status_array, with_inputs
from msg_adapters.imu import imu_to_msg

sys.path.insert(0, str(PEERS))
from raw_sender import write_samples  # noqa: E402

pytestmark = pytest.mark.timeout(120)

S = 1_000_000_000
T = 100 * S


def _seq(n: int) -> dict:
    return {"publication_sequence_number": n}


def _flow(w: InputWatch, seqs, t0: int, period_ns: int, gids=None) -> int:
    """Messages numbered ``seqs`` every ``period_ns`` from ``t0``; returns the time of the last."""
    t = t0
    for k, n in enumerate(seqs):
        t = t0 + k * period_ns
        w.message(_seq(n), t, (lambda: gids) if gids is not None else None)
    return t


def test_an_input_flows_then_stalls_after_three_periods_or_the_floor():
    w = InputWatch("imu/data_raw", required=True)
    assert w.state(0) == WAITING and w.state(T) == WAITING
    last = _flow(w, range(1, 11), T, S // 10)                       # 10 Hz
    assert w.state(last + S) == FLOWING
    assert w.state(last + 19 * S // 10) == FLOWING and w.state(last + 21 * S // 10) == STALLED   # the 2 s floor
    r = w.report(last + 3 * S)
    assert r.state == STALLED and r.required and r.age_s == pytest.approx(3.0) and r.stall_after_s == 2.0
    slow = InputWatch("wifi/scan")
    last = _flow(slow, range(1, 6), T, 4 * S)                        # a scan every 4 s
    assert slow.state(last + 11 * S) == FLOWING and slow.state(last + 13 * S) == STALLED
    assert slow.report(last + 13 * S).stall_after_s == 12.0
    # the flow resumes: the gap is kept, the period measured afresh
    slow.message(_seq(6), last + 20 * S)
    assert slow.state(last + 20 * S) == FLOWING and slow.last_gap_ns == 20 * S and slow.restarts == 0


def test_no_clock_yet_is_waiting_and_an_occasional_input_never_stalls():
    w = InputWatch("pdr/odom")
    w.message(_seq(1), 0)                         # sim time before /clock
    assert w.state(0) == WAITING and w.report(0).age_s is None
    pose = InputWatch("initialpose", stream=False)
    pose.message(_seq(1), T)
    pose.message(_seq(2), T + S)
    assert pose.state(T + 1000 * S) == RECEIVED


def test_a_publisher_restarted_counts_once_from_its_numbers_and_the_graph():
    w = InputWatch("pdr/odom")
    w.publishers_seen(frozenset({b"g1"}), T)
    last = _flow(w, range(1, 21), T, S // 10, frozenset({b"g1"}))
    # killed: g1 lingers in the graph (no goodbye); 3 s later another publisher numbers from 1
    w.publishers_seen(frozenset({b"g1"}), last + S)
    restart = last + 3 * S
    lost = [w.message(_seq(n), restart + k * S // 10, lambda: frozenset({b"g1", b"g2"})) for k, n in enumerate(range(1, 6))]
    assert w.restarts == 1 and w.last_restart_ns == restart and not any(lost)
    assert w.last_gap_ns == 3 * S
    w.publishers_seen(frozenset({b"g1", b"g2"}), restart + S)       # the new one in the graph: same restart
    w.publishers_seen(frozenset({b"g2"}), restart + 20 * S)        # the old one's lease ends
    assert w.restarts == 1


def test_a_restart_seen_in_the_graph_first_and_its_first_numbers_missed_is_not_a_loss():
    w = InputWatch("wifi/fix")
    w.publishers_seen(frozenset({b"g1"}), T)
    last = _flow(w, range(1, 6), T, S, frozenset({b"g1"}))
    w.publishers_seen(frozenset(), last + S)                          # it left cleanly
    w.publishers_seen(frozenset({b"g2"}), last + 2 * S)               # another came
    assert w.restarts == 1
    assert w.message(_seq(40), last + 3 * S, lambda: frozenset({b"g2"})) == 0   # published before we matched
    assert w.restarts == 1 and w.message(_seq(42), last + 4 * S, lambda: frozenset({b"g2"})) == 1   # a real gap


def test_interleaved_publishers_are_neither_restarts_nor_losses():
    w = InputWatch("imu/data")
    both = frozenset({b"g1", b"g2"})
    w.publishers_seen(both, T)
    t = T
    for n in range(1, 30):
        for _ in range(2):                        # 1, 1, 2, 2, ... from two writers at 20 Hz
            t += S // 20
            assert w.message(_seq(n), t, lambda: both) == 0
    assert w.restarts == 0 and w.state(t) == FLOWING


def _level(arr: DiagnosticArray) -> int:
    return next(iter(diagnostics_from_msg(arr).values())).level


def test_diagnostics_say_stalled_inputs_and_recent_restarts():
    ok = InputWatch("wifi/fix")
    req = InputWatch("pdr/odom", required=True)
    for w in (ok, req):
        _flow(w, range(1, 11), T, S // 10)
    now = T + 2 * S
    arr = with_inputs(status_array("/n", 0, "ok", {}, now), [ok.report(now), req.report(now)], now)
    d = next(iter(diagnostics_from_msg(arr).values()))
    assert d.level == 0 and d.message == "ok" and d.values["in.pdr/odom.state"] == FLOWING
    assert d.values["in.pdr/odom.upstream_restarts"] == "0" and d.values["in.pdr/odom.age_s"] == "1.10"
    later = T + 5 * S
    assert _level(with_inputs(status_array("/n", 0, "ok", {}, later), [ok.report(later)], later)) == 1
    arr = with_inputs(status_array("/n", 0, "ok", {}, later), [ok.report(later), req.report(later)], later)
    d = next(iter(diagnostics_from_msg(arr).values()))
    assert d.level == 2 and "pdr/odom stalled (no message for 4.1 s)" in d.message
    # a restart: WARN while recent, then OK with the count kept
    req.message(_seq(1), later)
    assert req.restarts == 1
    arr = with_inputs(status_array("/n", 0, "ok", {}, later), [req.report(later)], later)
    d = next(iter(diagnostics_from_msg(arr).values()))
    assert d.level == 1 and "pdr/odom: upstream restarted (1; 4.1 s without input)" in d.message
    much_later = later + 11 * S
    req.message(_seq(2), much_later - S // 10)
    arr = with_inputs(status_array("/n", 0, "ok", {}, much_later), [req.report(much_later)], much_later)
    d = next(iter(diagnostics_from_msg(arr).values()))
    assert d.level == 0 and d.values["in.pdr/odom.upstream_restarts"] == "1"


def _imu_samples(path, first: int, n: int) -> None:
    write_samples(path, [serialize_message(imu_to_msg(first + i * 50_000_000, "f", [0.1, 0.2, 9.8]))
                         for i in range(n)])


def test_a_killed_publisher_is_a_stall_and_its_restart_is_counted(ros_domain, tmp_path):
    """Live: a dummy node process and a publisher process at 20 Hz; the publisher killed (SIGKILL) ->
    the node's /diagnostics says the input stalled (WARN) within a few seconds; started again ->
    flowing, one upstream restart, the gap shown."""
    first, second = tmp_path / "first.bin", tmp_path / "second.bin"
    _imu_samples(first, S, 1200)
    _imu_samples(second, 200 * S, 1200)
    node = python_peer("dummy_node.py", "--ros-args", "-r", "__ns:=/live")
    sender = python_peer("raw_sender.py", str(first), "/live/imu/data_raw", "sensor_msgs/msg/Imu", "0.05")
    again = None
    try:
        with ros_node("monitor") as (mon, ex):
            got: list = []

            def on_diag(msg: DiagnosticArray) -> None:
                d = diagnostics_from_msg(msg).get("/live/dummy_node")
                if d is not None:
                    got.append(d)
            mon.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos_profile(Qos.RELIABLE))

            def latest(key: str) -> str:
                return got[-1].values.get(f"in.imu/data_raw.{key}", "") if got else ""
            assert spin_until(ex, lambda: latest("state") == FLOWING, 40), node.output()[-2000:]
            assert got[-1].level == 0
            sender.signal(signal.SIGKILL)
            n = len(got)
            assert spin_until(ex, lambda: len(got) > n and latest("state") == STALLED, 8), [g.values for g in got[-3:]]
            assert got[-1].level == 1 and "imu/data_raw stalled" in got[-1].message
            again = python_peer("raw_sender.py", str(second), "/live/imu/data_raw", "sensor_msgs/msg/Imu", "0.05")
            assert spin_until(ex, lambda: latest("state") == FLOWING and latest("upstream_restarts") == "1", 30), \
                (got[-1].values, node.output()[-2000:])
            assert float(latest("last_gap_s")) >= 2.0 and "upstream restarted (1" in got[-1].message
            assert got[-1].values["lost.total"] == "0"
    finally:
        for p in (sender, again, node):
            if p is not None:
                p.stop()


def test_a_multi_user_node_reports_each_users_inputs_and_a_user_who_left(ros_domain):
    from dummy_node import DummyStage
    from indoor_loc.nodes.stage_node import StageNode

    class Users(DummyStage):
        NODE_NAME = "users_node"
        MULTI_USER = True

        def _on_imu(self, msg, recv_ns, user=None):
            return []

    with ros_node("probe") as (probe, _):
        node = StageNode(Users, context=probe.context)
        try:
            for user in ("dan", "eve"):
                node._follow(user)
                cb = node._callback("imu/data_raw", user)
                for n in range(1, 4):
                    cb(imu_to_msg(S + n, "f", [0.0, 0.0, 9.8]), _seq(n))
            now = node.get_clock().now().nanoseconds
            d = diagnostics_from_msg(node.diagnostics_msg(now + S))["/users_node"]
            assert d.level == 0 and d.values["in.dan/imu/data_raw.state"] == FLOWING
            assert d.values["in.eve/imu/data_raw.count"] == "3"
            node._finished_users.add("dan")                     # dan left; eve went quiet
            d = diagnostics_from_msg(node.diagnostics_msg(now + 5 * S))["/users_node"]
            assert d.values["in.dan/imu/data_raw.state"] == "left" and d.values["in.eve/imu/data_raw.state"] == STALLED
            assert d.level == 1 and "eve/imu/data_raw stalled" in d.message and "dan" not in d.message
        finally:
            node.destroy_node()
