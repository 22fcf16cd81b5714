"""MCAP bag I/O: what BagWriter writes is read back identically by an independent reader (rosbags),
carries rosbag2's layout (schemas, QoS, metadata record), merges across files, and survives a
writer killed at any byte (recover)."""
from __future__ import annotations

import array
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability, QosReliability

from indoor_loc.bag import BagWriter, bag_topics, read_bag, recover, scan_records
from indoor_loc.bag.schemas import DELIMITER, message_definition, msg_dependencies, parse_qos_yaml, qos_dict, qos_yaml
from indoor_loc.contract import TOPICS, msg_class
from indoor_loc.errors import BagError

T0 = 1_700_000_000_000_000_000


def _fill(msg, rng: np.random.Generator, depth: int = 0):
    """Set every field of an rclpy message to seeded random values (sequences get 0-3 elements)."""
    for name, typ in msg.get_fields_and_field_types().items():
        cur = getattr(msg, name)
        if typ in ("double", "float"):
            setattr(msg, name, float(np.float32(rng.normal())) if typ == "float" else float(rng.normal()))
        elif typ in ("int8", "int16", "int32", "int64"):
            setattr(msg, name, int(rng.integers(-100, 100)))
        elif typ in ("uint8", "uint16", "uint32", "uint64", "octet", "byte"):
            setattr(msg, name, int(rng.integers(0, 100)) if typ not in ("octet", "byte") else bytes([int(rng.integers(0, 4))]))
        elif typ == "boolean":
            setattr(msg, name, bool(rng.integers(0, 2)))
        elif typ == "string":
            setattr(msg, name, f"s{int(rng.integers(0, 1000))}")
        elif typ.startswith(("double[", "float[")):
            arr = rng.normal(size=len(cur))
            setattr(msg, name, arr.astype(np.float32) if typ.startswith("float") else arr)
        elif typ.startswith("sequence<") and depth < 3:
            inner = typ[len("sequence<"):-1]
            if inner == "string":
                setattr(msg, name, [f"v{i}" for i in range(int(rng.integers(0, 3)))])
            elif inner in ("double", "float"):
                setattr(msg, name, list(rng.normal(size=int(rng.integers(0, 3)))))
            elif "/" in inner:
                cls = msg_class(inner.replace("/", "/msg/", 1))
                setattr(msg, name, [_fill(cls(), rng, depth + 1) for _ in range(int(rng.integers(1, 3)))])
        elif "/" in typ and "[" not in typ and "<" not in typ:
            _fill(cur, rng, depth + 1)
    return msg


def _assert_same(ours, theirs, path: str = "msg") -> None:
    """Compare an rclpy message with a rosbags-deserialised one field by field."""
    for name in ours.get_fields_and_field_types():
        a, b = getattr(ours, name), getattr(theirs, name)
        where = f"{path}.{name}"
        if hasattr(a, "get_fields_and_field_types"):
            _assert_same(a, b, where)
        elif isinstance(a, (list, tuple)) and a and hasattr(a[0], "get_fields_and_field_types"):
            assert len(a) == len(b), where
            for i, (x, y) in enumerate(zip(a, b)):
                _assert_same(x, y, f"{where}[{i}]")
        elif isinstance(a, (list, tuple, np.ndarray, array.array)):
            assert len(a) == len(b), where
            if len(a) and isinstance(a[0], str):
                assert list(a) == list(b), where
            else:
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=where)
        elif isinstance(a, bytes):
            assert a[0] == int(b) % 256, where     # rosbags reads ROS 2 `byte` as int8
        elif isinstance(a, float):
            assert a == b or (math.isnan(a) and math.isnan(b)), where
        else:
            assert a == b, where


def _contract_types() -> list[str]:
    return sorted({t.type for t in TOPICS.values()})


@pytest.fixture
def contract_bag(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, dict[str, list]]:
    """A bag with every contract type on its contract topic under /walk01, 3 messages each."""
    path = tmp_path / "all.mcap"
    written: dict[str, list] = {}
    with BagWriter(path, chunk_size=4096) as w:
        for k in range(3):
            for i, (rel, spec) in enumerate(sorted(TOPICS.items())):
                topic = rel if rel.startswith("/") else f"/walk01/{rel}"
                msg = _fill(msg_class(spec.type)(), rng)
                w.write(topic, msg, T0 + k * 10**9 + i)
                written.setdefault(topic, []).append(msg)
    return path, written


