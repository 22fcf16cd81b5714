"""MCAP bags as rosbag2 writes them: write, read (merged over files), list topics, recover.

A file written here is what ``ros2 bag record -s mcap`` (Jazzy) would write for the same messages:
profile ``ros2``; one schema per type (encoding ``ros2msg``, the full concatenated ``.msg`` text, see
:mod:`indoor_loc.bag.schemas`); one channel per topic (message encoding ``cdr``, metadata
``offered_qos_profiles`` and ``topic_type_hash``); messages with ``log_time`` = the stamp given to
:meth:`BagWriter.write` in ns; a ``rosbag2`` metadata record whose ``serialized_metadata`` is the
bag's ``metadata.yaml`` content (version 9); chunked (zstd or lz4) with message indexes and a summary.

Every record reaches the file when its chunk closes (the stream is flushed after each write), so a
writer killed with SIGKILL loses at most the chunk in progress; :func:`recover` rewrites such a
file into a valid one.
"""
from __future__ import annotations

import heapq
import io
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple, Sequence

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

try:
    from zstandard import ZstdError
except ImportError:                      # without zstandard the mcap library reads no zstd chunk anyway
    ZstdError = McapError                # type: ignore[misc,assignment]

from indoor_loc.bag.schemas import message_definition, qos_dict, qos_yaml, type_hash
from indoor_loc.contract import TOPICS, Qos, msg_class, split_ns, type_name_of
from indoor_loc.errors import BagError

PROFILE = "ros2"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
METADATA_NAME = "rosbag2"
BAG_VERSION = 9                      # rosbag2 metadata version of Jazzy
DEFAULT_CHUNK_SIZE = 1 << 20         # bytes of uncompressed records per chunk
LIBRARY = "indoor_loc"
_MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_DATA_END = 1, 2, 3, 4, 5, 6, 15

# Offered QoS written for topics whose publisher QoS is not known (offline outputs): the QoS the
# live node would offer for that contract topic.
_CONTRACT_QOS = {
    Qos.SENSOR: dict(reliability="best_effort", depth=200),
    Qos.RELIABLE: dict(reliability="reliable", depth=50),
    Qos.LATCHED: dict(reliability="reliable", durability="transient_local", depth=1),
    Qos.BEST_EFFORT: dict(reliability="best_effort", depth=5),
}


class BagMessage(NamedTuple):
    """One deserialised message: full topic name, ``pkg/msg/Name``, log time in ns, rclpy message."""
    topic: str
    type: str
    stamp_ns: int
    msg: Any


class RawMessage(NamedTuple):
    """One message as stored: CDR bytes, log and publish time in ns."""
    topic: str
    type: str
    stamp_ns: int
    data: bytes
    publish_ns: int


@dataclass(frozen=True)
class TopicInfo:
    """A channel of a bag: type, message count and the offered QoS text as recorded."""
    topic: str
    type: str
    count: int
    qos_yaml: str = ""
    type_hash: str = ""


def contract_qos_profiles(topic: str) -> list[dict[str, Any]]:
    """The QoS the package's nodes offer on ``topic`` (full name), by the contract's relative name."""
    _, rel = split_ns(topic, set(TOPICS))
    spec = TOPICS.get(rel) or TOPICS.get(topic)
    kw = _CONTRACT_QOS.get(spec.qos, {}) if spec is not None else {}
    return [qos_dict(**kw)]


class _FlushingStream:
    """File stream that flushes after each write: the MCAP writer writes whole records (a chunk
    with its indexes) at once, so what it has written survives the process being killed."""

    def __init__(self, path: Path) -> None:
        self._f = open(path, "wb")

    def write(self, data: bytes) -> int:
        n = self._f.write(data)
        self._f.flush()
        return n

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        self._f.flush()

    def fsync(self) -> None:
        self._f.flush()
        os.fsync(self._f.fileno())

    def close(self) -> None:
        self._f.close()


@dataclass
class _Topic:
    channel_id: int
    type: str
    qos_yaml: str
    type_hash: str
    count: int = 0
    sequence: int = 0


