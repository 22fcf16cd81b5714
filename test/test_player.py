"""Player as a real process: a use_sim_time subscriber process receives every message in stamp
order, the latched topic, and /clock in bag time; remap, topic filter and start offset apply."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import Imu

from indoor_loc.bag import BagWriter
from indoor_loc.errors import ConfigError
from indoor_loc.nodes.player_node import add_arguments, latched, parse_remaps, run

PEERS = Path(__file__).resolve().parent / "bag_peers"
# namespaces of our own: other DDS tests on this machine may share the domain and use /walkNN
U = f"bagtest{os.getpid()}"
T0 = 1_700_000_000_000_000_000
DT = 10_000_000                  # 100 Hz


def _make_bag(path: Path, ns: str, n: int) -> None:
    with BagWriter(path, chunk_size=4000) as w:
        gt = PathMsg()
        gt.header.frame_id = "map"
        gt.poses = [PoseStamped(), PoseStamped(), PoseStamped()]
        w.write(f"{ns}/ground_truth", gt, T0)
        for i in range(n):
            m = Imu()
            m.header.frame_id = str(i)
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(T0 + i * DT, 10**9)
            w.write(f"{ns}/imu/data_raw", m, T0 + i * DT)


def _ready(proc, max_lines: int = 50) -> bool:
    """Whether the peer says "ready" (lines before it are the middleware's: Fast DDS logs a shared-memory
    port it cannot lock, left behind by a process killed earlier, and goes on over UDP)."""
    for _ in range(max_lines):
        line = proc.stdout.readline()
        if not line:
            return False
        if line.strip() == "ready":
            return True
    return False


def _play_and_listen(bag: Path, listen_ns: str, expected: int, *player_args: str) -> tuple[list[str], str]:
    env = os.environ.copy()
    # the subscriber's deadline runs from before the player starts, which on a loaded machine can take
    # tens of seconds: it ends as soon as it has every message, the deadline only bounds a failure
    sub = subprocess.Popen([sys.executable, str(PEERS / "subscriber.py"), listen_ns, str(expected), "90"],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        assert _ready(sub)
        player = subprocess.run([sys.executable, "-m", "indoor_loc.nodes.player_node", str(bag),
                                 "--wait-for-subscribers", "30", *player_args],
                                capture_output=True, text=True, env=env, timeout=90)
        out, _ = sub.communicate(timeout=90)
    finally:
        if sub.poll() is None:            # a failed test leaves nothing running in its domain
            sub.kill()
            sub.communicate(timeout=10)
    assert player.returncode == 0, player.stdout + player.stderr
    return out.splitlines(), player.stderr


# the tests' time bounds are above the sum of their condition deadlines (which a loaded machine may use
# up one after another), not expected durations
@pytest.mark.timeout(240)
def test_player_publishes_in_order_with_clock(ros_domain: int, tmp_path: Path) -> None:
    bag = tmp_path / "walk.mcap"
    n = 80
    _make_bag(bag, f"/{U}_5", n)
    lines, log = _play_and_listen(bag, f"/{U}_5", n, "--clock", "--rate", "2")
    imu = [ln.split() for ln in lines if ln.startswith("imu ")]
    assert [int(f[1]) for f in imu] == list(range(n)), lines[-5:]
    assert [int(f[2]) for f in imu] == [T0 + i * DT for i in range(n)]
    assert "gt 3" in lines                                           # latched topic delivered
    clocks = [int(ln.split()[1]) for ln in lines if ln.startswith("clock ")]
    assert clocks and all(T0 <= c <= T0 + n * DT for c in clocks)  # /clock runs in bag time
    assert clocks == sorted(clocks)
    # the subscriber's clock (use_sim_time) follows /clock: bag time, never wall time (0 = no
    # /clock received yet, possible for the first messages on a loaded machine)
    sim_now = [int(f[3]) for f in imu]
    assert sim_now[-1] > 0 and all(t == 0 or T0 <= t <= T0 + (n + 10) * DT for t in sim_now)
    done = [ln for ln in lines if ln.startswith("done")][0]
    n_clock = int(done.split()[3])
    # 0.4 s of wall time at 100 Hz: about 40 /clock messages (fewer if the machine is slow)
    assert 5 <= n_clock <= 80, done
    assert f"played {n + 1} messages" in log


@pytest.mark.timeout(240)
def test_player_remap_topics_and_start_offset(ros_domain: int, tmp_path: Path) -> None:
    bag = tmp_path / "walk.mcap"
    n = 50
    _make_bag(bag, f"/{U}_6", n)
    # skip the first 0.2 s (20 messages), play only IMU, renamed into another namespace
    lines, log = _play_and_listen(bag, f"/{U}_other", n - 20, "--rate", "4", "--start-offset", "0.2",
                                  "--topics", f"/{U}_6/imu/data_raw",
                                  "--remap", f"/{U}_6/imu/data_raw:=/{U}_other/imu/data_raw")
    ids = [int(ln.split()[1]) for ln in lines if ln.startswith("imu ")]
    assert ids == list(range(20, n))
    assert not any(ln.startswith("gt ") for ln in lines)
    assert f"played {n - 20} messages" in log


def test_player_options_and_latched_topics() -> None:
    assert parse_remaps(["/a:=/b", "c:=d"]) == {"/a": "/b", "/c": "/d"}
    with pytest.raises(ConfigError, match="OLD:=NEW"):
        parse_remaps(["/a=/b"])
    for topic in ("/walk01/ground_truth", "/u/map/graph", "/backend/wifi_map", "/x/pf/pose"):
        assert latched(topic, "")
    assert not latched("/walk01/imu/data", "- durability: transient_local\n")   # contract wins
    assert latched("/foo", "- durability: transient_local\n")
    assert not latched("/foo", "- durability: transient_local\n- durability: volatile\n")
    p = argparse.ArgumentParser()
    add_arguments(p)
    a = p.parse_args(["x.mcap", "--clock"])
    assert a.clock == 100.0 and a.rate == 1.0 and not a.loop


def test_player_rejects_bad_options(tmp_path: Path, capsys, monkeypatch) -> None:
    from indoor_loc.cli import main
    bag = tmp_path / "b.mcap"
    _make_bag(bag, "/w", 2)
    p = argparse.ArgumentParser()
    add_arguments(p)
    for args, match in ([["--rate", "0"], "play.rate: expected > 0"], [["--clock", "-5"], "play.clock"],
                        [["--start-offset", "-1"], "play.start_offset"], [["--remap", "a"], "OLD:=NEW"]):
        with pytest.raises(ConfigError, match=match):
            run(p.parse_args([str(bag), *args]))
    assert main(["play", str(tmp_path / "missing.mcap")]) == 2         # BagError, before any DDS
    assert "does not exist" in capsys.readouterr().err
    monkeypatch.chdir(tmp_path)                                          # a relative path: where it looked
    assert main(["play", "missing.mcap"]) == 2
    assert f"bag missing.mcap does not exist (in {tmp_path})" in capsys.readouterr().err


@pytest.mark.timeout(150)
def test_player_loops_until_sigint(ros_domain: int, tmp_path: Path) -> None:
    import signal
    bag = tmp_path / "walk.mcap"
    n = 20
    _make_bag(bag, f"/{U}_7", n)
    env = os.environ.copy()
    # the subscriber's clock starts before the player process does: on a loaded machine (a fresh
    # clone compiling its modules, the parallel suite) the player can take tens of seconds to start
    sub = subprocess.Popen([sys.executable, str(PEERS / "subscriber.py"), f"/{U}_7", str(2 * n), "90"],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    assert _ready(sub)
    player = subprocess.Popen([sys.executable, "-m", "indoor_loc.nodes.player_node", str(bag), "--loop",
                               "--rate", "5", "--wait-for-subscribers", "20"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        out, _ = sub.communicate(timeout=100)
    finally:
        player.send_signal(signal.SIGINT)
        log, _ = player.communicate(timeout=30)
    assert player.returncode == 0, log
    ids = [int(ln.split()[1]) for ln in out.splitlines() if ln.startswith("imu ")]
    assert ids[: 2 * n] == list(range(n)) * 2, (ids, out[-500:], log)
    assert "looping" in log



@pytest.mark.timeout(120)
def test_player_publishes_diagnostics(ros_domain: int, tmp_path: Path) -> None:
    """The player reports on /diagnostics like every node: what it published, and a WARN for
    topics played without a subscriber (here: nobody listens to the IMU)."""
    import threading

    from diagnostic_msgs.msg import DiagnosticArray

    from helpers_dds import ros_node, spin_until
    from indoor_loc.contract import Qos
    from indoor_loc.nodes.base import qos_profile
    from indoor_loc.nodes.player_node import PlayerNode
    from msg_adapters.diagnostics import diagnostics_from_msg

    bag = tmp_path / "walk.mcap"
    n = 30
    _make_bag(bag, f"/{U}_9", n)
    with ros_node("probe") as (probe, ex):
        got: list = []
        probe.create_subscription(DiagnosticArray, "/diagnostics",
                                  lambda m: got.extend(diagnostics_from_msg(m).values()), qos_profile(Qos.RELIABLE))
        player = PlayerNode([bag], rate=0.5, context=probe.context)       # 0.6 s of playback
        try:
            assert spin_until(ex, lambda: player._diag_pub.get_subscription_count() > 0, 40)
            t = threading.Thread(target=player.play)
            t.start()
            assert spin_until(ex, lambda: not t.is_alive() and any(
                s.values.get("published") == str(n + 1) for s in got if s.name == "/player"), 60)
            t.join()
        finally:
            player.destroy_node()
    mine = [s for s in got if s.name == "/player"]
    assert len(mine) >= 2                                       # during playback and at the end
    last = mine[-1]
    assert last.level == 1 and f"/{U}_9/imu/data_raw" in last.values["without_subscribers"]
    assert last.values["last_bag_stamp_ns"] == str(T0 + (n - 1) * DT)


def test_min_subscribers_parsing() -> None:
    from indoor_loc.nodes.player_node import MinSubscribers
    m = MinSubscribers(["2", "imu/mag=3", "/walk16/imu/mag=4", "data_raw=0"])
    assert m("/walk16/imu/data_raw") == 0 and m("/alice/imu/data_raw") == 0
    assert m("/walk16/imu/mag") == 4 and m("/alice/imu/mag") == 3          # a full name beats a relative one
    assert m("/alice/wifi/scan") == 2 and m("/alice/xyzimu/mag") == 2     # relative names match whole elements
    assert MinSubscribers()("/x") == 1
    assert m.unused(["/alice/imu/mag", "/alice/imu/data_raw"]) == ["/walk16/imu/mag"]
    for bad in ("x", "-1", "imu/mag=", "=2", "/=1", "imu/mag=two"):
        with pytest.raises(ConfigError, match="min_subscribers"):
            MinSubscribers([bad])


@pytest.mark.timeout(240)
def test_player_waits_for_the_subscribers_it_is_told_of(ros_domain: int, tmp_path: Path) -> None:
    """Two processes subscribe to a topic; one matches late. With ``--min-subscribers TOPIC=2`` the
    player waits for both (a stable count of one is not enough), so neither misses a message."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from helpers_dds import Peer, ros_node, spin_for, spin_until

    ns = f"/{U}_m"
    bag = tmp_path / "walk.mcap"
    n = 40
    _make_bag(bag, ns, n)
    got: dict[str, list[int]] = {"first": [], "late": []}
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    with ros_node("probe") as (probe, ex):
        probe.create_subscription(Imu, f"{ns}/imu/data_raw", lambda m: got["first"].append(int(m.header.frame_id)),
                                  qos)
        player = Peer([sys.executable, "-m", "indoor_loc.nodes.player_node", str(bag), "--rate", "4",
                       "--topics", f"{ns}/imu/data_raw", "--wait-for-subscribers", "40",
                       "--min-subscribers", "imu/data_raw=2"])
        try:
            assert player.wait_line("imu/data_raw", 60), player.output()     # publisher created
            spin_for(ex, 2.5)                      # the first subscriber alone: well past the settle time
            assert got["first"] == [], player.output()
            probe.create_subscription(Imu, f"{ns}/imu/data_raw",
                                      lambda m: got["late"].append(int(m.header.frame_id)), qos)
            assert spin_until(ex, lambda: len(got["first"]) == n and len(got["late"]) == n, 60), \
                (len(got["first"]), len(got["late"]), player.output())
            assert player.wait(timeout=60) == 0, player.output()
        finally:
            player.stop()
    assert got["first"] == got["late"] == list(range(n))
    assert f"subscribers when playing starts: {ns}/imu/data_raw 2" in player.output()
    assert "fewer subscribers" not in player.output()


