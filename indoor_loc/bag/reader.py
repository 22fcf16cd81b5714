"""Read MCAP bags (one or several, merged in log-time order): messages, raw CDR, topics and counts."""
from __future__ import annotations

import heapq
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

from mcap.exceptions import McapError
from mcap.reader import make_reader

from indoor_loc.bag.recover import ZstdError, scan_records
from indoor_loc.contract import msg_class
from indoor_loc.errors import BagError


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


_RECORD = struct.Struct("<BQ")          # opcode, record length
_MESSAGE = struct.Struct("<HIQQ")        # channel id, sequence, log time, publish time
_OP_MESSAGE = 0x05


def _chunks_in_order(summary: Any, wanted: set[str] | None) -> list | None:
    """The chunk indexes to read, in file order, when reading them one after another and sorting
    each one's messages by log time gives the log-time order (chunks that do not overlap in time);
    None otherwise (or without a chunk index)."""
    if summary is None or not summary.chunk_indexes:
        return None
    ids = None if wanted is None else {cid for cid, c in summary.channels.items() if c.topic in wanted}
    chunks = [c for c in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
              if ids is None or not c.message_index_offsets or ids & c.message_index_offsets.keys()]
    if any(c.compression not in ("", "zstd", "lz4") for c in chunks):
        return None
    for a, b in zip(chunks, chunks[1:]):
        if a.message_end_time > b.message_start_time:
            return None
    return chunks


def _iter_chunks(f: Any, summary: Any, chunks: list, wanted: set[str] | None) -> Iterator[tuple[int, int, RawMessage]]:
    """Messages chunk by chunk, each chunk's sorted by log time (ties: position), parsed straight
    from the decompressed chunk: the order of the ``mcap`` reader's ``log_time_order`` without its
    per-message heap."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk

    names: dict[int, tuple[str, str] | None] = {}
    for cid, c in summary.channels.items():
        if wanted is None or c.topic in wanted:
            schema = summary.schemas.get(c.schema_id) if c.schema_id else None
            names[cid] = (c.topic, schema.name if schema is not None else "")
        else:
            names[cid] = None
    for index in chunks:
        f.seek(index.chunk_start_offset + 1 + 8)
        chunk = Chunk.read(ReadDataStream(f))
        if chunk.compression == "zstd":
            import zstandard
            buf = zstandard.decompress(chunk.data, chunk.uncompressed_size)
        elif chunk.compression == "lz4":
            import lz4.frame
            buf = lz4.frame.decompress(chunk.data)
        else:
            buf = chunk.data
        out: list[tuple[int, int, RawMessage]] = []
        pos, end, last, ordered = 0, len(buf), -1, True
        while pos < end:
            op, length = _RECORD.unpack_from(buf, pos)
            pos += 9
            if op == _OP_MESSAGE:
                cid, seq, log_time, pub_time = _MESSAGE.unpack_from(buf, pos)
                name = names.get(cid, ("", ""))
                if name is not None:
                    if cid not in names:
                        raise ValueError(f"message on unknown channel {cid}")
                    out.append((log_time, seq, RawMessage(name[0], name[1], log_time, buf[pos + 22:pos + length],
                                                          pub_time)))
                    ordered = ordered and log_time >= last
                    last = log_time
            pos += length
        if pos != end:
            raise ValueError("chunk ends inside a record")
        if not ordered:
            out.sort(key=lambda x: x[0])        # stable: ties keep their position
        yield from out


def _iter_file(path: Path, topics: set[str] | None) -> Iterator[tuple[int, int, RawMessage]]:
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            try:
                summary = reader.get_summary()
            except (McapError, struct.error, ValueError, EOFError):
                summary = None
            chunks = _chunks_in_order(summary, topics)
            if chunks is not None:
                yield from _iter_chunks(f, summary, chunks, topics)
                return
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
    files = bag_files(paths)
    if len(files) == 1:
        for _, _, m in _iter_file(files[0], wanted):
            yield m
        return
    # (log time, file, position in the file): ties keep the file order, then each file's own order
    # (the file's reader yields log-time order), with no key function for the heap to call
    streams = [((t, i, k, m) for k, (t, _, m) in enumerate(_iter_file(p, wanted))) for i, p in enumerate(files)]
    for _, _, _, m in heapq.merge(*streams):
        yield m


class MessageDecoder:
    """Deserialise stored messages to rclpy message classes (classes looked up once per type)."""

    def __init__(self) -> None:
        from rclpy.serialization import deserialize_message
        self._deserialize = deserialize_message
        self._classes: dict[str, type] = {}

    def __call__(self, m: RawMessage) -> BagMessage:
        cls = self._classes.get(m.type)
        if cls is None:
            try:
                cls = self._classes[m.type] = msg_class(m.type)
            except (ImportError, AttributeError, ValueError) as err:
                raise BagError(f"topic {m.topic}: message type {m.type!r} is not importable") from err
        return BagMessage(m.topic, m.type, m.stamp_ns, self._deserialize(m.data, cls))


def read_bag(paths: str | os.PathLike | Iterable[str | os.PathLike],
             topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Messages of one or more bags in log-time order, deserialised to rclpy message classes.

    Args:
        paths: one bag or several (merged, e.g. one per user).
        topics: full topic names to keep (default all).
    """
    decode = MessageDecoder()
    for m in read_raw(paths, topics):
        yield decode(m)


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
