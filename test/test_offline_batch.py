"""Offline IMU batch path (bulk CDR decoding + ``Stage.process_batch``) == message by message (live path)."""
from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from indoor_loc.bag import BagWriter, read_bag
from indoor_loc.bag.bulk import bulk_items, decode_imu, decode_mag
from indoor_loc.pipeline.offline import run_offline
from indoor_loc.imu.stepometer import Stepometer
from indoor_loc.pipeline.imu_stage import ImuStage
from msg_adapters.imu import imu_from_msg, imu_to_msg, mag_from_msg, mag_to_msg

S = 1_000_000_000


def _quat_z(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])


def test_bulk_decode_equals_the_adapters():
    rng = np.random.default_rng(1)
    msgs = [imu_to_msg(10 * S + k * 7_654_321, "phone/imu", rng.normal(0, 3, 3), rng.normal(0, 1, 3),
                       _quat_z(rng.uniform(-3, 3)), np.diag(rng.uniform(0.01, 0.1, 3))) for k in range(50)]
    msgs[3] = imu_to_msg(10 * S + 3 * 7_654_321, "phone/imu", rng.normal(0, 3, 3))   # no gyro, no orientation
    items = bulk_items("sensor_msgs/msg/Imu", [serialize_message(m) for m in msgs])
    assert items is not None and len(items) == len(msgs)
    for got, m in zip(items, msgs):
        want = imu_from_msg(m)
        assert got.stamp_ns == want.stamp_ns and got.frame_id == want.frame_id == "phone/imu"
        for a, b in zip(got[2:], want[2:]):
            assert (a is None) == (b is None)
            if a is not None:
                np.testing.assert_array_equal(a, b)
    mags = [mag_to_msg(5 * S + k * S // 50, "phone/mag", rng.normal(0, 4e-5, 3)) for k in range(20)]
    got_mag = bulk_items("sensor_msgs/msg/MagneticField", [serialize_message(m) for m in mags])
    assert got_mag is not None
    for (t, f), m in zip(got_mag, mags):
        t2, f2 = mag_from_msg(m)
        assert t == t2
        np.testing.assert_array_equal(f, f2)
    # not one layout (another frame id) or a message the adapter rejects: not taken in bulk
    other = imu_to_msg(11 * S, "other_frame", [0.0, 0.0, 9.8])
    assert decode_imu([serialize_message(msgs[0]), serialize_message(other)]) is None
    bad = imu_to_msg(12 * S, "phone/imu", [0.0, 0.0, 9.8])
    bad.linear_acceleration.x = float("nan")
    assert decode_imu([serialize_message(bad)]) is not None
    assert bulk_items("sensor_msgs/msg/Imu", [serialize_message(msgs[0]), serialize_message(bad)]) is None
    assert decode_mag([b"\x00\x01\x00\x00"]) is None


def _bag(path):
    """Two users on overlapping clocks: /u1 raw IMU at 100 Hz + magnetometer at 50 Hz (with a NaN
    sample and a stamp going backwards), /u2 phone orientation at 50 Hz; walking at 1.8 Hz."""
    rng = np.random.default_rng(7)
    with BagWriter(path) as w:
        for k in range(2500):
            t = 3 * S + k * 10_000_000 + int(rng.integers(0, 200_000))
            yaw = 0.3 * np.sin(0.2 * k / 100)
            acc = np.array([0.2, 0.1, 9.81 + 2.5 * np.sin(2 * np.pi * 1.8 * k / 100)]) + rng.normal(0, 0.05, 3)
            gyro = np.array([0.0, 0.0, 0.3 * 0.2 * np.cos(0.2 * k / 100)]) + rng.normal(0, 0.01, 3)
            stamp = t - 50_000_000 if k == 1500 else t
            msg = imu_to_msg(stamp, "u1/imu", acc, gyro)
            if k == 700:
                msg.linear_acceleration.x = float("nan")
            w.write("/u1/imu/data_raw", msg, t)
            if k % 2 == 0:
                field = 4e-5 * np.array([np.cos(-yaw), np.sin(-yaw), -0.8])
                w.write("/u1/imu/mag", mag_to_msg(t + 1_000_000, "u1/imu", field), t + 1_000_000)
                t2 = t + 3_000_000
                acc2 = np.array([0.0, 0.3, 9.81 + 2.0 * np.sin(2 * np.pi * 1.7 * k / 100)]) + rng.normal(0, 0.05, 3)
                w.write("/u2/imu/data", imu_to_msg(t2, "u2/imu", acc2, None, _quat_z(0.5 + yaw),
                                                   np.diag([0.01, 0.01, 0.02])), t2)


def _content(out):
    """Every output message (deserialised: CDR padding bytes are not part of a message) per topic in
    stamp order, /diagnostics without its wall-clock timings."""
    per_topic: dict[str, list] = {}
    diags = []
    for m in read_bag([out]):
        if m.topic != "/diagnostics":
            per_topic.setdefault(m.topic, []).append((m.stamp_ns, m.msg))
            continue
        for st in m.msg.status:
            kv = tuple((v.key, v.value) for v in st.values if not v.key.startswith("process_ms"))
            diags.append((m.stamp_ns, st.name, st.level, st.message, kv))
    return per_topic, sorted(diags)


def test_batch_path_gives_the_message_by_message_output(tmp_path, monkeypatch):
    bag = tmp_path / "in.mcap"
    _bag(bag)
    params = tmp_path / "params.yaml"
    params.write_text("/u2/imu_node:\n  ros__parameters:\n    heading_source: orientation\n")
    calls = []
    original = ImuStage.process_batch
    steady = []
    extend = Stepometer.extend_steady

    def spy(self, topic, items, recv_ns):
        calls.append((self.namespace, topic, len(items)))
        return original(self, topic, items, recv_ns)

    def spy_extend(self, t, acc):
        steady.append(len(t))
        return extend(self, t, acc)

    monkeypatch.setattr(ImuStage, "process_batch", spy)
    monkeypatch.setattr(Stepometer, "extend_steady", spy_extend)
    a = run_offline([bag], tmp_path / "batch.mcap", nodes=["imu"], params=params, progress=False)
    assert {(ns, t) for ns, t, _ in calls} == {("/u1", "imu/data_raw"), ("/u1", "imu/mag"), ("/u2", "imu/data")}
    assert sum(steady) > 1000                       # /u2's orientations went through the column path
    n_batched = sum(n for *_, n in calls)
    calls.clear()
    b = run_offline([bag], tmp_path / "single.mcap", nodes=["imu"], params=params, progress=False, batch=False)
    assert not calls
    assert n_batched >= 0.9 * b.messages_in        # all but the runs holding the bad messages
    raw_a, diag_a = _content(tmp_path / "batch.mcap")
    raw_b, diag_b = _content(tmp_path / "single.mcap")
    assert {"/u1/pdr/odom", "/u1/imu/data", "/u2/pdr/odom"} <= set(raw_b)
    assert len(raw_b["/u1/pdr/odom"]) > 20 and len(raw_b["/u2/pdr/odom"]) > 20
    assert raw_a == raw_b                           # same messages, same values (exactly)
    assert diag_a == diag_b and len(diag_b) > 40
    strip = {k: {kk: v for kk, v in kv.items() if not kk.startswith("process_ms")} for k, kv in a.per_stage.items()}
    assert strip == {k: {kk: v for kk, v in kv.items() if not kk.startswith("process_ms")}
                     for k, kv in b.per_stage.items()}
    assert a.per_stage["/u1/imu_node"]["rejected.nan"] == "1"
    assert a.per_stage["/u1/imu_node"]["rejected.non_monotonic_stamp"] == "1"
    assert (a.messages_in, a.messages_out, a.ticks) == (b.messages_in, b.messages_out, b.ticks)


@pytest.mark.parametrize("frame", ["u1/imu", ""])
def test_bulk_decode_handles_frame_id_lengths(frame):
    msgs = [imu_to_msg(S + k, frame, [0.0, 0.1 * k, 9.8]) for k in range(3)]
    arr = decode_imu([serialize_message(m) for m in msgs])
    assert arr is not None and arr.frame_id == frame
    np.testing.assert_array_equal(arr.linear_acceleration[:, 1], [0.0, 0.1, 0.2])


def test_unchanged_statuses_are_written_again_with_the_new_stamp(tmp_path, monkeypatch):
    """/diagnostics of a stage that did nothing since its last status is that status restamped: the
    output equals building every status afresh, including a WARN that ends while the user is idle."""
    import msg_adapters.diagnostics as diagnostics
    from indoor_loc.pipeline import offline

    bag = tmp_path / "in.mcap"
    rng = np.random.default_rng(3)
    with BagWriter(bag) as w:
        for k in range(3000):                              # 50 Hz: /a for 30 s (a NaN at 24 s), /b for 60 s
            t = 5 * S + k * 20_000_000
            for ns, end in (("/a", 1500), ("/b", 3000)):
                if k >= end:
                    continue
                acc = np.array([0.0, 0.2, 9.81 + 2.0 * np.sin(2 * np.pi * 1.8 * k / 50)]) + rng.normal(0, 0.05, 3)
                msg = imu_to_msg(t, ns[1:] + "/imu", acc, None, _quat_z(0.01 * k), np.diag([0.01, 0.01, 0.02]))
                if ns == "/a" and k == 1200:
                    msg.linear_acceleration.y = float("nan")
                w.write(ns + "/imu/data", msg, t)
    params = tmp_path / "params.yaml"
    params.write_text("/**/imu_node:\n  ros__parameters:\n    heading_source: orientation\n")
    built = []
    original = diagnostics.stage_diagnostics

    def spy(name, stage, now_ns):
        built.append(name)
        return original(name, stage, now_ns)

    monkeypatch.setattr(diagnostics, "stage_diagnostics", spy)
    a = run_offline([bag], tmp_path / "reuse.mcap", nodes=["imu"], params=params, progress=False)
    n_reused = a.ticks * 2 - len(built)
    monkeypatch.setattr(offline, "REUSE_DIAGNOSTICS", False)
    built.clear()
    b = run_offline([bag], tmp_path / "fresh.mcap", nodes=["imu"], params=params, progress=False)
    assert len(built) == b.ticks * 2 and n_reused > 20       # /a idle for 30 ticks
    raw_a, diag_a = _content(tmp_path / "reuse.mcap")
    raw_b, diag_b = _content(tmp_path / "fresh.mcap")
    assert raw_a == raw_b and len(raw_b["/a/pdr/odom"]) > 10
    assert diag_a == diag_b
    levels_a = [int.from_bytes(level, "little") for t, name, level, *_ in diag_b if name == "/a/imu_node"]
    assert levels_a[-1] == 0 and 1 in levels_a[-35:]       # the WARN of the NaN ends while /a is idle
    restamped = [(m.msg.header.stamp.sec * S + m.msg.header.stamp.nanosec, m.stamp_ns)
                 for m in read_bag([tmp_path / "reuse.mcap"]) if m.topic == "/diagnostics"]
    assert len(restamped) == 2 * a.ticks and all(h == t for h, t in restamped)


def test_with_header_stamp_changes_only_the_stamp():
    from rclpy.serialization import deserialize_message
    from diagnostic_msgs.msg import DiagnosticArray

    from indoor_loc.bag.bulk import with_header_stamp
    from msg_adapters.diagnostics import status_array

    arr = status_array("/u1/imu_node", 1, "1 messages rejected", {"in.imu/data.count": "12"}, 7 * S + 5)
    data = with_header_stamp(serialize_message(arr), 2_000_000_000 * S + 999_999_999)
    assert data is not None
    got = deserialize_message(data, DiagnosticArray)
    assert (got.header.stamp.sec, got.header.stamp.nanosec) == (2_000_000_000, 999_999_999)
    arr.header.stamp = got.header.stamp
    assert got == arr
    assert with_header_stamp(serialize_message(arr), -1) is None
    assert with_header_stamp(serialize_message(arr), 2**31 * S) is None
    assert with_header_stamp(b"\x01\x00" + serialize_message(arr)[2:], S) is None     # big-endian CDR


def test_heading_history_add_many_and_at_equal_one_sample_at_a_time():
    from indoor_loc.imu.pdr import HeadingHistory
    from indoor_loc.measurements import wrap_angle

    rng = np.random.default_rng(11)
    t = np.cumsum(rng.integers(1, 30_000_000, 3000)).tolist()
    t[500] = t[499]                                             # a repeated stamp is skipped by both
    yaw = wrap_angle(np.cumsum(rng.normal(0, 0.3, 3000))).tolist()   # crosses +-pi many times
    var = rng.uniform(0.01, 0.1, 3000).tolist()
    one, many = HeadingHistory(horizon_s=10.0), HeadingHistory(horizon_s=10.0)
    for k in range(3000):
        one.add(t[k], yaw[k], var[k])
    for a, b in [(0, 1), (1, 700), (700, 2999), (2999, 3000)]:
        many.add_many(t[a:b], yaw[a:b], var[a:b])
    assert list(one._t) == list(many._t) and list(one._yaw) == list(many._yaw) and list(one._var) == list(many._var)
    for q in [t[0] - 5, t[-1] + 5] + rng.integers(t[-1] - 12 * S, t[-1], 200).tolist():
        got = many.at(q)
        # reference: np.searchsorted over a copy, linear interpolation of the unwrapped yaw
        ts = np.array(one._t)
        i = int(np.searchsorted(ts, q))
        if i <= 0:
            want = (wrap_angle(one._yaw[0]), one._var[0])
        elif i >= len(ts):
            want = (wrap_angle(one._yaw[-1]), one._var[-1])
        else:
            w = (q - ts[i - 1]) / float(ts[i] - ts[i - 1])
            want = (wrap_angle(one._yaw[i - 1] + w * (one._yaw[i] - one._yaw[i - 1])), max(one._var[i - 1], one._var[i]))
        assert got == want
