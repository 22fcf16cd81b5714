"""A sample a node cannot take never stops its input (over DDS, the sender in another process).

A truncated or garbage sample reaches the node (its inputs are raw) and is counted ``undecodable``.
An empty one never does: Fast DDS refuses a DATA submessage without payload, so a reliable
subscription waits for it and holds back everything after it from that publisher. The node sees the
input stall with its publisher still there, listens beside it best effort, finds the publisher's
numbers going on, counts the missing sample ``undecodable`` and those held back as lost, and
subscribes anew: the later messages are processed. The same on the per-message path, the raw fast
path (``imu/data_raw`` handed over in runs) and a multi-user stage's per-user subscriptions.
"""
from __future__ import annotations

import re
import signal
import sys
import time

import pytest
from rclpy.serialization import serialize_message

from helpers_dds import PEERS, Peer, python_peer, ros_node, spin_until
from msg_adapters.imu import imu_from_msg, imu_to_msg
from indoor_loc.nodes.stage_node import StageNode

sys.path.insert(0, str(PEERS))
from dummy_node import DummyStage  # noqa: E402
from raw_sender import write_samples  # noqa: E402

pytestmark = pytest.mark.timeout(120)

T0 = 1_000_000_000
PERIOD_S = 0.05


class _Counting(DummyStage):
    """Records the stamps it accepts (no outputs)."""
    NODE_NAME = "zl_node"

    def __init__(self, params, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        self.stamps: list[int] = []

    def _on_imu(self, msg, recv_ns: int, user: str | None = None):
        self.stamps.append(imu_from_msg(msg).stamp_ns)
        return []


class _FastStage(_Counting):
    """Takes imu/data_raw in runs (the node's raw fast path)."""
    NODE_NAME = "zl_fast_node"

    def __init__(self, params, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        self.on_batch("imu/data_raw", lambda sample, recv_ns: self.stamps.append(sample.stamp_ns) or [])


class _UsersStage(_Counting):
    """One instance for every user (per-user subscriptions, users discovered in the graph)."""
    NODE_NAME = "zl_users_node"
    MULTI_USER = True


def _samples() -> tuple[list[bytes], list[int]]:
    """40 good IMU samples with a truncated and a garbage one among them, an empty one, 100 good."""
    good = [T0 + i * 50_000_000 for i in range(140)]
    data = [serialize_message(imu_to_msg(t, "f", [0.1, 0.2, 9.8])) for t in good]
    samples = data[:30] + [b"\x00\x01\x00\x00", b"\xff" * 12] + data[30:40] + [b""] + data[40:]
    return samples, good


@pytest.mark.parametrize("stage_cls,ns", [(_Counting, "/zl_msg"), (_FastStage, "/zl_fast"), (_UsersStage, "")])
def test_later_messages_are_processed_after_a_sample_the_node_cannot_take(ros_domain, tmp_path, stage_cls, ns):
    samples, good = _samples()
    path = tmp_path / "samples.bin"
    write_samples(path, samples)
    topic = f"{ns or '/carol'}/imu/data_raw"
    with ros_node("probe") as (probe, ex):
        node = StageNode(stage_cls, context=probe.context, **({"namespace": ns} if ns else {}))
        ex.add_node(node)
        sender = python_peer("raw_sender.py", str(path), topic, "sensor_msgs/msg/Imu", str(PERIOD_S))
        try:
            assert spin_until(ex, lambda: sender.proc.poll() is not None, 60), sender.output()[-2000:]
            assert sender.proc.returncode == 0, sender.output()[-2000:]
            stage = node.stage
            assert spin_until(ex, lambda: stage.stamps and stage.stamps[-1] == good[-1], 10), \
                (len(stage.stamps), stage.diag.rejected)
            diag = stage.diag
            assert stage.stamps[:40] == good[:40]                           # all before the empty sample
            assert stage.stamps == sorted(set(stage.stamps)) and set(stage.stamps) <= set(good)
            lost = sum(diag.lost.values())
            assert len(stage.stamps) + lost == len(good), (len(stage.stamps), lost)
            assert len(stage.stamps) >= 60                                   # the stream goes on after it
            assert dict(diag.rejected) == {"undecodable": 3}                 # truncated, garbage, empty
            inp = node._inputs[topic if stage.MULTI_USER else "imu/data_raw"]
            assert inp.watch.resubscribed == 1
            # the probe closes once the subscription delivers again, or (the stream may have ended on
            # the probe) once the publisher has left the graph: about a second on a loaded machine
            assert spin_until(ex, lambda: inp.probe is None, 10)
        finally:
            sender.stop()
            ex.remove_node(node)
            node.destroy_node()


def test_the_recorder_records_on_after_a_sample_it_cannot_take(ros_domain, tmp_path):
    """The recorder's reliable subscription stuck behind an empty sample is made anew: the later
    messages are in the bag; the refused one and those held back are counted lost."""
    from indoor_loc.bag.reader import read_raw
    from indoor_loc.nodes.inputs import _cdr_stamp_ns
    samples, good = _samples()
    path = tmp_path / "samples.bin"
    write_samples(path, samples)
    out = tmp_path / "rec.mcap"
    topic = "/zlrec/imu/data_raw"
    recorder = Peer([sys.executable, "-m", "indoor_loc.nodes.recorder_node", "-t", topic, "-o", str(out)])
    sender = python_peer("raw_sender.py", str(path), topic, "sensor_msgs/msg/Imu", str(PERIOD_S))
    try:
        assert sender.wait(timeout=60) == 0, sender.output()[-2000:] + recorder.output()[-2000:]
        assert recorder.wait_seen("subscribed anew", 10), recorder.output()[-3000:]
        time.sleep(2.0)                                   # the last ones written
        recorder.signal(signal.SIGINT)
        assert recorder.wait(timeout=30) == 0, recorder.output()[-3000:]
    finally:
        sender.stop()
        recorder.stop()
    datas = [m.data for m in read_raw(out, [topic])]
    assert [d for d in datas if len(d) <= 12] == samples[30:32]        # the truncated and garbage ones, as sent
    stamps = [_cdr_stamp_ns(d) for d in datas if len(d) > 12]
    lost = re.search(r"LOST before reaching the recorder: (\d+) messages", recorder.output())
    assert lost is not None, recorder.output()[-2000:]
    assert stamps[:40] == good[:40] and stamps[-1] == good[-1] and len(stamps) >= 60
    assert stamps == sorted(set(stamps)) and set(stamps) <= set(good)
    # the truncated and garbage samples are recorded as sent; the empty one and those held back are lost
    assert len(stamps) + 2 + int(lost.group(1)) == len(samples), (len(stamps), lost.group(0))