def test_clock_never_runs_past_the_next_message(ros_domain: int, tmp_path: Path, monkeypatch) -> None:
    """A player that stalls (here its monotonic clock jumps 0.1 s after the 5th message, as a loaded
    machine may deschedule it) publishes the late messages at once, and /clock never passes the stamp
    of the next message to publish: nodes on sim time are not told a time whose data is still to come."""
    import time as real_time

    from helpers_dds import ros_node
    from indoor_loc.nodes import player_node

    class StallingTime:
        """The player's time: sleeps advance it at once; the test makes it jump."""
        def __init__(self) -> None:
            self.t = 1000.0

        def monotonic(self) -> float:
            return self.t

        def sleep(self, s: float) -> None:
            self.t += max(s, 1e-4)

        def time_ns(self) -> int:
            return real_time.time_ns()

    fake = StallingTime()
    monkeypatch.setattr(player_node, "time", fake)
    bag = tmp_path / "walk.mcap"
    n = 20
    _make_bag(bag, f"/{U}_c", n)            # ground truth at T0, then imu i at T0 + i DT
    with ros_node("probe") as (probe, _):
        player = player_node.PlayerNode([bag], rate=1.0, clock_hz=100.0, context=probe.context)
        try:
            seen: list[tuple[int, int]] = []           # (messages published so far, /clock value)
            publish_clock, diagnostics = player._publish_clock, player._maybe_diagnostics

            def clock(bag_ns: int) -> None:
                seen.append((player.published, bag_ns))
                publish_clock(bag_ns)

            def after_publish(force: bool = False) -> None:
                if player.published == 5 and fake.t < 1001.0:
                    fake.t += 0.1                      # the stall: 0.1 s (10 messages) with nothing done
                diagnostics(force)
            monkeypatch.setattr(player, "_publish_clock", clock)
            monkeypatch.setattr(player, "_maybe_diagnostics", after_publish)
            player.play()
        finally:
            player.destroy_node()
    assert player.published == n + 1
    assert any(k > 15 for k, _ in seen)                   # /clock goes on once the player caught up
    assert [c for _, c in seen] == sorted(c for _, c in seen)
    next_stamp = [T0] + [T0 + i * DT for i in range(n)]  # stamp of the k-th message played
    assert all(c <= next_stamp[k] for k, c in seen if k < len(next_stamp)), \
        [(k, c - T0) for k, c in seen if k < len(next_stamp) and c > next_stamp[k]]
