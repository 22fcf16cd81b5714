"""nodes/base.py: StageNode parameters, QoS table, and a dummy stage run as a real node process
(bad messages counted and dropped, /diagnostics once a second, bad parameters -> exit 2)."""
from __future__ import annotations

import math
import os
import signal
import sys
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from sensor_msgs.msg import Imu

from helpers_dds import PEERS, Peer, python_peer, ros_node, spin_until
from indoor_loc.contract import TOPICS, Qos
from indoor_loc.errors import ConfigError
from msg_adapters.diagnostics import diagnostics_from_msg
from msg_adapters.imu import imu_from_msg, imu_to_msg
from msg_adapters.pose import pose_from_msg
from indoor_loc.nodes.base import QOS_PROFILES, StageNode, node_usage, qos_profile, run_stage_node

sys.path.insert(0, str(PEERS))
from dummy_node import DummyStage  # noqa: E402

# a bound for a hung test, above the sum of a test's condition deadlines (which a loaded machine may
# use up one after another), not an expected duration
pytestmark = pytest.mark.timeout(180)


def test_qos_table_covers_every_contract_role():
    assert set(QOS_PROFILES) == set(Qos)
    assert {t.qos for t in TOPICS.values()} <= set(QOS_PROFILES)
    latched = qos_profile(Qos.LATCHED)
    assert latched.durability == DurabilityPolicy.TRANSIENT_LOCAL and latched.reliability == ReliabilityPolicy.RELIABLE
    assert qos_profile(Qos.SENSOR).reliability == ReliabilityPolicy.BEST_EFFORT
    assert qos_profile(Qos.BEST_EFFORT).reliability == ReliabilityPolicy.BEST_EFFORT
    assert qos_profile(Qos.RELIABLE).durability == DurabilityPolicy.VOLATILE


