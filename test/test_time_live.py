"""The shared time policy live, as separate processes over DDS: one wrongly stamped message never
silences a node, and a bag replayed on a looping ``/clock`` gives the same outputs in every pass
(pipeline/time_policy.py)."""
from __future__ import annotations

import subprocess
import sys
import time
from contextlib import contextmanager
from typing import Any, Callable, NamedTuple

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry

from helpers_dds import Peer, child_env, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.nodes.qos import qos_profile
from indoor_loc.wifi.radiomap import save_radiomap
from msg_adapters.diagnostics import diagnostics_from_msg
from msg_adapters.odom import odom_from_msg
from msg_adapters.pose import fix_from_msg
from msg_adapters.wifi_scan import scan_to_msg
from test_wifi_fix_stage import grid_map, scan_at

pytestmark = pytest.mark.timeout(240)   # above the sum of the condition deadlines
S = 1_000_000_000
YEAR_2036_NS = 2_082_758_400 * S


def _node(module: str, *ros_args: str) -> Peer:
    return Peer([sys.executable, "-m", f"indoor_loc.nodes.{module}", "--ros-args", *ros_args], env=child_env())


def _diag_of(diags: list, name: str):
    for arr in reversed(diags):
        d = diagnostics_from_msg(arr)
        if name in d:
            return d[name]
    return None

class _SimClockWifiFix(NamedTuple):
    proc: Peer
    ex: Any
    fixes: list
    now: list          # [the sim clock, ns]: the test may set it back
    send: Callable[..., None]
    values: Callable[[], dict]


@contextmanager
def _wifi_fix_on_sim_clock(tmp_path, *, seed: int, tick_ns: int):
    """``wifi_fix_node`` for /alice on ``use_sim_time`` with a probe publishing ``/clock`` (from 100 s,
    ``tick_ns`` every 50 ms of the wall clock), scans stamped as asked (``send(*stamps_s)``), and
    reading its fixes and its ``/diagnostics`` values; the node must not have raised."""
    from rosgraph_msgs.msg import Clock

    from msg_adapters.time import stamp_from_ns
    map_dir = save_radiomap(grid_map(), tmp_path / "rm")
    node_proc = _node("wifi_fix_node", "-r", "__ns:=/alice", "-p", f"radiomap:={map_dir}", "-p", "use_sim_time:=true")
    rng = np.random.default_rng(seed)
    try:
        with ros_node("probe") as (node, ex):
            fixes: list = []
            diags: list = []
            now = [100 * S]
            clock = node.create_publisher(Clock, "/clock", qos_profile(Qos.RELIABLE))

            def tick() -> None:
                now[0] += tick_ns
                clock.publish(Clock(clock=stamp_from_ns(now[0])))
            node.create_timer(0.05, tick)
            pub = node.create_publisher(DiagnosticArray, "/alice/wifi/scan", qos_profile(Qos.RELIABLE))
            node.create_subscription(PoseWithCovarianceStamped, "/alice/wifi/fix", fixes.append,
                                     qos_profile(Qos.RELIABLE))
            node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: pub.get_subscription_count() > 0 and
                              _diag_of(diags, "/alice/wifi_fix_node") is not None, 60), node_proc.output()

            def send(*stamps_s: float) -> None:
                for t in stamps_s:
                    pub.publish(scan_to_msg(scan_at(rng.uniform(0.5, 9.5, 2), int(t * S))))

            def values() -> dict:
                d = _diag_of(diags, "/alice/wifi_fix_node")
                return dict(d.values) if d else {}
            yield _SimClockWifiFix(node_proc, ex, fixes, now, send, values)
        assert "Traceback" not in node_proc.output()
    finally:
        node_proc.stop()



