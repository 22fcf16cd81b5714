"""``indoor-loc up``: config validation, command lines, and real runs (two dummy nodes in two
namespaces stopped by SIGINT; a dying child stops the rest; respawn; required)."""
from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import pytest
import yaml

from helpers_dds import PEERS, Peer, child_env, ros_node, spin_until
from indoor_loc.errors import ConfigError
from indoor_loc.supervisor import load_config, package_executables, param_text, parse_config

ROOT = Path(__file__).resolve().parents[1]
DUMMY = str(PEERS / "dummy_node.py")
EXIT = str(PEERS / "exit_peer.py")

# a bound for a hung test, above the sum of a test's condition deadlines (which a loaded machine may
# use up one after another), not an expected duration
pytestmark = pytest.mark.timeout(240)


def write(tmp_path: Path, data) -> Path:
    p = tmp_path / "up.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def bringup(cfg: Path, **env: str) -> Peer:
    return Peer([sys.executable, "-m", "indoor_loc.cli", "up", str(cfg)], env=child_env(**env), cwd=str(ROOT))


def test_example_config_is_valid():
    cfg = load_config(ROOT / "config" / "bringup_example.yaml")
    names = [n.name for n in cfg.nodes]
    assert names == ["player", "imu_walk01", "wifi_walk01", "pdr_kf_walk01", "recorder"]
    imu = cfg.nodes[1]
    cmd = imu.command()
    assert cmd[cmd.index("--ros-args"):][:3] == ["--ros-args", "-r", "__ns:=/walk01"]
    assert "--params-file" in cmd and str(ROOT / "config" / "imu_node.yaml") in cmd
    assert cmd[-6:] == ["-p", "step_length_m:=0.7", "-p", "heading_source:=auto", "-p", "sensor_reliability:=reliable"]
    assert "use_sim_time:=true" in cmd and "use_sim_time:=false" in cfg.nodes[0].command()
    assert imu.respawn and cfg.nodes[0].required and cfg.env["ROS_DOMAIN_ID"] == "42"


def test_command_line_layout(tmp_path):
    pf = tmp_path / "p.yaml"
    pf.write_text("/**:\n  ros__parameters:\n    gain: 2.0\n")
    cfg = parse_config({"params_files": [str(pf)], "nodes": [{
        "name": "a", "script": DUMMY, "namespace": "/alice/", "args": ["x", 3], "params": {"label": "0.5", "gain": 2,
                                                                                             "weights": [1.0, 2.0]},
        "remap": {"imu/data_raw": "imu/raw2"}, "ros_args": ["--log-level", "debug"]}]}, tmp_path)
    assert cfg.nodes[0].command() == [
        sys.executable, DUMMY, "x", "3", "--ros-args", "-r", "__ns:=/alice", "-r", "imu/data_raw:=imu/raw2",
        "--params-file", str(pf.resolve()), "-p", "label:='0.5'", "-p", "gain:=2", "-p", "weights:=[1.0, 2.0]",
        "--log-level", "debug"]
    assert param_text(True) == "true" and param_text("auto") == "auto" and param_text(0.65) == "0.65"
    exe = package_executables()
    assert {"player", "recorder"} <= set(exe) and all(v.startswith("indoor_loc.nodes.") for v in exe.values())
    assert len(set(exe.values())) == len(exe)          # one name per node (an error message lists them)


