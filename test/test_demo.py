"""``indoor-loc demo`` end to end: simulated walkers, one multi-user process per stage over DDS, the
recording opened with ``rosbags``, the score table, the picture; nothing left running (also on Ctrl-C)."""
from __future__ import annotations

import importlib.util
import os
import re
import signal
import sys
import time
from pathlib import Path

import yaml

from helpers_dds import Peer, child_env


def _processes_mentioning(text: str) -> list[str]:
    """Command lines of live processes that mention ``text`` (our unique output directory)."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (d / "stat").read_text().split()[2]
        except OSError:
            continue
        if text in cmd and state != "Z":
            found.append(f"{d.name}: {cmd}")
    return found


def test_demo_runs_every_node_live_and_scores_them(ros_domain, tmp_path):
    from rosbags.highlevel import AnyReader

    out = tmp_path / "demo"
    demo = Peer([sys.executable, "-m", "indoor_loc.cli", "demo", "--out", str(out), "--walkers", "2",
                 "--duration", "24", "--seed", "3"], env=child_env())
    try:
        rc = demo.wait(timeout=240)
    finally:
        demo.stop()
    text = demo.output()
    assert rc == 0, text
    assert "score each estimator" in text and "RTS-smoothed" in text
    # stopped in dependency order once the bag was played, by the demo itself (no Ctrl-C hint)
    waves = [text.index(f"[up] stopping {first}") for first in ("imu (", "wifi (", "pdr_kf", "recorder")]
    assert waves == sorted(waves) and "Ctrl-C stops them" not in text, text
    # ... after the multi-user nodes had finished both walkers (they left once the bag was played)
    log = (out / "nodes.log").read_text()
    for node in ("imu", "wifi", "pdr_kf") + (("pf",) if importlib.util.find_spec("indoor_loc.nodes.tll_pf_node") else ()):
        for w in ("alice", "bob"):
            done = re.search(rf"^\[{node}\] \[INFO\] .*user '{w}' finished", log, re.M)
            assert done and done.start() < log.index("[up] stopping imu ("), (node, w)
    assert (out / "demo.png").stat().st_size > 20_000
    # one multi-user process per stage served both walkers
    cfg = yaml.safe_load((out / "bringup.yaml").read_text())
    nodes = {n["name"]: n for n in cfg["nodes"]}
    for name in ("imu", "wifi", "pdr_kf"):
        assert "--multi-user" in nodes[name]["args"] and nodes[name]["params"]["users"] == ["alice", "bob"]
    assert {"recorder", "player"} <= set(nodes) and not any(n.endswith(("_alice", "_bob")) for n in nodes)
    # the recording opens in rosbags and holds every output topic of every node
    with AnyReader([out / "live.mcap"]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        for w in ("alice", "bob"):
            for rel in ("imu/data", "pdr/odom", "wifi/fix", "pdr_kf/pose", "pdr_kf/path"):
                assert counts.get(f"/{w}/{rel}", 0) > 0, f"/{w}/{rel} missing: {sorted(counts)}"
        assert counts.get("/diagnostics", 0) > 0
        # the nodes of later builds, when this build has them
        if importlib.util.find_spec("indoor_loc.nodes.backend_node") is not None:
            for w in ("alice", "bob"):
                assert counts.get(f"/backend/{w}/path", 0) > 0 and counts.get(f"/backend/{w}/pose", 0) > 0
        if importlib.util.find_spec("indoor_loc.nodes.tll_pf_node") is not None:
            for w in ("alice", "bob"):
                assert counts.get(f"/{w}/pf/pose", 0) > 0
        assert counts["/alice/imu/data"] > 1000          # 100 Hz AEKF output of a 24 s walk
        conn = next(c for c in reader.connections if c.topic == "/alice/wifi/fix")
        msg = reader.deserialize(next(reader.messages(connections=[conn]))[2], conn.msgtype)
        assert msg.header.frame_id == "map"
    # the table: the smoothed estimate follows the truth (errors of the order the simulator allows)
    rows = [ln.split() for ln in text.splitlines() if "RTS-smoothed" in ln]
    assert len(rows) == 2
    for r in rows:
        mean_err = float(r[r.index("|") + 1])
        assert mean_err < 3.0, text
    assert not _processes_mentioning(str(out)), "processes left behind"


def test_demo_ctrl_c_stops_every_process(ros_domain, tmp_path):
    out = tmp_path / "demo_int"
    demo = Peer([sys.executable, "-m", "indoor_loc.cli", "demo", "--out", str(out), "--walkers", "1",
                 "--duration", "60"], env=child_env())
    try:
        assert demo.wait_line(r"started player", timeout=120) is not None, demo.output()
        time.sleep(3.0)
        demo.signal(signal.SIGINT)
        rc = demo.wait(timeout=60)
    finally:
        demo.stop()
    assert rc == 130, demo.output()
    deadline = time.monotonic() + 10
    while _processes_mentioning(str(out)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _processes_mentioning(str(out)), "processes left behind after Ctrl-C"


def test_demo_bringup_stops_in_dependency_order(tmp_path):
    """The demo's nodes (given as modules) stop player first, then the estimators from sources to
    sinks, the recorder last, so every node's last outputs are recorded."""
    from indoor_loc.demo import _module_exists, bringup_config
    from indoor_loc.supervisor import parse_config

    params = tmp_path / "params.yaml"
    params.write_text("/**/imu_node:\n  ros__parameters:\n    step_length_m: 0.7\n")
    sim = {"params": params, "bag": tmp_path / "sim.mcap", "dir": tmp_path}
    has_pf, has_backend = _module_exists("tll_pf_node"), _module_exists("backend_node")
    for per_user in (True, False):        # one process per stage and walker, or one multi-user process per stage
        cfg = parse_config(bringup_config(["alice", "bob"], sim, tmp_path, rate=1.0, foxglove=8765,
                                          per_user=per_user), tmp_path)
        order = {n.name: n.stop_order for n in cfg.nodes}
        assert order["player"] == 0 and order["recorder"] == 9 and order["view"] == 9
        # the particle filter and the back-end are in the bring-up whenever this build has their nodes
        for w in ("alice", "bob") if per_user else ("",):
            sfx = f"_{w}" if w else ""
            assert 0 < order[f"imu{sfx}"] < order[f"wifi{sfx}"] < order[f"pdr_kf{sfx}"]
            assert (f"pf{sfx}" in order) == has_pf
            if has_pf:
                assert order[f"pf{sfx}"] > order[f"wifi{sfx}"]
        assert ("backend" in order) == has_backend
        if has_backend:
            assert max(v for k, v in order.items() if k.startswith("pdr_kf")) < order["backend"] < order["recorder"]


