"""Done as docs/nodes.md ("Running live") says, over DDS in separate processes: import one PUTMC walk, start imu_node,
wifi_fix_node and pdr_kf_node in the walk's namespace with the importer's params.yaml, `recorder -a`
and `player -r 5 --wait-for-subscribers --min-subscribers imu/data=2 wifi/scan=2`; the recorded
outputs equal the offline `indoor-loc run` of the same bag (message counts per topic, positions
within float tolerance) and the recorder holds every input message."""
from __future__ import annotations

import signal
import sys
import time
from collections import Counter

import numpy as np
import pytest
from conftest import dataset

from helpers_dds import Peer, child_env
from indoor_loc.bag import read_bag
from indoor_loc.cli import main as cli_main
from indoor_loc.pipeline.offline import run_offline
from msg_adapters.path import path_from_msg
from msg_adapters.pose import pose_from_msg

pytestmark = pytest.mark.timeout(240)
NS = "/walk16"
OUTPUTS = ("pdr/odom", "wifi/fix", "pdr_kf/pose")


def _node(module: str, params, *extra: str, **kw) -> Peer:
    # a replay, as the recipe in docs/nodes.md says: the player publishes reliable, the nodes take their
    # sensor inputs reliable too (the default, best effort, suits real drivers)
    return Peer([sys.executable, "-m", module, "--ros-args", "-r", f"__ns:={NS}", "--params-file", str(params),
                 "-p", "sensor_reliability:=reliable", *extra], **kw)


#: a replay at 5x on a busy machine: a wifi/fix may reach pdr_kf_node after later PDR hops (a fix held
#: up for a second on its way, a process descheduled, is 5 s of bag time late); holding each hop 15 s
#: of bag time (3 s of wall time) keeps the stamp order of the offline run through such stalls
EXTRA = {"pdr_kf_node": ("-p", "odom_hold_s:=15.0")}


def test_live_nodes_over_dds_equal_the_offline_run(ros_domain, tmp_path):
    putmc = dataset("putmc")
    imp = tmp_path / "import"
    assert cli_main(["import", "putmc", str(putmc), str(imp), "--walks", "16", "--no-progress"]) == 0
    bag, params = imp / "walk16.mcap", imp / "params.yaml"
    offline = run_offline([bag], tmp_path / "offline.mcap", nodes=["imu", "wifi", "pdr_kf"], params=params,
                          progress=False)
    assert all(kv["rejected.total"] == "0" for kv in offline.per_stage.values())

    env = child_env()
    live = tmp_path / "live.mcap"
    nodes = {m: _node(f"indoor_loc.nodes.{m}", params, *EXTRA.get(m, ()), env=env)
             for m in ("imu_node", "wifi_fix_node", "pdr_kf_node")}
    rec = Peer([sys.executable, "-m", "indoor_loc.nodes.recorder_node", "-a", "-o", str(live), "--poll", "0.2"], env=env)
    try:
        for name, p in nodes.items():
            assert p.wait_line(rf"{name} up", 60), p.output()
        assert rec.wait_line(r"recording all topics", 60), rec.output()
        # `-a` subscribes to a topic once it has discovered its publisher: wait for the nodes' outputs
        # (a user starts the recorder first and waits for these lines the same way)
        want = [f"{NS}/{rel}: recording [" for rel in ("pdr/odom", "wifi/fix", "pdr_kf/pose", "pdr_kf/path")]
        deadline = time.monotonic() + 60
        while not all(any(w in line for line in rec.lines) for w in want) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert all(any(w in line for line in rec.lines) for w in want), rec.output()
        # ... and until the nodes' publishers have matched those subscriptions (DDS matches each side
        # asynchronously; what a publisher sends before it matched a subscriber never reaches it)
        matched = {"imu_node": ["pdr/odom: 2 "], "wifi_fix_node": ["wifi/fix: 2 "],
                   "pdr_kf_node": ["pdr_kf/pose: 1 ", "pdr_kf/path: 1 "]}
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not all(
                any(w + "matched" in line for line in nodes[n].lines) for n, ws in matched.items() for w in ws):
            time.sleep(0.1)
        assert all(any(w + "matched" in line for line in nodes[n].lines) for n, ws in matched.items() for w in ws), \
            [nodes[n].output() for n in matched]
        # ... and wifi_fix_node has fitted its radio map (in the background, from its start): scans that
        # come during the fit are located when it ends, late for pdr_kf_node on a slow machine
        assert nodes["wifi_fix_node"].wait_seen(r"radio map fitted in", 60), nodes["wifi_fix_node"].output()
        # the nodes' inputs each have two subscribers (the node and the recorder): a stable non-zero
        # count can be the recorder alone while imu_node's subscription is still being matched
        player = Peer([sys.executable, "-m", "indoor_loc.nodes.player_node", str(bag), "-r", "5",
                       "--wait-for-subscribers", "30", "--min-subscribers", "imu/data=2", "wifi/scan=2"], env=env)
        assert player.wait(timeout=120) == 0, player.output()
        assert "without subscribers" not in player.output() and "fewer subscribers" not in player.output(), \
            player.output()
        assert f"{NS}/imu/data 2" in player.output(), player.output()
        for name in ("imu_node", "wifi_fix_node", "pdr_kf_node"):       # dependency order, recorder last
            nodes[name].signal(signal.SIGINT)
            assert nodes[name].wait(timeout=30) == 0, nodes[name].output()
            assert "ERROR" not in nodes[name].output(), nodes[name].output()
        rec.signal(signal.SIGINT)
        assert rec.wait(timeout=30) == 0, rec.output()
        assert "LOST" not in rec.output() and "lost before" not in rec.output(), rec.output()
    finally:
        for p in [*nodes.values(), rec]:
            p.stop()
            print(f"---- {' '.join(p.cmd[2:4])}\n{p.output()[-3000:]}")   # shown when the test fails

    src = Counter(m.topic for m in read_bag([bag]))
    got = Counter(m.topic for m in read_bag([live]))
    for topic, n in src.items():                                   # every input message recorded
        assert got[topic] == n, (topic, got[topic], n)
    off_msgs = list(read_bag([tmp_path / "offline.mcap"]))
    off = Counter(m.topic for m in off_msgs)
    live_msgs = list(read_bag([live]))
    for rel in OUTPUTS:
        topic = f"{NS}/{rel}"
        assert off[topic] > 0 and got[topic] == off[topic], (topic, got[topic], off[topic], [p.output()[-1500:] for p in nodes.values()])
    for rel in ("wifi/fix", "pdr_kf/pose"):
        a = np.array([pose_from_msg(m.msg).xy for m in off_msgs if m.topic == f"{NS}/{rel}"])
        b = np.array([pose_from_msg(m.msg).xy for m in live_msgs if m.topic == f"{NS}/{rel}"])
        np.testing.assert_allclose(b, a, atol=1e-9)
    final = [path_from_msg(m.msg) for m in (off_msgs, live_msgs) for m in m if m.topic == f"{NS}/pdr_kf/path"]
    off_path = [path_from_msg(m.msg) for m in off_msgs if m.topic == f"{NS}/pdr_kf/path"][-1]
    live_path = [path_from_msg(m.msg) for m in live_msgs if m.topic == f"{NS}/pdr_kf/path"][-1]
    assert final and np.array_equal(live_path[0], off_path[0])
    np.testing.assert_allclose(live_path[1], off_path[1], atol=1e-9)