@pytest.mark.parametrize("data,match", [
    ([1, 2], r"bringup: expected a mapping"),
    ({"nodes": []}, r"bringup.nodes: expected a non-empty list"),
    ({"nodes": [{"name": "a", "script": DUMMY}], "extra": 1}, r"unknown key\(s\) \['extra'\]"),
    ({"nodes": [{"name": "a", "script": DUMMY, "respwan": True}]}, r"nodes\[0\]: unknown key\(s\) \['respwan'\]"),
    ({"nodes": [{"name": "a", "script": DUMMY}, {"name": "a", "script": DUMMY}]}, r"nodes\[1\].name: duplicate"),
    ({"nodes": [{"name": "a b", "script": DUMMY}]}, r"nodes\[0\].name: expected a label"),
    ({"nodes": [{"name": "a"}]}, r"exactly one of executable / module / script"),
    ({"nodes": [{"name": "a", "script": DUMMY, "module": "x"}]}, r"exactly one of"),
    ({"nodes": [{"name": "a", "executable": "imu_nod"}]},
     r"unknown executable 'imu_nod'; expected one of \[.*'imu_node'"),
    ({"nodes": [{"name": "a", "module": "no_such_pkg.mod"}]}, r"cannot import"),
    ({"nodes": [{"name": "a", "script": "missing.py"}]}, r"missing.py does not exist"),
    ({"nodes": [{"name": "a", "script": DUMMY, "namespace": "alice"}]}, r"namespace: expected '' or an absolute"),
    ({"nodes": [{"name": "a", "script": DUMMY, "namespace": "/al ice"}]}, r"namespace"),
    ({"nodes": [{"name": "a", "script": DUMMY, "params_files": ["nope.yaml"]}]}, r"nope.yaml does not exist"),
    ({"nodes": [{"name": "a", "script": DUMMY, "params": {"gain": {"x": 1}}}]}, r"params.gain: expected a scalar"),
    ({"nodes": [{"name": "a", "script": DUMMY, "params": [1]}]}, r"params: expected a mapping"),
    ({"nodes": [{"name": "a", "script": DUMMY, "respawn": "yes"}]}, r"respawn: expected true or false"),
    ({"nodes": [{"name": "a", "script": DUMMY, "respawn_delay_s": -1}]}, r"respawn_delay_s: expected a number >= 0"),
    ({"nodes": [{"name": "a", "script": DUMMY}], "env": {"ROS_DOMAIN_ID": 300}}, r"ROS_DOMAIN_ID: expected an integer"),
    ({"nodes": [{"name": "a", "script": DUMMY}], "use_sim_time": "true"}, r"use_sim_time: expected true or false"),
    ({"nodes": [{"name": "a", "script": DUMMY}], "stop_timeout_s": 0}, r"stop_timeout_s: expected a number > 0"),
    ({"nodes": [{"name": "a", "script": DUMMY, "remap": ["a:=b"]}]}, r"remap: expected a mapping"),
])
def test_config_errors(tmp_path, data, match):
    with pytest.raises(ConfigError, match=match):
        parse_config(data, tmp_path)


def test_bad_params_file_and_cli_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("gain: 2.0\n")
    with pytest.raises(ConfigError, match="no 'ros__parameters'"):
        parse_config({"nodes": [{"name": "a", "script": DUMMY, "params_files": [str(bad)]}]}, tmp_path)
    from indoor_loc.cli import main
    cfg = write(tmp_path, {"nodes": [{"name": "a", "script": "missing.py"}]})
    assert main(["up", str(cfg)]) == 2
    assert main(["up", str(tmp_path / "absent.yaml")]) == 2


def test_two_nodes_in_namespaces_stop_cleanly_on_sigint(ros_domain, tmp_path):
    pf = tmp_path / "gain.yaml"
    pf.write_text("/bob/dummy_node:\n  ros__parameters:\n    gain: 3.0\n")
    cfg = write(tmp_path, {"env": {"ROS_DOMAIN_ID": ros_domain}, "nodes": [
        {"name": "alice", "script": DUMMY, "namespace": "/alice", "params": {"label": "A"}},
        {"name": "bob", "script": DUMMY, "namespace": "/bob", "params_files": [str(pf)]}]})
    # The bring-up itself runs in another domain: the probe only sees the nodes if `env` is applied.
    up = bringup(cfg, ROS_DOMAIN_ID=str(ros_domain + 100))
    try:
        assert up.wait_line(r"^\[(alice|bob)\] .*dummy_node up", 60), up.output()
        assert up.wait_line(r"^\[(alice|bob)\] .*dummy_node up", 60), up.output()
        with ros_node("probe") as (node, ex):
            want = {("dummy_node", "/alice"), ("dummy_node", "/bob")}
            assert spin_until(ex, lambda: want <= set(node.get_node_names_and_namespaces()), 40), \
                node.get_node_names_and_namespaces()
        pids = [int(line.split("(pid ")[1].split(")")[0]) for line in up.lines if "started" in line]
        assert len(pids) == 2
        up.signal(signal.SIGINT)
        assert up.wait(timeout=40) == 0, up.output()
        out = up.output()
        assert "[up] alice stopped (exit status 0)" in out and "[up] bob stopped (exit status 0)" in out
        assert "Traceback" not in out and "[up] all nodes stopped" in out
        for pid in pids:
            with pytest.raises(ProcessLookupError):
                os.kill(pid, 0)
    finally:
        up.stop()