def test_demo_with_the_view_delivers_every_input_to_its_node(ros_domain, tmp_path):
    """The live view subscribes to every topic: the player must still wait for imu_node and
    wifi_fix_node (by name), so every walker's every played IMU message reaches its imu_node --
    counted from the nodes' last /diagnostics in the recording against the simulated bag -- and the
    demo says so beside the scores, on a localhost-only DDS domain."""
    from indoor_loc.bag import bag_info
    from indoor_loc.demo_inputs import last_statuses

    out = tmp_path / "demo_view"
    demo = Peer([sys.executable, "-m", "indoor_loc.cli", "demo", "--out", str(out), "--walkers", "2",
                 "--duration", "12", "--seed", "3", "--foxglove", "0"], env=child_env())
    try:
        rc = demo.wait(timeout=240)
    finally:
        demo.stop()
    text = demo.output()
    assert rc == 0, text
    assert f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']} (yours)" in text and "discovery LOCALHOST" in text, text
    assert "inputs: every played message reached its node" in text, text
    played = {name: info.count for name, info in bag_info([out / "sim" / "sim.mcap"]).items()}
    statuses = last_statuses(out / "live.mcap")
    for w in ("alice", "bob"):
        values = statuses[f"/{w}/imu_node"]
        assert int(values["in.imu/data_raw.count"]) == played[f"/{w}/imu/data_raw"] > 1000, values
        assert "missed_at_start.imu/data_raw" not in values
    late = [ln for ln in (out / "nodes.log").read_text().splitlines()
            if ln.startswith(("[imu", "[wifi")) and "publisher's #" in ln]
    assert not late, late
    assert not _processes_mentioning(str(out)), "processes left behind"


def test_demo_robots_run_their_estimators_without_a_stepometer(tmp_path):
    """``indoor-loc demo --robots``: a robot's namespace gets the WiFi node and the estimators (on its
    own odometry: params.yaml per user, user_params multi-user), no imu_node; its odometry is an input,
    not recorded again."""
    import re

    from indoor_loc.demo import INPUT_TOPICS_RE, bringup_config

    params = tmp_path / "params.yaml"
    params.write_text("/**/imu_node:\n  ros__parameters:\n    step_length_m: 0.7\n")
    sim = {"params": params, "bag": tmp_path / "sim.mcap", "dir": tmp_path, "robots": ["robot1"]}
    names = {n["name"] for n in bringup_config(["alice", "robot1"], sim, tmp_path, rate=1.0, foxglove=None,
                                              per_user=True)["nodes"]}
    assert {"imu_alice", "wifi_robot1", "pdr_kf_robot1"} <= names and "imu_robot1" not in names
    # multi-user (the default): walkers and robots share one process per stage; a robot's estimators take
    # its own odometry by their user_params; no stepometer for it
    nodes = {n["name"]: n for n in bringup_config(["alice", "robot1"], sim, tmp_path, rate=1.0, foxglove=None)["nodes"]}
    assert {"imu", "wifi", "pdr_kf"} <= set(nodes) and not {n for n in nodes if n.endswith("_robot1")}
    assert nodes["imu"]["params"]["users"] == ["alice"] and nodes["pdr_kf"]["params"]["users"] == ["alice", "robot1"]
    assert nodes["pdr_kf"]["params"]["user_params.robot1.motion_source"] == "odom"
    assert not any(k.startswith("user_params") for k in nodes["imu"]["params"])
    assert nodes["wifi"]["params"]["users"] == ["alice", "robot1"] and "--multi-user" in nodes["wifi"]["args"]
    player = nodes["player"]["args"]
    assert "odom=pdr_kf_node_io,tll_pf_io" in " ".join(player)
    assert re.search(INPUT_TOPICS_RE, "/robot1/odom") and not re.search(INPUT_TOPICS_RE, "/alice/pdr/odom")
