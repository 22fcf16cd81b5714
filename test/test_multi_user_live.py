"""Multi-user nodes live over DDS (``<node> --multi-user``): one process per stage serving three
simulated walkers gives each walker, message for message, what that walker's own per-user stage gives
on the same input (the stages of ``indoor-loc run``, run here one per user as the oracle); users leave
(their end-of-input outputs come) and appear mid-run; two shards split the users by the hash of their
name without overlap or gaps, and a shard killed mid-run is reported by the survivor."""
from __future__ import annotations

import dataclasses
import signal
import sys
import time
from pathlib import Path

import pytest

from helpers_dds import Peer, child_env, ros_node, spin_until

pytestmark = pytest.mark.timeout(300)

USERS = ("alice", "bob", "carol")


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> dict[str, Path]:
    from indoor_loc.commands.sim import generate
    from indoor_loc.sim.scenario import SimConfig
    from indoor_loc.sim.walker import ImuParams
    from indoor_loc.sim.rf import ScannerParams
    cfg = SimConfig(walkers=3, duration_s=16.0, seed=7, imu=dataclasses.replace(ImuParams(), rate_hz=50.0,
                                                                                  mag_rate_hz=25.0),
                    scanner=dataclasses.replace(ScannerParams(), period_s=2.5))
    return generate(tmp_path_factory.mktemp("mu") / "sim", cfg, quiet=True)


def _stage(cls, params_file: Path, user: str):
    from indoor_loc.params import load_params_file, params_for_node, params_from_dict
    vals = params_for_node(load_params_file(params_file), cls.NODE_NAME, f"/{user}")
    return cls(params_from_dict(cls.PARAMS, vals), namespace=f"/{user}")


def _oracle(stage_cls, params_file: Path, msgs: list) -> dict[str, list]:
    """Per user: its own per-user stage on its messages (``(topic, msg)`` in order), then its finish."""
    stages = {u: _stage(stage_cls, params_file, u) for u in USERS}
    out: dict[str, list] = {}
    for topic, msg, recv in msgs:
        _, user, rel = topic.split("/", 2)
        for t, m in stages[user].process(rel, msg, recv):
            out.setdefault(f"/{user}/{t}", []).append(m)
    for user, st in stages.items():
        for t, m in st.run_finish():
            out.setdefault(f"/{user}/{t}", []).append(m)
    return out


def _node(kind: str, params: Path, *extra: str) -> Peer:
    return Peer([sys.executable, "-m", f"indoor_loc.nodes.{kind}", "--multi-user", "--ros-args", "--params-file",
                 str(params), "-p", "sensor_reliability:=reliable", "-p", "user_timeout_s:=2.0", *extra],
                env=child_env())


def _play(node, ex, msgs: list, wait_for: list[Peer], rate: float = 4.0, subscribers: int = 1) -> None:
    """Publish ``msgs`` (full topic, message or CDR bytes, log ns) at ``rate`` x their log time, once the
    nodes have subscribed, ``subscribers`` to each topic (they discover the users from these publishers);
    then remove the publishers."""
    from indoor_loc.contract import Qos, msg_class
    from indoor_loc.nodes.base import qos_profile
    pubs = {}
    for topic, msg, _ in msgs:
        if topic not in pubs:
            cls = type(msg) if not isinstance(msg, bytes) else msg_class(_TYPES[topic.split("/", 2)[2]])
            pubs[topic] = node.create_publisher(cls, topic, qos_profile(Qos.RELIABLE))
    assert spin_until(ex, lambda: all(p.get_subscription_count() >= subscribers for p in pubs.values()), 60), \
        "\n".join(p.output()[-2000:] for p in wait_for)
    spin_until(ex, lambda: False, 1.5)      # a match completes on the subscriber's side a moment later
    t0, first = time.monotonic(), msgs[0][2]
    for topic, msg, log_ns in msgs:
        due = t0 + (log_ns - first) * 1e-9 / rate
        while time.monotonic() < due:
            ex.spin_once(timeout_sec=max(0.0, min(0.01, due - time.monotonic())))
        pubs[topic].publish(msg)
    spin_until(ex, lambda: all(p.wait_for_all_acked(rclpy_duration(0.0)) for p in pubs.values()), 30)
    for p in pubs.values():
        node.destroy_publisher(p)


def rclpy_duration(s: float):
    from rclpy.duration import Duration
    return Duration(nanoseconds=int(s * 1e9))


_TYPES = {"imu/data_raw": "sensor_msgs/msg/Imu", "imu/mag": "sensor_msgs/msg/MagneticField",
          "wifi/scan": "diagnostic_msgs/msg/DiagnosticArray"}


