"""Recorder as a real process against a real publisher process: SIGINT / SIGTERM give a complete
bag (rosbags reads every message); SIGKILL leaves a file that `recover` makes valid up to the last
complete chunk."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import QosDurability, QosReliability

from indoor_loc.bag import bag_topics, recover, scan_records

PEERS = Path(__file__).resolve().parent / "bag_peers"
# namespaces of our own: other DDS tests on this machine may share the domain and use /walkNN
U = f"bagtest{os.getpid()}"


def _start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=os.environ.copy())


def _recorder(out: Path, *args: str) -> subprocess.Popen:
    return _start(["-m", "indoor_loc.nodes.recorder_node", "-o", str(out), *args])


def _wait_line(proc: subprocess.Popen, text: str, timeout: float) -> str:
    """Read the process output until a line containing ``text`` (or fail with what it printed)."""
    seen = []
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        seen.append(line)
        if text in line:
            return line
    raise AssertionError(f"no {text!r} line within {timeout} s; output:\n{''.join(seen)}")


def _stop(proc: subprocess.Popen, sig: int, timeout: float = 30.0) -> str:
    proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"process did not stop on signal {sig}:\n{out}") from None
    return out


def _kill(proc: subprocess.Popen) -> None:
    """A process the test could not stop as planned does not outlive it (its domain is used again)."""
    if proc.poll() is None:
        proc.kill()
        proc.communicate(timeout=10)


def _wait_recorded(path: Path, topic: str, at_least: int, timeout: float) -> int:
    """Wait until the bag being written holds ``at_least`` messages of ``topic`` in closed chunks
    (the recorder closes a chunk every second), so a signal is sent only once everything arrived."""
    end = time.monotonic() + timeout
    n = 0
    while time.monotonic() < end:
        if path.exists():
            scan = scan_records(path)
            n = sum(scan.counts.get(cid, 0) for cid, ch in scan.channels.items() if ch.topic == topic)
            if n >= at_least:
                break
        time.sleep(0.2)
    return n


def _read_imu_ids(path: Path, topic: str) -> tuple[list[int], dict]:
    with AnyReader([path]) as r:
        conns = {c.topic: c for c in r.connections}
        ids = [int(r.deserialize(raw, c.msgtype).header.frame_id)
               for c, _, raw in r.messages(connections=[conns[topic]])]
    return ids, conns


# the tests' time bounds are above the sum of their condition deadlines (which a loaded machine may use
# up one after another), not expected durations
@pytest.mark.timeout(180)
def test_sigint_gives_complete_bag_with_matched_qos(ros_domain: int, tmp_path: Path) -> None:
    out = tmp_path / "rec.mcap"
    pub = _start([str(PEERS / "publisher.py"), f"/{U}_1", "60", "100"])
    rec = _recorder(out, "-t", "imu/data_raw", "ground_truth", "--namespace", f"/{U}_1", "--chunk-size", "4000")
    try:
        _wait_line(pub, "published 60", 60)
        _wait_recorded(out, f"/{U}_1/imu/data_raw", 60, 60)
        log = _stop(rec, signal.SIGINT)
    finally:
        _kill(rec)
        pub.terminate()
        pub.communicate(timeout=10)
    assert rec.returncode == 0, log
    assert "recorded 61 messages" in log, log
    ids, conns = _read_imu_ids(out, f"/{U}_1/imu/data_raw")
    assert ids == list(range(60))
    assert conns[f"/{U}_1/ground_truth"].msgcount == 1          # latched, published before we subscribed
    assert conns[f"/{U}_1/ground_truth"].ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL
    assert conns[f"/{U}_1/imu/data_raw"].ext.offered_qos_profiles[0].reliability == QosReliability.RELIABLE
    assert bag_topics(out)[f"/{U}_1/imu/data_raw"] == ("sensor_msgs/msg/Imu", 60)


@pytest.mark.timeout(180)
def test_sigterm_with_all_topics_discovers_late_best_effort_publisher(ros_domain: int, tmp_path: Path) -> None:
    out = tmp_path / "all.mcap"
    rec = _recorder(out, "-a", "--poll", "0.3")
    pub = None
    try:
        # the recorder is up (it has looked at the graph once) before the publisher exists: found by polling
        _wait_line(rec, "recording all topics", 60)
        pub = _start([str(PEERS / "publisher.py"), f"/{U}_2", "40", "100", "--best-effort"])
        _wait_line(pub, "published 40", 60)
        _wait_recorded(out, f"/{U}_2/imu/data_raw", 40, 10)   # best effort may drop a few: then 10 s
        log = _stop(rec, signal.SIGTERM, timeout=30)
    finally:
        _kill(rec)
        if pub is not None:
            pub.terminate()
            pub.communicate(timeout=10)
    assert rec.returncode == 0, log
    assert f"/{U}_2/imu/data_raw: recording [sensor_msgs/msg/Imu] (best_effort, volatile" in log, log
    ids, conns = _read_imu_ids(out, f"/{U}_2/imu/data_raw")
    # best effort over loopback: in order, no duplicates, (nearly) all there
    assert ids == sorted(set(ids)) and len(ids) >= 36, ids
    assert conns[f"/{U}_2/imu/data_raw"].ext.offered_qos_profiles[0].reliability == QosReliability.BEST_EFFORT
    assert f"/{U}_2/ground_truth" in conns


@pytest.mark.timeout(180)
def test_sigkill_then_recover_keeps_complete_chunks(ros_domain: int, tmp_path: Path) -> None:
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu
    out, fixed = tmp_path / "killed.mcap", tmp_path / "fixed.mcap"
    chunk = 3000
    n = 150
    per_chunk = chunk // len(serialize_message(Imu())) + 2     # at most this many messages in one chunk
    pub = _start([str(PEERS / "publisher.py"), f"/{U}_3", str(n), "200"])
    rec = _recorder(out, "-t", f"/{U}_3/imu/data_raw", "--chunk-size", str(chunk), "--flush-interval", "0")
    try:
        _wait_line(pub, f"published {n}", 60)
        # the reliable stream has arrived: every chunk but the open one is written (then kill)
        _wait_recorded(out, f"/{U}_3/imu/data_raw", n - per_chunk, 60)
        rec.kill()                                   # SIGKILL: no summary, last chunk in memory
        rec.communicate(timeout=10)
    finally:
        _kill(rec)
        pub.terminate()
        pub.communicate(timeout=10)
    with pytest.raises(AnyReaderError):              # not a valid MCAP for an ordinary reader
        with AnyReader([out]) as r:
            list(r.messages())
    complete = scan_records(out).messages
    res = recover(out, fixed)
    assert res.messages == complete and not res.bad_chunks
    ids, _ = _read_imu_ids(fixed, f"/{U}_3/imu/data_raw")
    assert ids == list(range(len(ids)))              # every message of the complete chunks, in order
    assert n - per_chunk <= len(ids) <= n, (len(ids), per_chunk)   # lost at most the open chunk


def test_recorder_rejects_bad_options(tmp_path: Path) -> None:
    import argparse

    from indoor_loc.errors import ConfigError
    from indoor_loc.nodes.recorder_node import add_arguments, is_hidden, run
    p = argparse.ArgumentParser()
    add_arguments(p)
    for args, match in ([["--chunk-size", "0"], "chunk_size"], [["--poll", "0"], "poll"],
                        [["--flush-interval", "-1"], "flush_interval"]):
        with pytest.raises(ConfigError, match=match):
            run(p.parse_args(["-t", "/x", "-o", str(tmp_path / "x.mcap"), *args]))
    with pytest.raises(SystemExit):                   # -t and -a are exclusive, one is required
        p.parse_args(["-t", "/x", "-a"])
    assert is_hidden("/a/_action/status") and not is_hidden("/walk01/imu/data")


def test_recorder_refuses_to_overwrite(tmp_path: Path) -> None:
    import argparse

    from indoor_loc.errors import ConfigError
    from indoor_loc.nodes.recorder_node import add_arguments, run
    p = argparse.ArgumentParser()
    add_arguments(p)
    out = tmp_path / "x.mcap"
    out.write_bytes(b"an earlier recording")
    with pytest.raises(ConfigError, match="exists; refusing to overwrite it"):
        run(p.parse_args(["-t", "/x", "-o", str(out)]))
    assert out.read_bytes() == b"an earlier recording"
    assert p.parse_args(["-t", "/x", "-o", str(out), "--overwrite"]).overwrite


def _imu(k: int):
    from sensor_msgs.msg import Imu
    m = Imu()
    m.header.stamp.sec, m.header.stamp.nanosec = 1 + k // 200, (k % 200) * 5_000_000
    m.header.frame_id = str(k)
    return m


@pytest.mark.timeout(180)
def test_recorder_takes_bursts_and_counts_what_it_lost(ros_domain: int, tmp_path: Path, monkeypatch) -> None:
    """One callback takes everything already queued on every subscription (rclpy's per-callback
    cost is paid per burst, not per message); the bag keeps each topic's order; a message DDS
    overwrote before it was taken is counted; what is still queued at the end is taken too."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu

    from helpers_dds import ros_node, spin_until
    from indoor_loc.bag import BagWriter, read_raw
    from indoor_loc.nodes import recorder_node

    a, b = f"/{U}_b/imu/a", f"/{U}_b/imu/b"
    writer = BagWriter(tmp_path / "burst.mcap")
    writer.open()
    with ros_node("probe") as (probe, ex):
        qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {t: probe.create_publisher(Imu, t, qos) for t in (a, b)}
        monkeypatch.setattr(recorder_node, "SUB_DEPTH", 2000)       # DDS keeps 2000 per topic here
        rec = recorder_node.RecorderNode(writer, topics=[a, b], context=probe.context, flush_interval_s=0)
        rex = SingleThreadedExecutor(context=probe.context)
        rex.add_node(rec)
        try:
            assert set(rec._subs) == {a, b}
            assert spin_until(ex, lambda: all(p.get_subscription_count() == 1 for p in pubs.values()), 40)
            sent = {a: 0, b: 0}

            def publish(topic: str, n: int) -> None:
                for _ in range(n):
                    pubs[topic].publish(_imu(sent[topic]))
                    sent[topic] += 1
                assert pubs[topic].wait_for_all_acked(rclpy_duration(30))    # all in the recorder's queue

            publish(a, 1500)
            publish(b, 1500)
            # the first message callback takes the whole burst of both topics (a timer may run first)
            assert spin_until(rex, lambda: rec.received > 0, 30)
            assert rec.received == 3000, rec.received
            publish(a, 2500)                                # 500 more than DDS keeps: overwritten, counted
            assert spin_until(rex, lambda: rec.received >= 5000, 30)
            assert rec.received == 5000 and rec.lost == {a: 500}, (rec.received, rec.lost)
            publish(b, 300)                                 # queued when the spin ends: the last pass
            assert rec.take_remaining() == 300
        finally:
            rex.remove_node(rec)
            rec.destroy_node()
            rec.close()
            writer.close()
    got: dict[str, list[int]] = {a: [], b: []}
    log = []
    from rclpy.serialization import deserialize_message
    for m in read_raw([tmp_path / "burst.mcap"]):
        got[m.topic].append(int(deserialize_message(m.data, Imu).header.frame_id))
        log.append(m.stamp_ns)
    assert got[a] == list(range(1500)) + list(range(2000, 4000))      # the 500 oldest of the burst lost
    assert got[b] == list(range(1800))
    assert log == sorted(log)


def rclpy_duration(seconds: float):
    from rclpy.duration import Duration
    return Duration(seconds=seconds)