def test_dying_node_stops_the_others(tmp_path):
    started = tmp_path / "started.log"     # crash dies only once steady is up (its handlers in place)
    cfg = write(tmp_path, {"stop_timeout_s": 5, "nodes": [
        {"name": "steady", "script": EXIT, "args": ["--log", str(started)]},
        {"name": "crash", "script": EXIT, "args": ["--after", "0.5", "--until-lines", str(started), "1",
                                                    "--code", "3"]}]})
    up = bringup(cfg)
    try:
        assert up.wait(timeout=60) == 1, up.output()
        out = up.output()
        assert "[crash] exit_peer exiting with 3" in out and "[up] crash died: stopping the others" in out
        assert "[steady] exit_peer stopped by signal 2" in out and "[up] steady stopped (exit status 0)" in out
    finally:
        up.stop()


def test_respawn_and_required(tmp_path):
    # `main` runs until `flaky` has started three times (however slowly this machine starts them):
    # without respawn it would run until the test's deadline
    started = tmp_path / "flaky_started.log"
    cfg = write(tmp_path, {"nodes": [
        {"name": "flaky", "script": EXIT, "args": ["--after", "0.1", "--code", "1", "--log", str(started)],
         "respawn": True, "respawn_delay_s": 0.2},
        {"name": "main", "script": EXIT, "args": ["--after", "2.5", "--until-lines", str(started), "3"],
         "required": True}]})
    up = bringup(cfg)
    try:
        assert up.wait(timeout=60) == 0, up.output()
        out = up.output()
        starts = out.count("[up] started flaky")
        assert starts >= 3, out                      # respawned while `main` ran
        assert "[up] main is required and exited: stopping the others" in out
        assert out.count("[up] started main") == 1
    finally:
        up.stop()


def test_all_children_exiting_ends_the_bringup(tmp_path):
    cfg = write(tmp_path, {"nodes": [{"name": f"n{i}", "script": EXIT, "args": ["--after", "0.2", "x y"]}
                                     for i in range(2)]})
    up = bringup(cfg)
    try:
        assert up.wait(timeout=30) == 0, up.output()
        assert "[n0] exit_peer start argv=['--after', '0.2', 'x y', '--ros-args']" in up.output()
        assert up.output().count("exited with status 0") == 2
    finally:
        up.stop()


def test_a_child_still_starting_is_stopped_without_a_traceback(tmp_path):
    """A node still importing when a required sibling ends gets SIGTERM (ends quietly), not SIGINT
    (a KeyboardInterrupt traceback from whatever it was importing)."""
    slow = tmp_path / "slow_start.py"
    slow.write_text("import time\ntime.sleep(30)\nprint('up', flush=True)\n")   # no handlers, no output yet
    cfg = write(tmp_path, {"stop_timeout_s": 5, "nodes": [
        {"name": "slow", "script": str(slow)},
        {"name": "main", "script": EXIT, "args": ["--after", "1.0"], "required": True}]})
    up = bringup(cfg)
    try:
        assert up.wait(timeout=30) == 0, up.output()
        out = up.output()
        assert "[up] slow stopped (exit status -15)" in out, out
        assert "Traceback" not in out and "KeyboardInterrupt" not in out, out
    finally:
        up.stop()