def _collect(node, topics: dict[str, type]) -> dict[str, list]:
    """Every message on ``topics`` (reliable, volatile: matches the nodes' latched outputs too)."""
    from indoor_loc.contract import Qos
    from indoor_loc.nodes.base import qos_profile
    got: dict[str, list] = {t: [] for t in topics}
    for t, cls in topics.items():
        node.create_subscription(cls, t, got[t].append, qos_profile(Qos.RELIABLE))
    return got


def _ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _bag(sim, rels: tuple[str, ...]) -> list:
    from indoor_loc.bag import read_bag
    return [(m.topic, m.msg, m.stamp_ns) for m in read_bag([sim["bag"]])
            if m.topic.count("/") >= 2 and m.topic.split("/", 2)[1] in USERS and m.topic.split("/", 2)[2] in rels]


def test_front_end_nodes_serve_three_users_as_their_own_nodes(ros_domain, sim):
    """imu_node and wifi_fix_node, one process each for three users: per user, pdr/odom and wifi/fix
    message for message as the user's own stage gives them; each user leaves (its publishers gone for
    user_timeout_s) and gets its end-of-input hops."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from indoor_loc.pipeline.imu_stage import ImuStage
    from indoor_loc.pipeline.wifi_fix_stage import WifiFixStage

    msgs = _bag(sim, ("imu/data_raw", "imu/mag", "wifi/scan"))
    want = _oracle(ImuStage, sim["params"], [m for m in msgs if "/imu/" in m[0]])
    want.update(_oracle(WifiFixStage, sim["params"], [m for m in msgs if m[0].endswith("wifi/scan")]))
    nodes = [_node("imu_node", sim["params"]), _node("wifi_fix_node", sim["params"])]
    try:
        with ros_node("probe") as (node, ex):
            topics = {f"/{u}/pdr/odom": Odometry for u in USERS} | \
                     {f"/{u}/wifi/fix": PoseWithCovarianceStamped for u in USERS}
            got = _collect(node, topics)
            _play(node, ex, msgs, nodes)
            done = spin_until(ex, lambda: all(len(got[t]) >= len(want.get(t, [])) for t in topics)
                              and all(n.wait_seen(f"user '{u}' left", 0) for n in nodes for u in USERS), 60)
            if not done:
                pytest.fail(str(({t: (len(got[t]), len(want.get(t, []))) for t in topics},
                                 [(_ns(got[t][0]), _ns(want[t][0]), _ns(got[t][-1]), _ns(want[t][-1]))
                                  for t in topics if got[t]], [n.output()[-3000:] for n in nodes])))
            for t in topics:
                assert len(want[t]) > 3, t
                assert got[t] == want[t], t
    finally:
        for n in nodes:
            n.stop()


def test_imu_node_without_magnetometer_serves_three_users_as_their_own_nodes(ros_domain, sim):
    """imu_node (the simulator's heading_source: aekf) for three users whose phones have no magnetometer:
    the steady runs go through the AEKF's column path (pipeline/imu_raw_run.py) in the multi-user node,
    and every user's pdr/odom is still message for message its own per-user stage's, taken one
    sample at a time (the headings of those hops come from the filter's orientations)."""
    from nav_msgs.msg import Odometry
    from indoor_loc.pipeline.imu_stage import ImuStage

    msgs = _bag(sim, ("imu/data_raw",))
    want = _oracle(ImuStage, sim["params"], msgs)
    nodes = [_node("imu_node", sim["params"])]
    try:
        with ros_node("probe") as (node, ex):
            topics = {f"/{u}/pdr/odom": Odometry for u in USERS}
            got = _collect(node, topics)
            _play(node, ex, msgs, nodes)
            done = spin_until(ex, lambda: all(len(got[t]) >= len(want.get(t, [])) for t in topics)
                              and all(n.wait_seen(f"user '{u}' left", 0) for n in nodes for u in USERS), 60)
            assert done, str(({t: (len(got[t]), len(want.get(t, []))) for t in topics}, nodes[0].output()[-3000:]))
            for t in topics:
                assert len(want[t]) > 3, t
                assert got[t] == want[t], t
    finally:
        for n in nodes:
            n.stop()


def test_fusion_nodes_serve_three_users_as_their_own_nodes(ros_domain, sim):
    """pdr_kf_node and tll_pf, one process each for three users, fed each user's pdr/odom and wifi/fix
    (from the users' own front-end stages): per user, pdr_kf/pose and pf/pose message for message as
    the user's own stages give them."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.serialization import serialize_message
    from indoor_loc.pipeline.imu_stage import ImuStage
    from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage
    from indoor_loc.pipeline.pf_stage import PfStage
    from indoor_loc.pipeline.wifi_fix_stage import WifiFixStage

    front = _bag(sim, ("imu/data_raw", "imu/mag", "wifi/scan"))
    made = _oracle(ImuStage, sim["params"], [m for m in front if "/imu/" in m[0]])
    made.update(_oracle(WifiFixStage, sim["params"], [m for m in front if m[0].endswith("wifi/scan")]))
    msgs = []
    for t, lst in made.items():
        if t.endswith(("/pdr/odom", "/wifi/fix")):
            msgs += [(t, m, m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec) for m in lst]
    msgs.sort(key=lambda m: m[2])
    # from each user's first pdr/odom on: a fix before it would wait for PDR until the node's timer
    # (on the node's clock, not the stamps) lets it go on the speed model, which an offline oracle lacks
    first = {u: min(s for t, _, s in msgs if t == f"/{u}/pdr/odom") for u in USERS}
    msgs = [m for m in msgs if m[2] >= first[m[0].split("/")[1]]]
    want = _oracle(PdrKfStage, sim["params"], msgs)
    want.update(_oracle(PfStage, sim["params"], msgs))
    nodes = [_node("pdr_kf_node", sim["params"]), _node("tll_pf_node", sim["params"])]
    try:
        with ros_node("probe") as (node, ex):
            topics = {f"/{u}/{k}": PoseWithCovarianceStamped for u in USERS for k in ("pdr_kf/pose", "pf/pose")}
            got = _collect(node, topics)
            _play(node, ex, [(t, serialize_message(m), s) for t, m, s in msgs], nodes, rate=2.0, subscribers=2)
            if not spin_until(ex, lambda: all(len(got[t]) >= len(want.get(t, [])) for t in topics), 60):
                pytest.fail(str(({t: (len(got[t]), len(want.get(t, []))) for t in topics},
                                 {t: sorted({_ns(m) for m in want[t]} - {_ns(m) for m in got[t]})[:6] for t in topics},
                                 {t: (_ns(want[t][0]), _ns(want[t][-1]), len(msgs)) for t in topics},
                                 [n.output()[-1500:] for n in nodes])))
            for t in topics:
                assert len(want[t]) > 3, t
                assert got[t] == want[t], t
    finally:
        for n in nodes:
            n.stop()


_TYPES.update({"pdr/odom": "nav_msgs/msg/Odometry", "wifi/fix": "geometry_msgs/msg/PoseWithCovarianceStamped"})


def _diagnostics(node):
    from diagnostic_msgs.msg import DiagnosticArray
    from indoor_loc.contract import Qos
    from indoor_loc.nodes.base import qos_profile
    from msg_adapters.diagnostics import diagnostics_from_msg
    last: dict = {}
    node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: last.update(diagnostics_from_msg(m)),
                             qos_profile(Qos.RELIABLE))
    return last


def test_two_shards_split_users_and_a_killed_shard_is_reported(ros_domain, sim):
    """Two imu_node shards: each user is served by exactly the shard its name hashes to (all users
    served, none twice), a user appearing mid-run is served too; once shard 1 is killed (SIGKILL), shard 0
    reports shard 1's users as unserved; shard 1 restarted serves them again and the report clears."""
    import numpy as np
    from sensor_msgs.msg import Imu
    from indoor_loc.contract import Qos
    from indoor_loc.nodes.base import qos_profile
    from indoor_loc.pipeline.multi_user import shard_of
    from msg_adapters.imu import imu_to_msg

    users = [f"walker{i}" for i in range(6)]
    late = "walker6"
    assert {shard_of(u, 2) for u in users} == {0, 1}
    shards = [_node("imu_node", sim["params"], "-r", f"__ns:=/shard{i}", "-p", "shard_count:=2",
                    "-p", f"shard_index:={i}") for i in range(2)]
    try:
        with ros_node("probe") as (node, ex):
            diags = _diagnostics(node)
            pubs = {u: node.create_publisher(Imu, f"/{u}/imu/data_raw", qos_profile(Qos.RELIABLE)) for u in users}
            t = [time.time_ns()]

            def publish(seconds: float) -> None:
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    t[0] += 20_000_000
                    for p in pubs.values():
                        p.publish(imu_to_msg(t[0], "imu_link", np.array([0.0, 0.0, 9.81]), np.zeros(3)))
                    ex.spin_once(timeout_sec=0.02)

            def served_by() -> dict[str, str]:
                return {u: diags[f"/{u}/imu_node"].values.get("served_by", "")
                        for u in pubs if f"/{u}/imu_node" in diags}

            def all_served() -> bool:
                publish(0.2)
                return len(served_by()) == len(pubs)
            assert spin_until(ex, all_served, 60), (served_by(), [s.output()[-2000:] for s in shards])
            assert served_by() == {u: f"/shard{shard_of(u, 2)}/imu_node" for u in users}
            for i in range(2):
                mine = diags[f"/shard{i}/imu_node"].values["users"].split(",")
                assert sorted(mine) == sorted(u for u in users if shard_of(u, 2) == i)

            def none_unserved() -> bool:    # (a shard's status may predate the other's first statuses)
                publish(0.2)
                return all(diags[f"/shard{i}/imu_node"].values["unserved.count"] == "0" for i in range(2))
            assert spin_until(ex, none_unserved, 15), [diags[f"/shard{i}/imu_node"] for i in range(2)]
            pubs[late] = node.create_publisher(Imu, f"/{late}/imu/data_raw", qos_profile(Qos.RELIABLE))
            assert spin_until(ex, all_served, 30), served_by()
            assert served_by()[late] == f"/shard{shard_of(late, 2)}/imu_node"

            shards[1].signal(signal.SIGKILL)
            lost = sorted(u for u in pubs if shard_of(u, 2) == 1)

            def reported() -> bool:
                publish(0.2)
                st = diags.get("/shard0/imu_node")
                return st is not None and st.values.get("unserved.users", "") == ",".join(lost)
            assert spin_until(ex, reported, 30), diags.get("/shard0/imu_node")
            st = diags["/shard0/imu_node"]
            assert st.level >= 1 and "unserved" in st.message and st.values["unserved.shards"] == "1"

            # no shard takes them over (docs/scaling.md): the shard restarted serves them again, afresh
            for u in lost:
                del diags[f"/{u}/imu_node"]
            shards.append(_node("imu_node", sim["params"], "-r", "__ns:=/shard1", "-p", "shard_count:=2",
                                "-p", "shard_index:=1"))

            def served_again() -> bool:
                publish(0.2)
                st = diags.get("/shard0/imu_node")
                return all_served() and st is not None and st.values.get("unserved.count") == "0"
            assert spin_until(ex, served_again, 60), (served_by(), diags.get("/shard0/imu_node"))
            assert served_by() == {u: f"/shard{shard_of(u, 2)}/imu_node" for u in pubs}
    finally:
        for s in shards:
            s.stop()


def test_each_users_status_carries_its_own_input_counters_to_the_last(ros_domain):
    """A multi-user imu_node's per-user statuses carry what the per-user node's status carries: the
    user's input counts, and its own messages lost / published before the subscription matched (one
    user started publishing before the node was up, the other did not); and the node's last status,
    sent as it stops right after the input (SIGINT, before any user left), still has every user's
    counters (what `indoor-loc demo` reads to account for every played message)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu
    from indoor_loc.pipeline.imu_stage import ImuStage
    from msg_adapters.diagnostics import stage_diagnostics
    from msg_adapters.time import stamp_from_ns

    def imu(user: str) -> Imu:
        m = Imu()
        m.header.stamp = stamp_from_ns(time.time_ns())
        m.header.frame_id = f"{user}/imu_link"
        m.linear_acceleration.z = 9.81
        m.orientation_covariance[0] = -1.0
        return m

    users = ("early", "prompt")
    with ros_node("probe") as (node, ex):
        diags = _diagnostics(node)
        pubs = {u: node.create_publisher(Imu, f"/{u}/imu/data_raw",
                                         QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)) for u in users}
        sent: dict[str, list] = {u: [] for u in users}
        for _ in range(30):                  # nobody listens yet: a replay started too early
            pubs["early"].publish(imu("early"))
        proc = Peer([sys.executable, "-m", "indoor_loc.nodes.imu_node", "--multi-user", "--ros-args",
                     "-p", "sensor_reliability:=reliable", "-p", "users:=[early, prompt]"], env=child_env())
        try:
            assert spin_until(ex, lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 60), \
                proc.output()
            spin_until(ex, lambda: False, 1.0)
            for _ in range(40):
                for u in users:
                    sent[u].append(imu(u))
                    pubs[u].publish(sent[u][-1])
                spin_until(ex, lambda: False, 0.01)
            assert spin_until(ex, lambda: all(p.wait_for_all_acked(rclpy_duration(0.0)) for p in pubs.values()), 30)
            spin_until(ex, lambda: False, 0.5)
            proc.signal(signal.SIGINT)           # stopped right after its input: no user has left
            assert proc.wait(timeout=30) == 0, proc.output()[-3000:]
            spin_until(ex, lambda: False, 1.0)
        finally:
            proc.stop()
    for u in users:
        own = ImuStage(ImuStage.PARAMS(), namespace=f"/{u}")       # the per-user node's stage, same messages
        for m in sent[u]:
            own.process("imu/data_raw", m, _ns(m))
        own_keys = {kv.key for kv in stage_diagnostics(f"/{u}/imu_node", own, 0).status[0].values}
        st = diags[f"/{u}/imu_node"].values
        assert st.get("in.imu/data_raw.count") == "40", (u, st, proc.output()[-3000:])
        assert own_keys <= set(st), (u, own_keys - set(st))
    early, prompt = diags["/early/imu_node"].values, diags["/prompt/imu_node"].values
    assert early["missed_at_start.imu/data_raw"] == "30" and early["lost.imu/data_raw"] == "30", early
    assert "missed_at_start.imu/data_raw" not in prompt and prompt["lost.total"] == "0", prompt
    assert diags["/imu_node"].values["lost.total"] == "30"       # the node's totals


def test_a_user_leaving_mid_run_is_finished_and_leaves_the_nodes_after_it(ros_domain, sim):
    """imu_node, wifi_fix_node and pdr_kf_node multi-user, three users; alice's phone stops half-way
    (its publishers go) while bob and carol walk on: imu_node and wifi_fix_node finish alice (her
    end-of-input hops) and close her outputs, so pdr_kf_node sees her leave too and finishes her; bob
    and carol are served to the end of their input."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from indoor_loc.contract import Qos
    from indoor_loc.nodes.qos import qos_profile

    msgs = _bag(sim, ("imu/data_raw", "imu/mag", "wifi/scan"))
    t_first, t_last = msgs[0][2], msgs[-1][2]
    cut = t_first + (t_last - t_first) // 2
    nodes = [_node("imu_node", sim["params"]), _node("pdr_kf_node", sim["params"]),
             _node("wifi_fix_node", sim["params"])]
    try:
        with ros_node("probe") as (node, ex):
            diags = _diagnostics(node)
            poses = _collect(node, {f"/{u}/pdr_kf/pose": PoseWithCovarianceStamped for u in USERS})
            pubs = {}
            for topic, msg, _ in msgs:
                if topic not in pubs:
                    pubs[topic] = node.create_publisher(type(msg), topic, qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 60), \
                "\n".join(n.output()[-2000:] for n in nodes)
            spin_until(ex, lambda: False, 1.5)
            t0, rate, gone = time.monotonic(), 2.0, False
            for topic, msg, log_ns in msgs:
                if log_ns >= cut and not gone:          # alice's phone stops: her publishers go
                    spin_until(ex, lambda: all(p.wait_for_all_acked(rclpy_duration(0.0))
                                               for t, p in pubs.items() if t.startswith("/alice/")), 10)
                    for t in [t for t in pubs if t.startswith("/alice/")]:
                        node.destroy_publisher(pubs.pop(t))
                    gone = True
                if topic.startswith("/alice/") and gone:
                    continue
                due = t0 + (log_ns - t_first) * 1e-9 / rate
                while time.monotonic() < due:
                    ex.spin_once(timeout_sec=max(0.0, min(0.01, due - time.monotonic())))
                pubs[topic].publish(msg)
            # bob and carol still publish (their publishers stay): alice alone has left, downstream too
            assert nodes[0].wait_seen("user 'alice' finished", 30), nodes[0].output()[-3000:]
            assert spin_until(ex, lambda: bool(nodes[1].wait_seen("user 'alice' finished", 0)), 30), \
                nodes[1].output()[-3000:]
            spin_until(ex, lambda: False, 2.0)
            for n in nodes:
                assert not n.wait_seen("user '(bob|carol)' left", 0), n.output()[-3000:]
            played = {u: sum(1 for t, _, _ in msgs if t == f"/{u}/imu/data_raw") for u in ("bob", "carol")}
            assert spin_until(ex, lambda: all(diags.get(f"/{u}/imu_node") is not None and
                                              diags[f"/{u}/imu_node"].values.get("in.imu/data_raw.count") ==
                                              str(played[u]) for u in played), 30), \
                {u: diags[f"/{u}/imu_node"].values.get("in.imu/data_raw.count") for u in played}
            for u in USERS:
                assert len(poses[f"/{u}/pdr_kf/pose"]) > 3, u
            assert max(_ns(m) for m in poses["/alice/pdr_kf/pose"]) <= cut < max(_ns(m) for m in poses["/bob/pdr_kf/pose"])
    finally:
        for n in nodes:
            n.stop()
