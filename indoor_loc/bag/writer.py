"""Write MCAP bags as rosbag2 writes them (:class:`BagWriter`).

A file written here is what ``ros2 bag record -s mcap`` (Jazzy) would write for the same messages:
profile ``ros2``; one schema per type (encoding ``ros2msg``, the full concatenated ``.msg`` text, see
:mod:`indoor_loc.bag.schemas`); one channel per topic (message encoding ``cdr``, metadata
``offered_qos_profiles`` and ``topic_type_hash``); messages with ``log_time`` = the stamp given to
:meth:`BagWriter.write` in ns; a ``rosbag2`` metadata record whose ``serialized_metadata`` is the
bag's ``metadata.yaml`` content (version 9); chunked (zstd or lz4) with message indexes and a summary.

Every record reaches the file when its chunk closes (the stream is flushed after each write), so a
writer killed with SIGKILL loses at most the chunk in progress; :func:`indoor_loc.bag.recover.recover`
rewrites such a file into a valid one.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from mcap.writer import CompressionType, Writer

from indoor_loc.bag.schemas import message_definition, qos_dict, qos_yaml, type_hash
from indoor_loc.contract import TOPICS, Qos, split_ns, type_name_of
from indoor_loc.errors import BagError

PROFILE = "ros2"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
METADATA_NAME = "rosbag2"
BAG_VERSION = 9                      # rosbag2 metadata version of Jazzy
DEFAULT_CHUNK_SIZE = 1 << 20         # bytes of uncompressed records per chunk
LIBRARY = "indoor_loc"

# Offered QoS written for topics whose publisher QoS is not known (offline outputs): the QoS the
# live node would offer for that contract topic.
_CONTRACT_QOS = {
    Qos.SENSOR: dict(reliability="best_effort", depth=200),
    Qos.RELIABLE: dict(reliability="reliable", depth=50),
    Qos.LATCHED: dict(reliability="reliable", durability="transient_local", depth=1),
    Qos.BEST_EFFORT: dict(reliability="best_effort", depth=5),
}


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

    def write(self, topic: str, msg: Any, stamp_ns: int) -> bytes:
        """Serialise an rclpy message and append it with log time ``stamp_ns`` (int ns); returns
        the CDR bytes written (padding zeroed: the same message gives the same bytes, see
        :mod:`indoor_loc.bag.cdr_padding`)."""
        from rclpy.serialization import serialize_message

        from indoor_loc.bag.cdr_padding import zero_padding
        type_name = type_name_of(msg)
        if topic not in self._topics:
            self.add_topic(topic, type_name)
        elif self._topics[topic].type != type_name:
            raise BagError(f"topic {topic}: bag holds {self._topics[topic].type}, got a {type_name}")
        data = zero_padding(serialize_message(msg), type(msg))
        self.write_raw(topic, data, stamp_ns)
        return data

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