def test_one_scan_stamped_in_2036_does_not_silence_wifi_fix_node(ros_domain, tmp_path):
    """Scans stamped now, one stamped in 2036 among them: the 2036 one is rejected (future_stamp) and
    every later valid scan is located — before, the node refused every later scan as stamp_backwards
    until it was restarted."""
    map_dir = save_radiomap(grid_map(), tmp_path / "rm")
    node_proc = _node("wifi_fix_node", "-r", "__ns:=/alice", "-p", f"radiomap:={map_dir}")
    rng = np.random.default_rng(4)
    try:
        with ros_node("probe") as (node, ex):
            fixes: list = []
            diags: list = []
            pub = node.create_publisher(DiagnosticArray, "/alice/wifi/scan", qos_profile(Qos.RELIABLE))
            node.create_subscription(PoseWithCovarianceStamped, "/alice/wifi/fix", fixes.append,
                                     qos_profile(Qos.RELIABLE))
            node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: pub.get_subscription_count() > 0 and
                              _diag_of(diags, "/alice/wifi_fix_node") is not None, 60), node_proc.output()

            def send(stamp_ns: int) -> None:
                pub.publish(scan_to_msg(scan_at(rng.uniform(0.5, 9.5, 2), stamp_ns)))
            for _ in range(3):
                send(time.time_ns())
            assert spin_until(ex, lambda: len(fixes) == 3, 30), node_proc.output()
            send(YEAR_2036_NS)
            for _ in range(10):
                send(time.time_ns())
            assert spin_until(ex, lambda: len(fixes) == 13, 30), (len(fixes), node_proc.output())
            assert all(fix_from_msg(f).stamp_ns < YEAR_2036_NS for f in fixes)

            def rejected() -> dict:
                d = _diag_of(diags, "/alice/wifi_fix_node")
                return {k: v for k, v in d.values.items() if k.startswith("rejected.")} if d else {}
            assert spin_until(ex, lambda: rejected().get("rejected.future_stamp") == "1", 30), rejected()
            assert rejected()["rejected.total"] == "1"
        assert "Traceback" not in node_proc.output()
    finally:
        node_proc.stop()


def test_a_bag_played_twice_on_sim_time_gives_the_same_outputs_twice(ros_domain, tmp_path):
    """A simulated walk played in a loop with ``/clock`` into ``use_sim_time`` nodes: at the loop the
    clock goes back, imu_node and wifi_fix_node reset (one WARN each) and the second pass gives the
    same pdr/odom and wifi/fix as the first — before, imu_node refused every IMU message of the second
    pass and wifi_fix_node every scan (non_monotonic_stamp / stamp_backwards), so nothing came."""
    out = tmp_path / "sim"
    subprocess.run([sys.executable, "-m", "indoor_loc.cli", "sim", str(out), "--walkers", "1", "--duration", "16",
                    "--seed", "3"], check=True, capture_output=True, env=child_env())
    common = ["-r", "__ns:=/alice", "--params-file", str(out / "params.yaml"), "-p", "use_sim_time:=true",
              "-p", "sensor_reliability:=reliable"]
    nodes = [_node("imu_node", *common), _node("wifi_fix_node", *common)]
    player = None
    try:
        with ros_node("probe") as (node, ex):
            odoms: list = []
            fixes: list = []
            node.create_subscription(Odometry, "/alice/pdr/odom", odoms.append, qos_profile(Qos.RELIABLE))
            node.create_subscription(PoseWithCovarianceStamped, "/alice/wifi/fix", fixes.append,
                                     qos_profile(Qos.RELIABLE))
            player = Peer([sys.executable, "-m", "indoor_loc.nodes.player_node", str(out / "sim.mcap"), "-r", "2",
                           "--loop", "--clock", "--min-subscribers", "0", "/alice/imu/data_raw=1",
                           "/alice/imu/mag=1", "/alice/wifi/scan=1"], env=child_env())

            def passes(msgs, stamp_of) -> list[list]:
                """The messages split where their stamps go back (one list per pass)."""
                out: list[list] = [[]]
                for m in msgs:
                    if out[-1] and stamp_of(m) < stamp_of(out[-1][-1]):
                        out.append([])
                    out[-1].append(m)
                return out
            odom_stamp = lambda m: odom_from_msg(m).stamp_ns          # noqa: E731
            fix_stamp = lambda m: fix_from_msg(m).stamp_ns            # noqa: E731
            # the third pass has begun: the second one is complete
            assert spin_until(ex, lambda: len(passes(odoms, odom_stamp)) >= 3 and len(passes(fixes, fix_stamp)) >= 3,
                              150), "\n".join(p.output()[-3000:] for p in nodes + [player])
            player.signal()
            for msgs, read in ((odoms, odom_from_msg), (fixes, fix_from_msg)):
                first, second = passes(msgs, lambda m, read=read: read(m).stamp_ns)[:2]
                assert len(first) > 3 and len(first) == len(second)
                # every output, the last of a pass too: the samples published just before /clock goes back
                # are handled in their own pass whether the node takes them before or after the clock's
                # jump (pipeline/time_policy.py, the node's clock going back)
                for a, b in zip(first, second):
                    ra, rb = read(a), read(b)
                    assert ra.stamp_ns == rb.stamp_ns
                    xa = np.array([ra.x, ra.y]) if hasattr(ra, "x") else ra.xy
                    xb = np.array([rb.x, rb.y]) if hasattr(rb, "x") else rb.xy
                    np.testing.assert_allclose(xa, xb, atol=1e-9)
        for p in nodes:
            assert p.wait_seen(r"WARN.*clock jumped back .*state reset", 10), p.output()[-3000:]
            assert "Traceback" not in p.output()
    finally:
        if player is not None:
            player.stop()
        for p in nodes:
            p.stop()


