"""``imu_node``'s column path for runs of ``imu/data_raw`` (``indoor_loc/pipeline/imu_raw_run.py``) gives
what one sample at a time gives: the same ``pdr/odom`` and ``imu/data`` (byte for byte), in the same
order, the same counters."""
from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from indoor_loc.bag.bulk import bulk_items
from indoor_loc.bag.cdr_padding import canonical_cdr
from indoor_loc.pipeline import imu_raw_run
from indoor_loc.pipeline.imu_stage import ImuStage, ImuStageParams
from msg_adapters.imu import imu_to_msg
from msg_adapters.imu_cdr import imu_cdr, imu_cdr_run

S = 1_000_000_000


def _walk(n: int = 2000, rate_hz: float = 50.0) -> list[bytes]:
    """A phone walking at 1.8 Hz and turning slowly, with jittery stamps and one 0.8 s gap."""
    rng = np.random.default_rng(3)
    out, t = [], 100 * S
    for k in range(n):
        t += int(S / rate_hz) + int(rng.integers(-300_000, 300_000)) + (800_000_000 if k == 1200 else 0)
        acc = np.array([0.3, 0.2, 9.81 + 2.4 * np.sin(2 * np.pi * 1.8 * k / rate_hz)]) + rng.normal(0, 0.08, 3)
        gyro = np.array([0.01, -0.02, 0.25 * np.cos(0.1 * k / rate_hz)]) + rng.normal(0, 0.01, 3)
        out.append(serialize_message(imu_to_msg(t, "u1/imu", acc, gyro)))
    return out


def _recv(data: bytes) -> int:
    return int.from_bytes(data[4:8], "little") * S + int.from_bytes(data[8:12], "little") + 3_000_000


def _bytes(outs):
    return [(t, m if isinstance(m, bytes) else canonical_cdr(m)) for t, m in outs]   # (padding bytes vary)


@pytest.mark.parametrize("heading_source", ["auto", "aekf"])      # auto: VQF
@pytest.mark.parametrize("raw_outputs", [True, False])
def test_raw_runs_equal_one_sample_at_a_time(raw_outputs, heading_source, monkeypatch):
    datas = _walk()
    one = ImuStage(ImuStageParams(heading_source=heading_source), namespace="/u1")
    many = ImuStage(ImuStageParams(heading_source=heading_source), namespace="/u1")
    one.raw_outputs = many.raw_outputs = raw_outputs
    want = []
    for d in datas:
        items = bulk_items("sensor_msgs/msg/Imu", [d])
        want += [(t, m) for _, t, m in one.process_batch("imu/data_raw", items, [_recv(d)])]
    taken = []
    original = imu_raw_run.process_raw_run

    def spy(stage, items, recv_ns):
        taken.append(len(items))
        return original(stage, items, recv_ns)
    monkeypatch.setattr(imu_raw_run, "process_raw_run", spy)
    rng = np.random.default_rng(5)
    got, i = [], 0
    while i < len(datas):
        k = int(rng.choice([1, 2, 3, 5, 12, 40, 150]))
        run = datas[i:i + k]
        items = bulk_items("sensor_msgs/msg/Imu", run)
        got += [(t, m) for _, t, m in many.process_batch("imu/data_raw", items, [_recv(d) for d in run])]
        i += k
    assert sum(taken) > 0.8 * len(datas)            # the column path took the steady runs
    topics = [t for t, _ in want]
    assert topics.count("pdr/odom") > 40 and topics.count("imu/data") > 1900
    assert _bytes(got) == _bytes(want)
    assert many.diag.published == one.diag.published
    assert many.diag.received["imu/data_raw"].count == one.diag.received["imu/data_raw"].count == len(datas)
    assert many.diag.rejected == one.diag.rejected
    assert many.extra_diagnostics() == one.extra_diagnostics()


def test_imu_cdr_run_equals_imu_cdr_and_refuses_what_it_refuses():
    rng = np.random.default_rng(2)
    n = 7
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    acc, gyro = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    cov = np.diag([1e-3, 1e-3, 3.3])
    stamps = [5 * S + k * 20_000_123 for k in range(n)]
    for frame in ("u1/imu", "", "abc"):
        got = imu_cdr_run(stamps, frame, acc, gyro, q, cov)
        assert got == [imu_cdr(t, frame, acc[k], gyro[k], q[k], cov) for k, t in enumerate(stamps)]
    bad = q.copy()
    bad[3] *= 1.1                                   # not a unit quaternion
    assert imu_cdr_run(stamps, "f", acc, gyro, bad, cov) is None
    nan = acc.copy()
    nan[2, 1] = np.nan
    assert imu_cdr_run(stamps, "f", nan, gyro, q, cov) is None
    assert imu_cdr_run(stamps, "f", acc, gyro, q, np.full((3, 3), -1.0)) is None
