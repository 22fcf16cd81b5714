"""backend_node live over DDS: one node, users discovered from the ROS graph as they appear, a
user leaving gets its path published, SIGINT publishes every user's final path."""
from __future__ import annotations

import signal
import sys
import time

import numpy as np

import pytest

from backend_synth import SEC, corridor_walk, delay_fixes, survey
from helpers_dds import Peer, child_env, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.imu.pdr import Pdr, PdrParams
from indoor_loc.nodes.base import qos_profile
from indoor_loc.wifi.radiomap import save_radiomap
from msg_adapters.odom import odom_to_msg
from msg_adapters.path import path_from_msg
from msg_adapters.wifi_scan import scan_to_msg


# a bound for a hung test, above the sum of a test's condition deadlines (which a loaded machine may
# use up one after another), not an expected duration
pytestmark = pytest.mark.timeout(420)


def _messages(walk):
    pdr = Pdr(PdrParams(step_length_m=0.65))
    out = []
    for _, kind, payload in walk.events:
        if kind == 0:
            p = pdr.update(*payload)
            out.append(("pdr/odom", odom_to_msg(p.stamp_ns, "odom", "base_link", p.x, p.y, p.yaw, p.cov,
                                                p.speed, p.yaw_rate)))
        else:
            out.append(("wifi/scan", scan_to_msg(payload)))
    return out


def test_users_join_and_leave_live(ros_domain, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry, Path

    rm = save_radiomap(survey(0, 60, np.random.default_rng(1)), tmp_path / "map")
    params = tmp_path / "params.yaml"
    params.write_text(f"/**/backend_node:\n  ros__parameters:\n    radiomap: {rm}\n    user_timeout_s: 2.0\n"
                      "    wknn: {shared_threshold: 0.75, shared_strict: false}\n")
    node_proc = Peer([sys.executable, "-m", "indoor_loc.nodes.backend_node", "--ros-args", "--params-file",
                      str(params)], env=child_env())
    rng = np.random.default_rng(31)
    walks = {"alice": corridor_walk("alice", 2, 30, 0, rng), "bob": corridor_walk("bob", 40, 20, 3 * SEC, rng)}
    try:
        with ros_node("probe") as (node, ex):
            got: dict[str, list] = {f"{u}/{k}": [] for u in walks for k in ("pose", "path")}
            for key, lst in got.items():
                user, kind = key.split("/")
                node.create_subscription(PoseWithCovarianceStamped if kind == "pose" else Path,
                                         f"/backend/{user}/{kind}", lst.append,
                                         qos_profile(Qos.RELIABLE if kind == "pose" else Qos.LATCHED))
            diags: list = []
            node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: node.count_publishers("/diagnostics") > 0, 60), node_proc.output()

            def join(user):
                pubs = {"pdr/odom": node.create_publisher(Odometry, f"/{user}/pdr/odom", qos_profile(Qos.RELIABLE)),
                        "wifi/scan": node.create_publisher(DiagnosticArray, f"/{user}/wifi/scan",
                                                           qos_profile(Qos.RELIABLE))}
                # the node discovers the user from the graph and subscribes: wait for its readers
                assert spin_until(ex, lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 40), \
                    node_proc.output()
                for topic, msg in _messages(walks[user]):
                    pubs[topic].publish(msg)
                    spin_until(ex, lambda: False, 0.002)
                return pubs

            alice = join("alice")
            assert spin_until(ex, lambda: len(got["alice/pose"]) > 5, 40), node_proc.output()
            bob = join("bob")                                   # a second user joins later
            assert spin_until(ex, lambda: len(got["bob/pose"]) > 5, 40), node_proc.output()
            # the node's log reaches us through a pipe, its messages through DDS: either can come first
            assert node_proc.wait_seen(r"following user 'bob'", 30), node_proc.output()

            # alice leaves: her publishers go; after user_timeout_s her whole path is published
            for p in alice.values():
                node.destroy_publisher(p)
            assert spin_until(ex, lambda: len(got["alice/path"]) >= 1, 40), node_proc.output()
            stamps, xy, _ = path_from_msg(got["alice/path"][-1])
            truth = walks["alice"].true_xy_at(stamps)
            assert len(stamps) > 10 and np.mean(np.linalg.norm(xy - truth, axis=1)) < 1.5
            assert node_proc.wait_seen(r"user 'alice' left", 30), node_proc.output()
            assert not got["bob/path"]                          # bob is still there

            # SIGINT: every user's final (whole-graph optimised) path goes out before the node ends
            n_alice = len(got["alice/path"])
            node_proc.signal(signal.SIGINT)
            assert spin_until(ex, lambda: len(got["bob/path"]) >= 1 and len(got["alice/path"]) > n_alice, 60), \
                node_proc.output()
            stamps, xy, _ = path_from_msg(got["bob/path"][-1])
            assert np.mean(np.linalg.norm(xy - walks["bob"].true_xy_at(stamps), axis=1)) < 1.5
            del bob
        assert node_proc.wait(timeout=40) == 0, node_proc.output()
        assert "Traceback" not in node_proc.output()
    finally:
        node_proc.stop()