def test_scans_stamped_before_the_clock_went_back_are_located_in_their_own_pass(ros_domain, tmp_path):
    """``use_sim_time``: scans stamped just before ``/clock`` went back that the node takes after its
    clock-jump callback (published before the jump, queued) are located as the old pass's (judged by
    the clock before the jump), and the new pass resets the node once. Before, the reset came at the
    callback and such scans were refused as 80 s in the new clock's future (``future_stamp``), so the
    old pass's last fixes depended on when the node took them."""
    with _wifi_fix_on_sim_clock(tmp_path, seed=5, tick_ns=50_000_000) as w:   # sim time at the wall's pace
        ex, fixes, now, send, values, node_proc = w.ex, w.fixes, w.now, w.send, w.values, w.proc
        send(95, 96, 97, 98)
        assert spin_until(ex, lambda: len(fixes) == 4, 30), node_proc.output()
        now[0] = 10 * S                                     # the clock goes back 90 s
        assert spin_until(ex, lambda: node_proc.wait_seen(r"clock jumped back", 0) is not None, 30), \
            node_proc.output()[-3000:]
        send(99, 99.5)                                      # published before the jump, taken after it
        assert spin_until(ex, lambda: len(fixes) == 6, 20), (len(fixes), node_proc.output()[-3000:])
        send(10.1, 10.2, 10.3)                              # the new pass
        assert spin_until(ex, lambda: len(fixes) == 9, 20), (len(fixes), node_proc.output()[-3000:])
        assert [fix_from_msg(f).stamp_ns for f in fixes] == [
            int(t * S) for t in (95, 96, 97, 98, 99, 99.5, 10.1, 10.2, 10.3)]
        assert spin_until(ex, lambda: values().get("in.wifi/scan.count") == "9", 30), values()
        assert values()["rejected.total"] == "0" and values()["time_jumps"] == "1", values()


def test_a_stamp_far_back_is_no_clock_jump_when_the_clock_lags_the_stamps(ros_domain, tmp_path):
    """``use_sim_time`` with the node's clock seconds behind the stamps it takes (``/clock`` taken late
    by a busy node): one scan stamped 6 s back, at the clock's present, is a straggler (``stale_stamp``),
    not a jump the clock confirms — the clock never went back. Before, the watermark being ahead of
    the clock (and the far-back stamp its present) was taken as the clock having gone back: the user
    was reset at once (``time_jumps`` 1) — the fault benchmark's all-ports trial on sim time reset
    ``imu_node`` 29 times, ``pdr_kf_node`` six."""
    with _wifi_fix_on_sim_clock(tmp_path, seed=6, tick_ns=10_000_000) as w:   # sim time at a fifth of it
        ex, fixes, now, send, values, node_proc = w.ex, w.fixes, w.now, w.send, w.values, w.proc
        base = now[0] / S
        send(base + 4, base + 5, base + 6)                  # the stamps 4-6 s ahead of the node's clock
        assert spin_until(ex, lambda: len(fixes) == 3, 30), node_proc.output()
        send(base + 0.5)                                    # one stamped at the clock's present
        send(base + 7)                                      # and the stream goes on
        assert spin_until(ex, lambda: len(fixes) == 4, 20), (len(fixes), node_proc.output()[-3000:])
        assert fix_from_msg(fixes[-1]).stamp_ns == int((base + 7) * S)
        assert spin_until(ex, lambda: values().get("in.wifi/scan.count") == "5", 30), values()
        assert values()["time_jumps"] == "0" and values()["rejected.stale_stamp"] == "1", values()