class BagWriter:
    """Write an MCAP bag as rosbag2 does (``ros2`` profile, ``ros2msg`` schemas, ``cdr`` data).

    ``with BagWriter("out.mcap") as w: w.write("/walk01/imu/data", imu_msg, stamp_ns)``

    Args:
        path: output file (``.mcap``); its directory is created.
        chunk_size: uncompressed bytes per chunk; a killed writer loses at most one chunk.
        compression: ``"zstd"``, ``"lz4"`` or ``"none"``.
        ros_distro: stored in the rosbag2 metadata (default ``$ROS_DISTRO`` or ``"jazzy"``).
    """

    def __init__(self, path: str | os.PathLike, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = "zstd", ros_distro: str | None = None) -> None:
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE,
                "": CompressionType.NONE}.get(str(compression).lower())
        if comp is None:
            raise BagError(f"BagWriter.compression: expected 'zstd', 'lz4' or 'none', got {compression!r}")
        if int(chunk_size) <= 0:
            raise BagError(f"BagWriter.chunk_size: expected > 0 bytes, got {chunk_size!r}")
        self.path = Path(path)
        self._chunk_size = int(chunk_size)
        self._compression = comp
        self._ros_distro = ros_distro or os.environ.get("ROS_DISTRO", "jazzy")
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._stream: _FlushingStream | None = None
        self._writer: Writer | None = None
        self._start_ns: int | None = None
        self._end_ns: int | None = None
        self._custom_data: dict[str, str] = {}

    # -- life cycle --------------------------------------------------------------------------------
    def open(self) -> BagWriter:
        if self._writer is not None:
            return self
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._stream = _FlushingStream(self.path)
        except OSError as err:
            raise BagError(f"cannot create bag {self.path}: {err}") from err
        self._writer = Writer(self._stream, chunk_size=self._chunk_size, compression=self._compression)  # type: ignore[arg-type]
        from importlib.metadata import version
        self._writer.start(profile=PROFILE, library=f"{LIBRARY}; mcap {version('mcap')}")
        return self

    def close(self) -> None:
        """Write the rosbag2 metadata record and the summary, and close the file."""
        if self._writer is None:
            return
        writer, stream = self._writer, self._stream
        self._writer = None
        try:
            writer.add_metadata(METADATA_NAME, {"serialized_metadata": self.metadata_yaml()})
            writer.finish()
        finally:
            assert stream is not None
            stream.close()
            self._stream = None

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._writer is not None

    # -- topics and messages -----------------------------------------------------------------------
    def add_topic(self, topic: str, type_name: str, *, qos_profiles: Sequence[dict[str, Any]] | str | None = None,
                  topic_type_hash: str | None = None, definition: tuple[str, bytes] | None = None) -> None:
        """Declare ``topic`` of ``type_name`` ("pkg/msg/Name"). ``qos_profiles`` are the offered
        QoS (dicts from :func:`~indoor_loc.bag.schemas.qos_dict`, or the YAML text); default: the
        contract's QoS for that topic. ``definition`` = (schema encoding, schema data) to store
        instead of the local ``.msg`` text (when copying a bag). A topic declared again with the
        same type is a no-op."""
        if self._writer is None:
            self.open()
        assert self._writer is not None
        known = self._topics.get(topic)
        if known is not None:
            if known.type != type_name:
                raise BagError(f"topic {topic}: already in the bag as {known.type}, cannot write {type_name}")
            return
        if type_name not in self._schemas:
            encoding, data = definition or (SCHEMA_ENCODING, message_definition(type_name).encode())
            self._schemas[type_name] = self._writer.register_schema(type_name, encoding, data)
        if qos_profiles is None:
            qos_profiles = contract_qos_profiles(topic)
        qtext = qos_profiles if isinstance(qos_profiles, str) else qos_yaml(qos_profiles)
        thash = type_hash(type_name) if topic_type_hash is None else topic_type_hash
        cid = self._writer.register_channel(topic, MESSAGE_ENCODING, self._schemas[type_name],
                                            {"offered_qos_profiles": qtext, "topic_type_hash": thash})
        self._topics[topic] = _Topic(cid, type_name, qtext, thash)

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Serialise an rclpy message and append it with log time ``stamp_ns`` (int ns)."""
        from rclpy.serialization import serialize_message
        type_name = type_name_of(msg)
        if topic not in self._topics:
            self.add_topic(topic, type_name)
        elif self._topics[topic].type != type_name:
            raise BagError(f"topic {topic}: bag holds {self._topics[topic].type}, got a {type_name}")
        self.write_raw(topic, serialize_message(msg), stamp_ns)

    def write_raw(self, topic: str, data: bytes, stamp_ns: int, *, publish_ns: int | None = None) -> None:
        """Append CDR bytes on a topic declared with :meth:`add_topic` (or written before)."""
        if self._writer is None:
            raise BagError(f"bag {self.path} is closed")
        t = self._topics.get(topic)
        if t is None:
            raise BagError(f"topic {topic} was not declared with add_topic()")
        stamp_ns = int(stamp_ns)
        if stamp_ns < 0:
            raise BagError(f"topic {topic}: negative stamp {stamp_ns} ns")
        t.sequence += 1
        t.count += 1
        self._writer.add_message(t.channel_id, stamp_ns, bytes(data),
                                 stamp_ns if publish_ns is None else int(publish_ns), sequence=t.sequence)
        self._start_ns = stamp_ns if self._start_ns is None else min(self._start_ns, stamp_ns)
        self._end_ns = stamp_ns if self._end_ns is None else max(self._end_ns, stamp_ns)

    def flush(self) -> None:
        """Close the chunk in progress and push it to the file (call now and then while recording)."""
        if self._writer is not None:
            self._writer.flush()

    def set_custom_data(self, key: str, value: str) -> None:
        """A ``custom_data`` entry of the rosbag2 metadata."""
        self._custom_data[str(key)] = str(value)

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self._topics.values())

    def topic_counts(self) -> dict[str, int]:
        return {name: t.count for name, t in self._topics.items()}

    def metadata_yaml(self) -> str:
        """rosbag2 ``BagMetadata`` (version 9) as YAML, as rosbag2_storage_mcap stores it."""
        import yaml

        from indoor_loc.bag.schemas import parse_qos_yaml
        start = self._start_ns or 0
        duration = (self._end_ns or 0) - start
        count = self.message_count
        meta = {
            "version": BAG_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {"topic_metadata": {"name": name, "type": t.type, "serialization_format": MESSAGE_ENCODING,
                                    "offered_qos_profiles": parse_qos_yaml(t.qos_yaml),
                                    "type_description_hash": t.type_hash},
                 "message_count": t.count}
                for name, t in self._topics.items()],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.path.name],
            "files": [{"path": self.path.name, "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration}, "message_count": count}],
            "custom_data": dict(self._custom_data),
            "ros_distro": self._ros_distro,
        }
        return yaml.safe_dump(meta, sort_keys=False, default_flow_style=False)


# -- reading ---------------------------------------------------------------------------------------
def bag_files(paths: str | os.PathLike | Iterable[str | os.PathLike]) -> list[Path]:
    """Bag files; a directory (``ros2 bag record`` writes one) stands for the ``.mcap`` files in it."""
    items = [Path(paths)] if isinstance(paths, (str, os.PathLike)) else [Path(p) for p in paths]
    out: list[Path] = []
    for p in items:
        if p.is_dir():
            files = sorted(p.glob("*.mcap"))
            if not files:
                raise BagError(f"bag directory {p} holds no .mcap file")
            out += files
        else:
            out.append(p)
    return out


def _iter_file(path: Path, topics: set[str] | None) -> Iterator[tuple[int, int, RawMessage]]:
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for schema, channel, message in reader.iter_messages(
                    topics=sorted(topics) if topics is not None else None, log_time_order=True):
                yield (message.log_time, message.sequence,
                       RawMessage(channel.topic, schema.name if schema else "", message.log_time,
                                  message.data, message.publish_time))
    except FileNotFoundError as err:
        raise BagError(f"bag {path} does not exist") from err
    except (McapError, ZstdError, struct.error, ValueError, EOFError) as err:
        raise BagError(f"bag {path} cannot be read ({type(err).__name__}: {err}); if its writer was "
                       f"killed, run `indoor-loc bag recover {path} FIXED.mcap`") from err


def read_raw(paths: str | os.PathLike | Iterable[str | os.PathLike],
             topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
    """Stored messages of one or more bags merged in log-time order (ties: file order, then sequence)."""
    wanted = set(topics) if topics is not None else None
    streams = [((t, i, s, m) for t, s, m in _iter_file(p, wanted)) for i, p in enumerate(bag_files(paths))]
    for _, _, _, m in heapq.merge(*streams, key=lambda x: (x[0], x[1], x[2])):
        yield m


def read_bag(paths: str | os.PathLike | Iterable[str | os.PathLike],
             topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Messages of one or more bags in log-time order, deserialised to rclpy message classes.

    Args:
        paths: one bag or several (merged, e.g. one per user).
        topics: full topic names to keep (default all).
    """
    from rclpy.serialization import deserialize_message
    classes: dict[str, type] = {}
    for m in read_raw(paths, topics):
        cls = classes.get(m.type)
        if cls is None:
            try:
                cls = classes[m.type] = msg_class(m.type)
            except (ImportError, AttributeError, ValueError) as err:
                raise BagError(f"topic {m.topic}: message type {m.type!r} is not importable") from err
        yield BagMessage(m.topic, m.type, m.stamp_ns, deserialize_message(m.data, cls))