def test_a_fixed_user_list_is_followed_and_nobody_else(ros_domain, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry

    rm = save_radiomap(survey(0, 60, np.random.default_rng(1)), tmp_path / "map")
    params = tmp_path / "params.yaml"
    params.write_text(f"/**/backend_node:\n  ros__parameters:\n    radiomap: {rm}\n    users: [carol]\n"
                      "    wknn: {shared_threshold: 0.75, shared_strict: false}\n")
    node_proc = Peer([sys.executable, "-m", "indoor_loc.nodes.backend_node", "--ros-args", "--params-file",
                      str(params)], env=child_env())
    rng = np.random.default_rng(32)
    try:
        with ros_node("probe") as (node, ex):
            poses: dict[str, list] = {"carol": [], "dave": []}
            for u, lst in poses.items():
                node.create_subscription(PoseWithCovarianceStamped, f"/backend/{u}/pose", lst.append,
                                         qos_profile(Qos.RELIABLE))
            pubs = {(u, t): node.create_publisher(Odometry if t == "pdr/odom" else DiagnosticArray, f"/{u}/{t}",
                                                  qos_profile(Qos.RELIABLE))
                    for u in poses for t in ("pdr/odom", "wifi/scan")}
            assert spin_until(ex, lambda: all(pubs[("carol", t)].get_subscription_count() > 0
                                              for t in ("pdr/odom", "wifi/scan")), 60), node_proc.output()
            spin_until(ex, lambda: False, 2.5)          # two discovery rounds: dave must not be followed
            assert all(pubs[("dave", t)].get_subscription_count() == 0 for t in ("pdr/odom", "wifi/scan"))
            for u in poses:
                for topic, msg in _messages(corridor_walk(u, 2, 30, 0, rng)):
                    pubs[(u, topic)].publish(msg)
                    spin_until(ex, lambda: False, 0.002)
            assert spin_until(ex, lambda: len(poses["carol"]) > 5, 40), node_proc.output()
            spin_until(ex, lambda: False, 1.0)
            assert poses["dave"] == []
        assert node_proc.wait_seen(r"following user 'carol'", 30), node_proc.output()
        assert "'dave'" not in node_proc.output()
    finally:
        node_proc.stop()


def test_front_end_fixes_live(ros_domain, tmp_path):
    """``wifi_source: fix`` over DDS without a survey, from a slow WiFi node: each fix is published
    only once the odometry is 2 s (stamp time) past it — four times the reorder window. The node
    subscribes to the user's ``wifi/fix`` too, starts the user at its first fix, publishes poses as
    the walk goes, loses no fix (counted as waited for in ``/diagnostics``) and, when the user leaves,
    publishes the path the same messages give offline with every fix on time, at the fixes' floor."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry, Path

    from indoor_loc.measurements import Fix
    from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
    from msg_adapters.pose import fix_to_msg
    from msg_adapters.time import stamp_to_ns

    graph = dict(wifi_source="fix", joint=False, wifi_info=1.0, robust_kernel="huber", robust_threshold_m=1.345)
    params = tmp_path / "params.yaml"
    params.write_text("/**/backend_node:\n  ros__parameters:\n"
                      + "".join(f"    {k}: {v}\n" for k, v in graph.items()) + "    user_timeout_s: 2.0\n")
    node_proc = Peer([sys.executable, "-m", "indoor_loc.nodes.backend_node", "--ros-args", "--params-file",
                      str(params)], env=child_env())
    rng = np.random.default_rng(32)
    walk = corridor_walk("ann", 2, 30, 0, rng)
    on_time, fix_err = [], []          # (topic, msg), each fix right after its scan
    for topic, msg in _messages(walk):
        on_time.append((topic, msg))
        if topic == "wifi/scan":
            t = stamp_to_ns(msg.header.stamp)
            noise = rng.normal(0, 1.5, 2)
            fix_err.append(np.linalg.norm(noise))
            on_time.append(("wifi/fix", fix_to_msg(Fix(t, walk.true_xy_at([t])[0] + noise, 2.25 * np.eye(2), z=-5.0))))
    # the slow WiFi node: a fix once the odometry is 2 s past it
    late = [(t, m) for _, t, m in delay_fixes([(stamp_to_ns(m.header.stamp), t, m) for t, m in on_time], 2.0)]
    newest, n_waited = -1, 0           # fixes more than the reorder window behind the odometry
    for topic, msg in late:
        t = stamp_to_ns(msg.header.stamp)
        newest = max(newest, t) if topic == "pdr/odom" else newest
        n_waited += topic == "wifi/fix" and newest - t > 0.5 * SEC
    assert n_waited >= len(fix_err) - 1
    offline = BackendStage(BackendParams(**graph))
    for topic, msg in on_time:
        offline.process(topic, msg, 0, "ann")
    want = path_from_msg([m for t, m in offline.finish_user("ann") if t == "backend/ann/path"][-1])
    try:
        with ros_node("probe") as (node, ex):
            poses: list = []
            paths: list = []
            diags: list = []
            node.create_subscription(PoseWithCovarianceStamped, "/backend/ann/pose", poses.append,
                                     qos_profile(Qos.RELIABLE))
            node.create_subscription(Path, "/backend/ann/path", paths.append, qos_profile(Qos.LATCHED))
            node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: node.count_publishers("/diagnostics") > 0, 60), node_proc.output()
            pubs = {"pdr/odom": node.create_publisher(Odometry, "/ann/pdr/odom", qos_profile(Qos.RELIABLE)),
                    "wifi/scan": node.create_publisher(DiagnosticArray, "/ann/wifi/scan", qos_profile(Qos.RELIABLE)),
                    "wifi/fix": node.create_publisher(PoseWithCovarianceStamped, "/ann/wifi/fix",
                                                      qos_profile(Qos.RELIABLE))}
            assert spin_until(ex, lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 40), \
                node_proc.output()
            t_wall, t_odom = time.monotonic(), 0      # 10x real time: the window is 50 ms of wall time
            for topic, msg in late:
                if topic == "pdr/odom":
                    t_odom = stamp_to_ns(msg.header.stamp)
                spin_until(ex, lambda: False, max(t_wall + t_odom / SEC / 10 - time.monotonic(), 0.002))
                pubs[topic].publish(msg)
            assert spin_until(ex, lambda: len(poses) > 5, 40), node_proc.output()

            def fix_wait():
                for arr in reversed(diags):
                    for st in arr.status:
                        kv = {v.key: v.value for v in st.values}
                        if "fix_wait.fixes_waited_for" in kv and kv.get("user.ann.poses"):
                            return kv
                return {}
            assert spin_until(ex, lambda: fix_wait().get("in.ann/wifi/fix.count") == str(len(fix_err)), 30), \
                str({k: v for k, v in fix_wait().items() if "fix" in k or "rej" in k})
            # the count depends on when each fix met the odometry at the node (DDS orders topics separately)
            assert abs(int(fix_wait()["fix_wait.fixes_waited_for"]) - n_waited) <= 1, (fix_wait(), n_waited)
            assert fix_wait()["fix_wait.scans_given_up"] == "0" and fix_wait().get("rejected.total") == "0"
            for p in pubs.values():
                node.destroy_publisher(p)
            assert spin_until(ex, lambda: len(paths) >= 1, 40), node_proc.output()
            stamps, xy, yaw = path_from_msg(paths[-1])
            assert len(stamps) > 10 and {ps.pose.position.z for ps in paths[-1].poses} == {-5.0}
            assert np.array_equal(stamps, want[0])
            np.testing.assert_allclose(xy, want[1], atol=1e-9)            # what the on-time stream gives
            assert np.mean(np.linalg.norm(xy - walk.true_xy_at(stamps), axis=1)) < 0.8 * np.mean(fix_err)
        node_proc.signal(signal.SIGINT)
        assert node_proc.wait(timeout=40) == 0, node_proc.output()
        assert "Traceback" not in node_proc.output()
    finally:
        node_proc.stop()


@pytest.mark.parametrize("sim_time", [False, True])
def test_a_bag_played_in_a_loop_starts_the_user_afresh_live(ros_domain, tmp_path, sim_time):
    """``indoor-loc play --loop`` of one user's bag (stamps go back to the start at each loop): the
    node says the jump once per loop as a WARN naming the user (from its odometry; with
    ``use_sim_time`` and the player's ``--clock``, from ``/clock``), counts it in ``/diagnostics``,
    publishes each finished track's path, and keeps localising the user in the next pass — before,
    every message after the first loop was dropped as too_late."""
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Path

    from indoor_loc.bag import BagWriter
    from msg_adapters.time import stamp_to_ns

    rm = save_radiomap(survey(0, 60, np.random.default_rng(1)), tmp_path / "map")
    params = tmp_path / "params.yaml"
    params.write_text(f"/**/backend_node:\n  ros__parameters:\n    radiomap: {rm}\n    users: [lou]\n"
                      f"    use_sim_time: {str(sim_time).lower()}\n"
                      "    wknn: {shared_threshold: 0.75, shared_strict: false}\n")
    walk = corridor_walk("lou", 2, 26, 0, np.random.default_rng(33))
    bag = tmp_path / "lou.mcap"
    with BagWriter(bag) as w:
        for topic, msg in _messages(walk):
            w.write(f"/lou/{topic}", msg, stamp_to_ns(msg.header.stamp))
    node_proc = Peer([sys.executable, "-m", "indoor_loc.nodes.backend_node", "--ros-args", "--params-file",
                      str(params)], env=child_env())
    player = None
    try:
        with ros_node("probe") as (node, ex):
            paths: list = []
            diags: list = []
            node.create_subscription(Path, "/backend/lou/path", paths.append, qos_profile(Qos.LATCHED))
            node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: node.count_publishers("/diagnostics") > 0, 60), node_proc.output()
            player = Peer([sys.executable, "-m", "indoor_loc.nodes.player_node", str(bag), "-r", "5", "--loop",
                           "--wait-for-subscribers", "30"] + (["--clock"] if sim_time else []), env=child_env())

            def jumps() -> int:
                for arr in reversed(diags):
                    for st in arr.status:
                        kv = {v.key: v.value for v in st.values}
                        if "user.lou.time_jumps" in kv:
                            return int(kv["user.lou.time_jumps"])
                return 0
            assert spin_until(ex, lambda: jumps() >= 2, 90), node_proc.output() + player.output()
            said = r"clock jumped back .*: state reset for lou" if sim_time else r"lou: pdr/odom stamps jumped back"
            assert node_proc.wait_seen(r"WARN.*" + said, 10), node_proc.output()
            assert len(paths) >= 2                                  # each finished track's path
            for path in paths[:2]:
                stamps, xy, _ = path_from_msg(path)
                assert len(stamps) > 10 and np.mean(np.linalg.norm(xy - walk.true_xy_at(stamps), axis=1)) < 1.5
            player.signal(signal.SIGINT)
            assert player.wait(timeout=30) is not None
        assert "Traceback" not in node_proc.output()
    finally:
        if player is not None:
            player.stop()
        node_proc.stop()