def test_every_contract_type_reads_back_identically_with_rosbags(contract_bag) -> None:
    path, written = contract_bag
    got: dict[str, list] = {}
    with AnyReader([path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, stamp, raw in reader.messages():
            got.setdefault(conn.topic, []).append((stamp, reader.deserialize(raw, conn.msgtype)))
    assert set(got) == set(written)
    for topic, msgs in written.items():
        assert types[topic] == TOPICS.get(topic, TOPICS.get(topic.removeprefix("/walk01/"))).type
        assert len(got[topic]) == len(msgs) == 3
        for ours, (_, theirs) in zip(msgs, got[topic]):
            _assert_same(ours, theirs)


def test_read_bag_round_trip_and_topics(contract_bag) -> None:
    path, written = contract_bag
    msgs = list(read_bag(path))
    assert [m.stamp_ns for m in msgs] == sorted(m.stamp_ns for m in msgs)
    by_topic: dict[str, list] = {}
    for m in msgs:
        by_topic.setdefault(m.topic, []).append(m.msg)
    assert by_topic == written                       # rclpy messages compare field by field
    topics = bag_topics(path)
    assert {t: c for t, (_, c) in topics.items()} == {t: len(v) for t, v in written.items()}
    only = list(read_bag([path], topics=["/walk01/imu/data"]))
    assert [m.msg for m in only] == written["/walk01/imu/data"]


def test_rosbag2_layout_schema_qos_and_metadata(contract_bag) -> None:
    path, written = contract_bag
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        metadata = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
    assert header.profile == "ros2"
    assert all(s.encoding == "ros2msg" for s in summary.schemas.values())
    assert all(c.message_encoding == "cdr" for c in summary.channels.values())
    assert all(c.metadata["topic_type_hash"].startswith("RIHS01_") for c in summary.channels.values())
    assert all(ci.compression == "zstd" for ci in summary.chunk_indexes)
    # QoS as rosbag2 (Jazzy) stores it, also understood by rosbags
    qos = {c.topic: parse_qos_yaml(c.metadata["offered_qos_profiles"]) for c in summary.channels.values()}
    assert qos["/walk01/ground_truth"][0]["durability"] == "transient_local"
    assert qos["/walk01/imu/data_raw"][0]["reliability"] == "best_effort"
    with AnyReader([path]) as r:
        ext = {c.topic: c.ext.offered_qos_profiles[0] for c in r.connections}
    assert ext["/walk01/map/graph"].durability == QosDurability.TRANSIENT_LOCAL
    assert ext["/walk01/pf/particles"].reliability == QosReliability.BEST_EFFORT
    # the metadata record ros2 bag info / play read from an MCAP file
    assert len(metadata) == 1
    meta = yaml.safe_load(metadata[0].metadata["serialized_metadata"])
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    assert meta["message_count"] == sum(len(v) for v in written.values())
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts == {t: len(v) for t, v in written.items()}
    assert meta["starting_time"]["nanoseconds_since_epoch"] == T0


def test_message_definition_follows_rosbag2_concatenation() -> None:
    text = message_definition("sensor_msgs/msg/Imu")
    sections = text.split("\n" + DELIMITER + "\n")
    names = [s.splitlines()[0] for s in sections[1:]]
    # depth first, dependencies of each type in sorted order, each type once
    assert names == ["MSG: geometry_msgs/Quaternion", "MSG: geometry_msgs/Vector3", "MSG: std_msgs/Header",
                     "MSG: builtin_interfaces/Time"]
    assert sections[0].startswith("# This is a message to hold data from an IMU")
    assert msg_dependencies("Header header\nfloat64[9] c\n# Foo bar\nPose[] poses\n", "geometry_msgs") == \
        ["geometry_msgs/Header", "geometry_msgs/Pose"]
    with pytest.raises(BagError, match="no .msg definition"):
        message_definition("sensor_msgs/msg/NoSuchType")


def test_qos_yaml_round_trip() -> None:
    profiles = [qos_dict(reliability="best_effort", depth=7), qos_dict(durability="transient_local", depth=1)]
    assert parse_qos_yaml(qos_yaml(profiles)) == profiles
    assert parse_qos_yaml("- reliability: 2\n  durability: 1\n")[0] == {"reliability": "best_effort",
                                                                         "durability": "transient_local"}
    assert qos_yaml([]) == "" and parse_qos_yaml("") == []


def test_read_bag_merges_files_in_stamp_order(tmp_path: Path) -> None:
    from sensor_msgs.msg import Imu
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    with BagWriter(a) as wa, BagWriter(b) as wb:
        for i in range(50):
            m = Imu()
            m.header.frame_id = str(i)
            (wa if i % 3 else wb).write("/u1/imu/data_raw" if i % 3 else "/u2/imu/data_raw", m, T0 + i * 1000)
    msgs = list(read_bag([a, b]))
    assert [int(m.msg.header.frame_id) for m in msgs] == list(range(50))
    # a directory (as `ros2 bag record` writes) stands for its .mcap files
    assert [m.msg for m in read_bag(tmp_path)] == [m.msg for m in msgs]
    assert bag_topics([a, b]) == {"/u1/imu/data_raw": ("sensor_msgs/msg/Imu", 33),
                                  "/u2/imu/data_raw": ("sensor_msgs/msg/Imu", 17)}


def test_recover_truncated_file_keeps_every_complete_chunk(tmp_path: Path) -> None:
    from sensor_msgs.msg import Imu
    src = tmp_path / "full.mcap"
    with BagWriter(src, chunk_size=1500, compression="lz4") as w:
        for i in range(120):
            m = Imu()
            m.header.frame_id = str(i)
            w.write("/u/imu/data_raw", m, T0 + i * 10_000_000)
    data = src.read_bytes()
    previous = -1
    for cut in np.linspace(200, len(data), 9).astype(int):
        damaged = tmp_path / f"cut{cut}.mcap"
        damaged.write_bytes(data[:cut])
        complete_msgs = scan_records(damaged).messages
        fixed = tmp_path / f"fixed{cut}.mcap"
        res = recover(damaged, fixed)
        assert res.messages == complete_msgs
        assert res.truncated == (cut < len(data))
        with AnyReader([fixed]) as r:
            ids = [int(r.deserialize(raw, c.msgtype).header.frame_id) for c, _, raw in r.messages()]
        assert ids == list(range(len(ids)))               # a prefix of what was written, in order
        assert len(ids) == res.messages >= previous       # more file, never fewer messages
        previous = len(ids)
    assert previous == 120


def test_bag_errors(tmp_path: Path) -> None:
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import Imu
    with pytest.raises(BagError, match="compression"):
        BagWriter(tmp_path / "x.mcap", compression="bz2")
    with pytest.raises(BagError, match="chunk_size"):
        BagWriter(tmp_path / "x.mcap", chunk_size=0)
    with BagWriter(tmp_path / "x.mcap") as w:
        w.write("/a", Imu(), T0)
        with pytest.raises(BagError, match="already in the bag|bag holds"):
            w.write("/a", PoseArray(), T0)
        with pytest.raises(BagError, match="negative"):
            w.write("/a", Imu(), -1)
    with pytest.raises(BagError, match="does not exist"):
        list(read_bag(tmp_path / "missing.mcap"))
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(BagError, match="not an MCAP"):
        recover(tmp_path / "junk.mcap", tmp_path / "out.mcap")
    data = (tmp_path / "x.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 3])
    with pytest.raises(BagError, match="recover"):
        bag_topics(tmp_path / "cut.mcap")


def test_bag_cli_info_and_recover(tmp_path: Path, capsys) -> None:
    from sensor_msgs.msg import Imu

    from indoor_loc.cli import main
    src = tmp_path / "in.mcap"
    with BagWriter(src, chunk_size=800) as w:
        for i in range(30):
            w.write("/u/imu/data", Imu(), T0 + i * 10**8)
    data = src.read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 4])
    assert main(["bag", "info", str(src)]) == 0
    out = capsys.readouterr().out
    assert "/u/imu/data" in out and "30 msgs" in out and "2.900 s" in out
    assert main(["bag", "info", str(tmp_path / "cut.mcap")]) == 0
    assert "recover" in capsys.readouterr().out
    assert main(["bag", "recover", str(tmp_path / "cut.mcap"), str(tmp_path / "ok.mcap")]) == 0
    n = bag_topics(tmp_path / "ok.mcap")["/u/imu/data"][1]
    assert 0 < n < 30 and f"kept {n} messages" in capsys.readouterr().out


def test_foxglove_decoder_reads_the_same_values(contract_bag) -> None:
    """mcap-ros2-support parses the concatenated ros2msg schemas independently of rosbags."""
    from mcap_ros2.decoder import DecoderFactory
    path, written = contract_bag
    got: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages(log_time_order=True):
            got.setdefault(channel.topic, []).append(decoded)
    assert {t: len(v) for t, v in got.items()} == {t: len(v) for t, v in written.items()}
    for topic, msgs in written.items():
        for ours, theirs in zip(msgs, got[topic]):
            _assert_same(ours, theirs)


def test_recover_skips_a_damaged_chunk_and_keeps_the_rest(tmp_path: Path) -> None:
    from sensor_msgs.msg import Imu
    src = tmp_path / "full.mcap"
    with BagWriter(src, chunk_size=1500) as w:
        for i in range(60):
            m = Imu()
            m.header.frame_id = str(i)
            w.write("/u/imu/data_raw", m, T0 + i * 10_000_000)
    with open(src, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    bad = chunks[2]
    data = bytearray(src.read_bytes())
    data[bad.chunk_start_offset + bad.chunk_length - 3] ^= 0xFF      # inside the compressed records
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    res = recover(damaged, tmp_path / "fixed.mcap")
    assert res.bad_chunks == 1 and not res.truncated
    ids = [int(m.msg.header.frame_id) for m in read_bag(tmp_path / "fixed.mcap")]
    lost = [int(m.msg.header.frame_id) for m in read_bag(src)
            if bad.message_start_time <= m.stamp_ns <= bad.message_end_time]
    assert lost and ids == [i for i in range(60) if i not in lost]
    with pytest.raises(BagError, match="cannot be read"):      # an ordinary read stops there
        list(read_bag(damaged))


def test_read_runs_gives_read_raws_order_and_bytes(tmp_path: Path) -> None:
    """Runs (:func:`read_runs`) hold the messages of :func:`read_raw` in the same order, ties across
    files in file order, from chunked files (one with a chunk written out of order, one whose chunks
    overlap in time so it is read through the mcap reader), and ``records_of`` joins them."""
    from indoor_loc.bag.reader import read_raw, read_runs, records_of
    from msg_adapters.imu import imu_to_msg
    from rclpy.serialization import serialize_message

    s = 1_000_000_000
    rng = np.random.default_rng(5)
    paths = []
    for f in range(3):
        p = tmp_path / f"u{f}.mcap"
        with BagWriter(p, chunk_size=4000) as w:
            stamps = sorted(int(v) for v in rng.integers(0, 400, 300))     # many equal stamps across files
            if f == 1:
                stamps[100:110] = stamps[100:110][::-1]                        # out of order inside a chunk
            if f == 2:
                stamps[200:] = [t - 300 for t in stamps[200:]]                 # chunks overlap in time
            stamps = [t + 1000 for t in stamps]
            for k, t in enumerate(stamps):
                frame = f"u{f}" if k % 7 else f"u{f}/other"
                msg = imu_to_msg(t * s // 100 + 1, frame, [0.0, 0.1 * k, 9.8])
                w.write(f"/u{f}/imu/data" if k % 7 else f"/u{f}/imu/other", msg, t * s // 100 + 1)
        paths.append(p)
    want = [(m.topic, m.stamp_ns, m.data) for m in read_raw(paths)]
    # the reference: each file in log-time order by the mcap reader, merged by (time, file, position)
    ref = []
    for i, p in enumerate(paths):
        with open(p, "rb") as fh:
            ref += [(mm.log_time, i, k, ch.topic, bytes(mm.data))
                    for k, (_, ch, mm) in enumerate(make_reader(fh).iter_messages(log_time_order=True))]
    assert [(t, ts, d) for ts, _, _, t, d in sorted(ref)] == want and len(want) == 900
    runs = list(read_runs(paths))
    got = [(r.topic, t, r.data(k)) for r in runs for k, t in enumerate(r.stamps)]
    assert got == want
    assert all(len({r.topic}) == 1 and len(r) for r in runs) and len(runs) < len(want)
    same = [r for r in runs if r.topic == "/u0/imu/data"]
    mat = records_of(same)
    assert mat is not None and mat.tobytes() == b"".join(r.data(k) for r in same for k in range(len(r)))
    longest = max(same, key=len)
    assert len(longest) > 2 and bytes(longest.part(1, 2).records()[0]) == longest.data(1)
    other = [r for r in runs if r.topic == "/u0/imu/other"]
    assert records_of([same[0], other[0]]) is None                      # two sizes: no array
    assert len(serialize_message(imu_to_msg(s, "u0/other", [0.0, 0.0, 9.8]))) == len(other[0].data(0))