def bag_info(paths: str | os.PathLike | Iterable[str | os.PathLike]) -> dict[str, TopicInfo]:
    """Topics of the bags with type, message count and recorded QoS (summary, or a scan without one)."""
    out: dict[str, TopicInfo] = {}
    for path in bag_files(paths):
        for name, info in _file_topics(path).items():
            prev = out.get(name)
            if prev is not None and prev.type != info.type:
                raise BagError(f"topic {name} is {prev.type} in one bag and {info.type} in {path}")
            out[name] = info if prev is None else TopicInfo(name, info.type, prev.count + info.count,
                                                            prev.qos_yaml or info.qos_yaml,
                                                            prev.type_hash or info.type_hash)
    return out


def bag_topics(paths: str | os.PathLike | Iterable[str | os.PathLike]) -> dict[str, tuple[str, int]]:
    """``{topic: (type, message count)}`` over one or more bags."""
    return {name: (i.type, i.count) for name, i in bag_info(paths).items()}


def _file_topics(path: Path) -> dict[str, TopicInfo]:
    try:
        with open(path, "rb") as f:
            summary = None
            try:
                summary = make_reader(f).get_summary()
            except (McapError, struct.error, ValueError, OSError):
                summary = None
            if summary is not None and summary.statistics is not None:
                counts = summary.statistics.channel_message_counts
                return {c.topic: TopicInfo(c.topic, summary.schemas[c.schema_id].name if c.schema_id else "",
                                           counts.get(cid, 0), c.metadata.get("offered_qos_profiles", ""),
                                           c.metadata.get("topic_type_hash", ""))
                        for cid, c in summary.channels.items()}
    except FileNotFoundError as err:
        raise BagError(f"bag {path} does not exist") from err
    scan = scan_records(path)
    if scan.truncated:
        raise BagError(f"bag {path} has no summary and ends in a partial record (writer killed?); run "
                       f"`indoor-loc bag recover {path} FIXED.mcap`")
    return {c.topic: TopicInfo(c.topic, scan.schemas[c.schema_id].name if c.schema_id in scan.schemas else "",
                               scan.counts.get(cid, 0), c.metadata.get("offered_qos_profiles", ""),
                               c.metadata.get("topic_type_hash", ""))
            for cid, c in scan.channels.items()}