def test_help_prints_usage(capsys):
    assert run_stage_node(DummyStage, ["dummy_node", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.strip() == node_usage(DummyStage)
    assert "gain (default 1.0)" in out and "imu/data_raw [sensor_msgs/msg/Imu]" in out and "/diagnostics" in out


def test_help_names_the_topics_other_parameter_values_select(capsys):
    """A node's --help lists its topics with the default parameters, then the topics each other value
    of a port-changing parameter subscribes or publishes, naming the parameter (the back-end with
    wifi_source fix also takes wifi/fix; the PF with wifi_update scan takes wifi/scan instead of
    wifi/fix; imu_node with heading_source orientation does not publish imu/data; wifi_scan_node
    with an interface tool subscribes nothing)."""
    from indoor_loc.nodes import backend_node, imu_node, tll_pf_node, wifi_scan_node
    expected = {      # module: [(the list it amends, the line's start)]
        backend_node: [("subscribes", "  with wifi_source 'fix' (default 'scan'): also /<user>/wifi/fix "
                                      "[geometry_msgs/msg/PoseWithCovarianceStamped]")],
        tll_pf_node: [("subscribes", "  with wifi_update 'scan' (default 'fix'): wifi/scan "
                                     "[diagnostic_msgs/msg/DiagnosticArray] instead of wifi/fix "
                                     "[geometry_msgs/msg/PoseWithCovarianceStamped]")],
        imu_node: [("publishes", "  with heading_source 'orientation' (default 'auto'): without imu/data "
                                 "[sensor_msgs/msg/Imu]")],
        wifi_scan_node: [("subscribes", "  with source 'iw' or 'nmcli' (default 'topic'): without wifi/scan_raw ")],
    }
    for module, lines in expected.items():
        assert module.main([module.__name__, "--help"]) == 0
        out = capsys.readouterr().out.splitlines()
        for section, want in lines:
            hits = [k for k, line in enumerate(out) if line.startswith(want)]
            assert len(hits) == 1, (module.__name__, want, out[-6:])
            above = next(line for line in reversed(out[:hits[0]]) if not line.startswith("  "))
            assert above.startswith(section + ":"), (module.__name__, out[-6:])


def test_parameters_from_command_line(ros_domain):
    with ros_node("probe") as (probe, _):
        node = StageNode(DummyStage, context=probe.context, namespace="/alice",
                         cli_args=["--ros-args", "-p", "gain:=3", "-p", "weights:=[1.0, 2.5]", "-p", "label:=x"])
        try:
            p = node.stage.params
            assert p.gain == 3.0 and isinstance(p.gain, float)      # int in YAML/CLI -> float field
            assert p.weights == [1.0, 2.5] and p.label == "x" and p.enabled is True
            assert node.stage.namespace == "/alice"
            # live changes: refused (read at start-up), and the descriptors say so
            assert node.describe_parameter("gain").read_only and node.describe_parameter("label").read_only
            res = node.set_parameters([Parameter("gain", value=5.0)])[0]
            assert not res.successful and "read-only" in res.reason
            assert node.set_parameters([Parameter("use_sim_time", value=True)])[0].successful
            assert node.stage.params.gain == 3.0
        finally:
            node.destroy_node()


@pytest.mark.parametrize("overrides,match", [
    ([Parameter("gian", value=1.0)], r"unknown parameter\(s\) \['gian'\]"),
    ([Parameter("gain", value=0.0)], r"gain: expected > 0"),
    ([Parameter("gain", value="fast")], r"gain: expected float"),
    ([Parameter("enabled", value=1)], r"enabled: expected a bool"),
])
def test_invalid_parameters_raise_config_error(ros_domain, overrides, match):
    with ros_node("probe") as (probe, _):
        with pytest.raises(ConfigError, match=match):
            StageNode(DummyStage, context=probe.context, parameter_overrides=overrides)


def test_invalid_parameters_stop_the_process(tmp_path, ros_domain):
    typo = tmp_path / "typo.yaml"
    typo.write_text("/**:\n  ros__parameters:\n    gain: 2.0\n    step_lenght: 0.7\n")
    cases = {
        "range": (["-p", "gain:=-1.0"], "gain: expected > 0, got -1.0"),
        "type": (["-p", "label:=3"], "label: expected str, got 3"),
        "typo": (["--params-file", str(typo)], "unknown parameter(s) ['step_lenght']"),
        "args": (["--params-file", str(tmp_path / "missing.yaml")], "invalid arguments"),
    }
    # four processes starting at once, each then waiting up to 10 s for a /diagnostics subscriber
    # (they see each other) before it exits: on a loaded machine that is well over 20 s
    peers = {k: python_peer("dummy_node.py", "--ros-args", *a) for k, (a, _) in cases.items()}
    for k, peer in peers.items():
        try:
            rc = peer.wait(timeout=90)
        finally:
            peer.stop()
        assert rc == 2, f"{k}: rc {rc}\n{peer.output()}"
        assert cases[k][1] in peer.output(), f"{k}: {peer.output()}"


def test_a_node_that_cannot_start_ends_even_if_its_last_steps_stall():
    """After a start-up error the process ends within a bounded time with the error's status, whatever
    its report and the middleware's shutdown do meanwhile (here: a step that never returns)."""
    import subprocess
    code = ("import time; from indoor_loc.nodes.base import exit_after; "
            "exit_after(0.5, 2, 'stuck_node'); time.sleep(60)")
    t0 = time.monotonic()
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert res.returncode == 2 and time.monotonic() - t0 < 20
    assert "[stuck_node] still not ended 0.5 s after its start-up error: exiting" in res.stderr


def test_a_subscription_that_matched_late_says_so():
    """The first message taken is not its publisher's first: what was published before the
    subscription matched is said once (not counted as a loss: the topic is volatile)."""
    from indoor_loc.nodes.base import SequenceGaps
    said: list[int] = []
    gaps = SequenceGaps(said.append)
    assert gaps.gap({"publication_sequence_number": 478}) == 0
    assert gaps.gap({"publication_sequence_number": 479}) == 0
    assert gaps.gap({"publication_sequence_number": 482}) == 2          # a real gap is a loss
    assert said == [477]
    on_time: list[int] = []
    fresh = SequenceGaps(on_time.append)
    assert fresh.gap({"publication_sequence_number": 1}) == 0 and on_time == []
    # counted before the player's publisher was seen (0): its first message is still the first, and
    # the late start is not said at the next message
    stale = SequenceGaps(on_time.append)
    stale.publishers = 0
    assert stale.gap({"publication_sequence_number": 1}) == 0
    stale.publishers = 1
    assert stale.gap({"publication_sequence_number": 2}) == 0 and on_time == []
    assert stale.gap({"publication_sequence_number": 5}, lambda: 0) == 2     # a stale count hides no loss
    two = SequenceGaps(on_time.append)
    two.publishers = 2                       # two publishers: their numbers interleave, nothing is said
    assert two.gap({"publication_sequence_number": 40}) == 0 and two.gap({"publication_sequence_number": 7}) == 0
    assert on_time == []


def test_losses_between_two_publishers_numbers_are_counted():
    """Two publishers on one topic (a node's odometry and a flood from another): rclpy does not say
    which message is whose, yet the gaps in each one's numbers are counted, and a publisher joining
    or restarting is not a loss."""
    from indoor_loc.nodes.liveness import SequenceGaps

    def info(n):
        return {"publication_sequence_number": n}
    gaps = SequenceGaps()
    gaps.publishers = 2
    odom = [1, 2, 3, 4, 7, 8, 9, 10]                     # lost 5, 6
    flood = list(range(1, 301))
    del flood[100:140]                                   # lost 40 in a burst
    rng = np.random.default_rng(3)
    merged, i, j = [], 0, 0
    while i < len(odom) or j < len(flood):
        if j >= len(flood) or (i < len(odom) and rng.random() < 0.05):
            merged.append(odom[i])
            i += 1
        else:
            merged.append(flood[j])
            j += 1
    assert sum(gaps.gap(info(n)) for n in merged) == 2 + 40
    # a second publisher appearing mid-stream (counted alone so far): its numbers are not a loss
    joined = SequenceGaps()
    assert joined.gap(info(1)) == 0 and joined.gap(info(2)) == 0
    assert joined.gap(info(50), lambda: 2) == 0                # the graph says: two publishers now
    assert joined.gap(info(3)) == 0 and joined.gap(info(51)) == 0
    assert joined.gap(info(6)) == 2                             # 4 and 5 of the first one lost
    # one of them restarting (numbers below every run): not a loss either
    assert joined.gap(info(1)) == 0 and joined.gap(info(2)) == 0


def test_startup_error_is_an_error_in_diagnostics(ros_domain, tmp_path):
    """A node that cannot start (here: its radio map does not exist) exits 2 and says so in
    /diagnostics as ERROR under its own name, not only on stderr."""
    ns = f"/badstart{os.getpid()}"
    got: list[tuple[int, str, str]] = []
    with ros_node("monitor") as (mon, ex):
        def on_diag(msg: DiagnosticArray) -> None:
            got.extend((st.level[0], st.name, st.message) for st in msg.status)
        mon.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos_profile(Qos.RELIABLE))
        peer = Peer([sys.executable, "-m", "indoor_loc.nodes.wifi_fix_node", "--ros-args", "-r", f"__ns:={ns}",
                     "-p", f"radiomap:={tmp_path / 'missing'}"])
        try:
            assert spin_until(ex, lambda: any(name == f"{ns}/wifi_fix_node" for _, name, _ in got), 60), \
                (got, peer.output())
            assert peer.wait(timeout=30) == 2, peer.output()
        finally:
            peer.stop()
    level, name, message = next(g for g in got if g[1] == f"{ns}/wifi_fix_node")
    assert level == 2 and "configuration error" in message and "missing" in message, (level, message)
    assert "configuration error" in peer.output()                     # and on stderr, as before


def _bad(kind: str, stamp_ns: int) -> Imu:
    msg = imu_to_msg(stamp_ns, "alice/imu_link", [1.0, 2.0, 9.8], [0.0, 0.0, 0.1])
    if kind == "nan_acc":
        msg.linear_acceleration.x = math.nan
    elif kind == "inf_gyro":
        msg.angular_velocity.z = math.inf
    elif kind == "negative_stamp":
        msg.header.stamp.sec = -1
    return msg


def test_live_node_drops_bad_messages_and_reports_diagnostics(ros_domain, tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("/alice/dummy_node:\n  ros__parameters:\n    gain: 2.5\n    label: live\n")
    peer = python_peer("dummy_node.py", "--ros-args", "-r", "__ns:=/alice", "--params-file", str(params))
    try:
        with ros_node("probe") as (node, ex):
            poses: list[PoseWithCovarianceStamped] = []
            diags: list[tuple[float, dict]] = []

            def on_diag(msg: DiagnosticArray) -> None:
                d = diagnostics_from_msg(msg)
                if "/alice/dummy_node" in d:      # when the node published it (its clock), not when we got it
                    diags.append((msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, d["/alice/dummy_node"]))

            matched: list[int] = []     # the writer has matched the node's reader (not just the graph)
            pub = node.create_publisher(Imu, "/alice/imu/data_raw", qos_profile(Qos.RELIABLE),
                                        event_callbacks=PublisherEventCallbacks(
                                            matched=lambda st: matched.append(st.current_count)))
            node.create_subscription(PoseWithCovarianceStamped, "/alice/dummy/pose", poses.append,
                                     qos_profile(Qos.RELIABLE))
            node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: bool(matched) and matched[-1] > 0
                              and node.count_publishers("/alice/dummy/pose") > 0 and len(diags) > 0, 40), \
                peer.output()

            good = [(1_000_000_000 + i, np.array([0.5 * i, -1.0 - i, 9.8])) for i in range(3)]
            sequence = [imu_to_msg(good[0][0], "f", good[0][1]), _bad("nan_acc", good[0][0]),
                        _bad("inf_gyro", good[0][0]),
                        imu_to_msg(good[1][0], "f", good[1][1]), _bad("negative_stamp", 0),
                        imu_to_msg(good[2][0], "f", good[2][1])]
            for msg in sequence:
                pub.publish(msg)
            assert spin_until(ex, lambda: len(poses) == 3, 30), peer.output()
            for (stamp, acc), msg in zip(good, poses):
                p = pose_from_msg(msg)
                assert p.stamp_ns == stamp and np.array_equal(p.xy, 2.5 * acc[:2])

            def counted() -> bool:
                return bool(diags) and diags[-1][1].values.get("rejected.total") == "3"
            assert spin_until(ex, counted, 20)
            n0 = len(diags)
            assert spin_until(ex, lambda: len(diags) >= n0 + 3, 20)
            # about once a second (loose: shared CPUs): the mean period, since a tick the node made late
            # (a stall) is followed by one as much early (the timer keeps its phase)
            gaps = np.diff([t for t, _ in diags[n0 - 1:]])
            assert 0.7 < np.mean(gaps) < 1.4 and np.all(gaps < 3.0), gaps
            d = diags[-1][1]
            assert d.level == 1 and "3 messages rejected" in d.message
            assert d.values["rejected.nan"] == "2" and d.values["rejected.negative_stamp"] == "1"
            assert d.values["in.imu/data_raw.count"] == "6" and d.values["out.dummy/pose.count"] == "3"
            assert d.values["gain"] == "2.5" and d.values["label"] == "live"
            assert peer.proc.poll() is None, "node died on a bad message"

            # SIGINT: the node publishes the stage's finish() outputs before it goes
            peer.signal(signal.SIGINT)
            assert spin_until(ex, lambda: len(poses) == 4, 30), peer.output()
            assert pose_from_msg(poses[-1]).stamp_ns == 3          # DummyStage.finish(): accepted count
        assert peer.wait(timeout=15) == 0, peer.output()
        assert "dropped message (nan" in peer.output()
        assert "Traceback" not in peer.output()
    finally:
        peer.stop()


class _BuggyStage(DummyStage):
    """Returns an undeclared topic, then a wrong message class for a declared one."""
    NODE_NAME = "buggy_node"

    def _on_imu(self, msg, recv_ns):
        imu_from_msg(msg)
        return [("nope", msg), ("dummy/pose", msg)]


def test_stage_bugs_are_counted_not_fatal(ros_domain):
    with ros_node("probe") as (probe, _):
        node = StageNode(_BuggyStage, context=probe.context)
        try:
            cb = node._callback("imu/data_raw")
            cb(imu_to_msg(5, "f", [0.0, 0.0, 9.8]), {})
            cb(_bad("nan_acc", 6), {})
            assert node.stage.diag.rejected == {"internal_error": 2, "nan": 1}
            d = diagnostics_from_msg(node.diagnostics_msg(7))["/buggy_node"]
            assert d.values["rejected.internal_error"] == "2" and d.level == 2    # ERROR while recent
        finally:
            node.destroy_node()


def test_lost_messages_are_counted_and_warnings_follow_a_recent_window(ros_domain):
    with ros_node("probe") as (probe, _):
        node = StageNode(DummyStage, context=probe.context)
        try:
            writers = [1]
            node._publisher_gids = lambda topic: frozenset([b"w1", b"w2"][:writers[0]])   # one publisher in the graph
            node._gaps["imu/data_raw"].publishers = 1
            cb = node._callback("imu/data_raw")
            for seq in (1, 2, 6, 7):                                  # 3 messages never arrived
                cb(imu_to_msg(seq, "f", [0.0, 0.0, 9.8]), {"publication_sequence_number": seq})
            cb(_bad("nan_acc", 8), {"publication_sequence_number": 8})
            now = node.get_clock().now().nanoseconds
            d = diagnostics_from_msg(node.diagnostics_msg(now))["/dummy_node"]
            assert d.values["lost.imu/data_raw"] == "3" and d.values["lost.total"] == "3"
            assert d.level == 1 and "3 input messages lost" in d.message and "1 messages rejected" in d.message
            later = diagnostics_from_msg(node.diagnostics_msg(now + 11_000_000_000))["/dummy_node"]
            assert later.values["lost.total"] == "3" and "lost" not in later.message   # counters stay, WARN does not
            assert later.level == 1 and later.values["in.imu/data_raw.state"] == "stalled"   # 11 s without input
            writers[0] = 2                                                    # a second writer joined:
            node._gaps["imu/data_raw"].publishers = 1                         # seen at the gap, no guessing
            cb(imu_to_msg(9, "f", [0.0, 0.0, 9.8]), {"publication_sequence_number": 20})
            assert node.stage.diag.lost["imu/data_raw"] == 3
        finally:
            node.destroy_node()


def test_sigint_processes_what_was_already_received(ros_domain):
    """Messages DDS delivered before SIGINT are processed, not dropped: the node is stopped
    (SIGSTOP) while 900 messages (within its 1000-deep queue) are sent, resumed, and told to stop as soon as they are
    delivered; its finish() pose carries the count it accepted."""
    n = 900
    peer = python_peer("dummy_node.py", "--ros-args", "-r", "__ns:=/drain")
    try:
        with ros_node("probe") as (node, ex):
            poses: list[PoseWithCovarianceStamped] = []
            matched: list[int] = []
            pub = node.create_publisher(Imu, "/drain/imu/data_raw", qos_profile(Qos.RELIABLE).__class__(
                depth=n, reliability=ReliabilityPolicy.RELIABLE), event_callbacks=PublisherEventCallbacks(
                    matched=lambda st: matched.append(st.current_count)))
            node.create_subscription(PoseWithCovarianceStamped, "/drain/dummy/pose", poses.append,
                                     qos_profile(Qos.RELIABLE).__class__(depth=n + 10,
                                                                         reliability=ReliabilityPolicy.RELIABLE))
            assert spin_until(ex, lambda: bool(matched) and matched[-1] > 0
                              and node.count_publishers("/drain/dummy/pose") > 0, 30), peer.output()
            assert spin_until(ex, lambda: any("dummy_node up" in ln for ln in peer.lines), 30)
            peer.signal(signal.SIGSTOP)
            for i in range(n):
                pub.publish(imu_to_msg(1_000_000_000 + i, "f", np.array([0.1, 0.2, 9.8])))
            peer.signal(signal.SIGCONT)
            from rclpy.duration import Duration
            assert pub.wait_for_all_acked(Duration(seconds=20))     # all in the node's queue
            peer.signal(signal.SIGINT)
            assert peer.wait(timeout=30) == 0, peer.output()
            assert spin_until(ex, lambda: len(poses) >= n + 1, 30), (len(poses), peer.output()[-2000:])
            assert pose_from_msg(poses[-1]).stamp_ns == n          # finish(): every message accepted
    finally:
        peer.stop()