def test_stubborn_child_is_terminated(tmp_path):
    """A child that ignores SIGINT gets SIGTERM after stop_timeout_s."""
    stubborn = tmp_path / "stubborn.py"
    stubborn.write_text("import signal, sys, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                        "print('ready', flush=True)\ntime.sleep(60)\n")
    # SIGTERM comes stop_timeout_s after SIGINT, SIGKILL as long again after SIGTERM: 2 s for the child
    # to be scheduled and end on SIGTERM, also on a loaded machine
    cfg = write(tmp_path, {"stop_timeout_s": 2.0, "nodes": [{"name": "stubborn", "script": str(stubborn)}]})
    up = bringup(cfg)
    try:
        assert up.wait_line(r"^\[stubborn\] ready", 20), up.output()
        up.signal(signal.SIGINT)
        assert up.wait(timeout=20) == 0, up.output()   # SIGTERM is a clean stop for a stubborn child
        assert "still running 2 s after SIGINT: SIGTERM" in up.output()
    finally:
        up.stop()


def test_dry_run_prints_commands(capsys):
    from indoor_loc.cli import main
    assert main(["up", str(ROOT / "config" / "bringup_example.yaml"), "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in lines] == ["player", "imu_walk01", "wifi_walk01", "pdr_kf_walk01", "recorder"]
    assert "ROS_DOMAIN_ID=42" in lines[1] and "-r __ns:=/walk01" in lines[1] and "imu_node" in lines[1]


def test_program_that_cannot_start(tmp_path):
    import dataclasses
    import io

    from indoor_loc.supervisor import Bringup
    cfg = parse_config({"nodes": [{"name": "ok", "script": EXIT}]}, tmp_path)
    broken = dataclasses.replace(cfg.nodes[0], name="broken", program=(str(tmp_path / "not_there"),))
    out = io.StringIO()
    assert Bringup(dataclasses.replace(cfg, nodes=(cfg.nodes[0], broken)), out=out).run() == 1
    text = out.getvalue()
    assert "[up] cannot start broken" in text and "[up] ok stopped (exit status" in text


def test_stop_in_dependency_order_keeps_the_final_outputs(ros_domain, tmp_path):
    """The recorder stops last (stop_order 9): the node's end-of-input output, published while it
    stops, is in the bag; waves are logged in order."""
    bag = tmp_path / "rec.mcap"
    cfg = write(tmp_path, {"env": {"ROS_DOMAIN_ID": ros_domain}, "stop_timeout_s": 10, "nodes": [
        {"name": "rec", "executable": "recorder", "args": ["-t", "/alice/dummy/pose", "-o", str(bag)]},
        {"name": "alice", "script": DUMMY, "namespace": "/alice"}]})
    assert [n.stop_order for n in load_config(cfg).nodes] == [9, 1]
    up = bringup(cfg)
    try:
        assert up.wait_seen(r"^\[rec\] .*recording \[geometry_msgs", 60), up.output()
        # the node's publisher has matched the recorder's subscription (DDS matches each side on its
        # own, and what is published before never reaches it): the node's last output is then acked
        assert up.wait_seen(r"^\[alice\] .*dummy/pose: 1 matched subscription", 60), up.output()
        up.signal(signal.SIGINT)
        assert up.wait(timeout=60) == 0, up.output()
        out = up.output()
        assert out.index("[up] alice stopped") < out.index("[up] rec stopped")
    finally:
        up.stop()
    from indoor_loc.bag import read_bag
    poses = [m for m in read_bag([bag]) if m.topic == "/alice/dummy/pose"]
    assert len(poses) == 1          # the finish() output (stamp = number of accepted messages, 0)


def test_package_nodes_stop_in_dependency_order_also_as_modules(tmp_path):
    """A package node gets its default stop_order whether given as ``executable:`` or ``module:``
    (the demo's bring-up uses modules); other programs stop with the first wave after the player."""
    nodes = [("player", "executable", "player"), ("imu", "module", "indoor_loc.nodes.imu_node"),
             ("wifi", "module", "indoor_loc.nodes.wifi_fix_node"), ("kf", "executable", "pdr_kf_node"),
             ("pf", "module", "indoor_loc.nodes.tll_pf_node"), ("backend", "module", "indoor_loc.nodes.backend_node"),
             ("rec", "module", "indoor_loc.nodes.recorder_node"), ("view", "executable", "indoor_loc_view"),
             ("other", "script", EXIT)]
    cfg = parse_config({"nodes": [{"name": n, kind: v} for n, kind, v in nodes]}, tmp_path)
    assert {n.name: n.stop_order for n in cfg.nodes} == {
        "player": 0, "imu": 1, "wifi": 2, "kf": 3, "pf": 3, "backend": 4, "rec": 9, "view": 9, "other": 1}
    # node modules not installed as console scripts are named after their files
    from indoor_loc.supervisor import _stop_order
    files = {f"{m}_node": f"indoor_loc.nodes.{m}_node:main" for m in ("tll_pf", "view", "pdr_kf")}
    assert [_stop_order(0, {"module": f"indoor_loc.nodes.{m}_node"}, files) for m in ("tll_pf", "view", "pdr_kf")] \
        == [3, 9, 3]


def test_waves_stop_one_after_another(tmp_path):
    """Each stop_order wave gets SIGINT only once the wave before it has exited."""
    started = tmp_path / "started.log"
    cfg = write(tmp_path, {"stop_timeout_s": 10, "nodes": [
        {"name": name, "script": EXIT, "args": ["--log", str(started)], "stop_order": order}
        for name, order in (("sink", 9), ("source", 0), ("middle", 3))]})
    up = bringup(cfg)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (not started.exists() or len(started.read_text().splitlines()) < 3):
            time.sleep(0.05)
        assert len(started.read_text().splitlines()) == 3, up.output()
        up.signal(signal.SIGINT)
        assert up.wait(timeout=60) == 0, up.output()
        out = up.output()
        order = [out.index(s) for s in ("[up] stopping source (stop_order 0)", "[source] exit_peer stopped by signal",
                                        "[up] source stopped", "[up] stopping middle (stop_order 3)",
                                        "[middle] exit_peer stopped by signal", "[up] middle stopped",
                                        "[up] stopping sink (stop_order 9)", "[sink] exit_peer stopped by signal",
                                        "[up] sink stopped")]
        assert order == sorted(order), out
    finally:
        up.stop()


def test_a_node_that_ends_says_the_others_keep_running(tmp_path):
    """A node that is not required and ends cleanly leaves the others running, and the bring-up says
    how to stop them."""
    cfg = write(tmp_path, {"nodes": [{"name": "short", "script": EXIT, "args": ["--after", "0.2"]},
                                     {"name": "long", "script": EXIT}]})
    up = bringup(cfg)
    try:
        assert up.wait_seen(r"^\[up\] the other nodes keep running: Ctrl-C stops them \(short is not", 60), \
            up.output()
        up.signal(signal.SIGINT)
        assert up.wait(timeout=30) == 0, up.output()
        assert "[up] long stopped (exit status 0)" in up.output()
    finally:
        up.stop()


def test_a_second_ctrl_c_stops_every_wave_at_once(tmp_path):
    """Asked again while a wave is still stopping, the bring-up sends SIGTERM to every node at once
    instead of waiting stop_timeout_s per wave."""
    stubborn = tmp_path / "stubborn.py"
    stubborn.write_text("import signal, sys, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                        "print('ready', flush=True)\ntime.sleep(60)\n")
    cfg = write(tmp_path, {"stop_timeout_s": 30, "nodes": [
        {"name": "first", "script": str(stubborn), "stop_order": 0},
        {"name": "last", "script": str(stubborn), "stop_order": 9}]})
    up = bringup(cfg)
    try:
        assert up.wait_seen(r"^\[first\] ready", 30) and up.wait_seen(r"^\[last\] ready", 30), up.output()
        up.signal(signal.SIGINT)
        assert up.wait_seen(r"^\[up\] stopping first \(stop_order 0\)", 30), up.output()
        t0 = time.monotonic()
        up.signal(signal.SIGINT)
        assert up.wait(timeout=25) == 0, up.output()              # well before the first wave's 30 s
        assert time.monotonic() - t0 < 25
        out = up.output()
        assert "[up] asked again: stopping first, last at once (SIGTERM)" in out, out
        assert "[up] first stopped (exit status -15)" in out and "[up] last stopped (exit status -15)" in out
    finally:
        up.stop()