# -- recovery --------------------------------------------------------------------------------------
@dataclass
class ScanResult:
    """What a linear scan of a (possibly truncated) MCAP file found."""
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)
    messages: int = 0
    chunks: int = 0
    bad_chunks: int = 0
    complete: bool = False           # reached the footer
    truncated: bool = False          # ended inside a record
    valid_bytes: int = 0             # offset after the last whole record read


def _iter_records(path: Path, result: ScanResult) -> Iterator[Schema | Channel | Message]:
    """Schemas, channels and messages of ``path`` in file order, stopping cleanly at a truncated
    record or a chunk that fails its CRC / decompression (which is counted and skipped)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        if f.read(len(_MAGIC)) != _MAGIC:
            raise BagError(f"{path} is not an MCAP file (bad magic)")
        pos = len(_MAGIC)
        result.valid_bytes = pos
        while True:
            head = f.read(9)
            if len(head) < 9:
                result.truncated = pos < size
                return
            opcode, length = head[0], struct.unpack_from("<Q", head, 1)[0]
            if pos + 9 + length > size:
                result.truncated = True
                return
            body = f.read(length)
            pos += 9 + length
            if opcode == _OP_FOOTER:
                result.valid_bytes = pos
                result.complete = True
                return
            records: list[Any] = []
            try:
                if opcode == _OP_CHUNK:
                    chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
                    records = breakup_chunk(chunk, validate_crc=True)
                    result.chunks += 1
                elif opcode == _OP_SCHEMA:
                    records = [Schema.read(ReadDataStream(io.BytesIO(body)))]
                elif opcode == _OP_CHANNEL:
                    records = [Channel.read(ReadDataStream(io.BytesIO(body)))]
                elif opcode == _OP_MESSAGE:
                    records = [Message.read(ReadDataStream(io.BytesIO(body)), length)]
            except (McapError, ZstdError, ValueError, struct.error, EOFError, RuntimeError):
                # a damaged record (CRC mismatch, bad compression): skip it, keep what follows
                if opcode == _OP_CHUNK:
                    result.bad_chunks += 1
                continue
            result.valid_bytes = pos
            for r in records:
                if isinstance(r, Schema):
                    result.schemas[r.id] = r
                elif isinstance(r, Channel):
                    result.channels[r.id] = r
                elif isinstance(r, Message):
                    result.messages += 1
                    result.counts[r.channel_id] = result.counts.get(r.channel_id, 0) + 1
                else:
                    continue
                yield r


def scan_records(path: str | os.PathLike) -> ScanResult:
    """Scan a bag linearly (no summary needed) and count what is readable."""
    result = ScanResult()
    for _ in _iter_records(Path(path), result):
        pass
    return result


@dataclass(frozen=True)
class RecoverResult:
    """Counts of a :func:`recover` run."""
    messages: int
    topics: int
    chunks: int
    bad_chunks: int
    truncated: bool
    lost_bytes: int
    messages_without_channel: int


def recover(src: str | os.PathLike, dst: str | os.PathLike, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
            compression: str = "zstd") -> RecoverResult:
    """Rewrite a bag whose writer died (no summary, maybe a partial last chunk) into a valid bag
    holding every message of every complete chunk, with schemas, channels and QoS kept.

    Returns counts; raises BagError if ``src`` is not an MCAP file at all."""
    src, dst = Path(src), Path(dst)
    if not src.is_file():
        raise BagError(f"bag {src} does not exist")
    if src.resolve() == dst.resolve():
        raise BagError("recover: output must be a different file from the input")
    scan = ScanResult()
    orphans = 0
    with BagWriter(dst, chunk_size=chunk_size, compression=compression) as out:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        for rec in _iter_records(src, scan):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            else:
                ch = channels.get(rec.channel_id)
                schema = schemas.get(ch.schema_id) if ch is not None else None
                if ch is None or schema is None:
                    orphans += 1
                    continue
                if ch.topic not in out.topic_counts():
                    # keep the stored definition: it may come from another ROS install than this one
                    out.add_topic(ch.topic, schema.name, qos_profiles=ch.metadata.get("offered_qos_profiles", ""),
                                  topic_type_hash=ch.metadata.get("topic_type_hash", ""),
                                  definition=(schema.encoding, schema.data))
                out.write_raw(ch.topic, rec.data, rec.log_time, publish_ns=rec.publish_time)
        out.set_custom_data("recovered_from", src.name)
        written = out.message_count
        n_topics = len(out.topic_counts())
    size = src.stat().st_size
    return RecoverResult(messages=written, topics=n_topics, chunks=scan.chunks, bad_chunks=scan.bad_chunks,
                         truncated=scan.truncated, lost_bytes=0 if scan.complete else size - scan.valid_bytes,
                         messages_without_channel=orphans)

