"""Read MCAP bags (one or several, merged in log-time order): messages, raw CDR, topics and counts."""
from __future__ import annotations

import bisect
import heapq
import itertools
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


class _Block(NamedTuple):
    """Stored messages of one file in log-time order, in parallel lists: the CDR bytes of message
    ``i`` are ``buf[starts[i]:ends[i]]`` (a decompressed chunk, or the joined records)."""
    buf: bytes
    times: list[int]
    cids: list[int]
    starts: list[int]
    ends: list[int]
    pubs: list[int]
    names: dict[int, tuple[str, str]]        # channel -> (topic, type)


#: messages per block when a file is read through the ``mcap`` reader
_READER_BLOCK = 4096


def _chunk_blocks(f: Any, summary: Any, chunks: list, wanted: set[str] | None) -> Iterator[_Block]:
    """One block per chunk, its messages sorted by log time (ties: position), parsed straight from
    the decompressed chunk: the order of the ``mcap`` reader's ``log_time_order`` without its
    per-message heap."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk

    names: dict[int, tuple[str, str]] = {}
    for cid, c in summary.channels.items():
        if wanted is None or c.topic in wanted:
            schema = summary.schemas.get(c.schema_id) if c.schema_id else None
            names[cid] = (c.topic, schema.name if schema is not None else "")
    known = set(summary.channels)
    record, message = _RECORD.unpack_from, _MESSAGE.unpack_from
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
        times: list[int] = []
        cids: list[int] = []
        starts: list[int] = []
        ends: list[int] = []
        pubs: list[int] = []
        pos, end, last, ordered = 0, len(buf), -1, True
        while pos < end:
            op, length = record(buf, pos)
            pos += 9
            if op == _OP_MESSAGE:
                cid, _seq, log_time, pub_time = message(buf, pos)
                if cid in names:
                    times.append(log_time)
                    cids.append(cid)
                    starts.append(pos + 22)
                    ends.append(pos + length)
                    pubs.append(pub_time)
                    ordered = ordered and log_time >= last
                    last = log_time
                elif cid not in known:
                    raise ValueError(f"message on unknown channel {cid}")
            pos += length
        if pos != end:
            raise ValueError("chunk ends inside a record")
        if not ordered:                         # stable: ties keep their position
            order = sorted(range(len(times)), key=times.__getitem__)
            times, cids, starts, ends, pubs = ([v[k] for k in order] for v in (times, cids, starts, ends, pubs))
        if times:
            yield _Block(buf, times, cids, starts, ends, pubs, names)


def _reader_blocks(reader: Any, wanted: set[str] | None) -> Iterator[_Block]:
    """Blocks of the ``mcap`` reader's messages in log-time order (files without a usable chunk index)."""
    ids: dict[tuple[str, str], int] = {}
    names: dict[int, tuple[str, str]] = {}
    parts: list[bytes] = []
    times: list[int] = []
    cids: list[int] = []
    pubs: list[int] = []

    def block() -> _Block:
        ends = list(itertools.accumulate(len(d) for d in parts))
        return _Block(b"".join(parts), times, cids, [e - len(d) for e, d in zip(ends, parts)], ends, pubs, dict(names))

    for schema, channel, message in reader.iter_messages(
            topics=sorted(wanted) if wanted is not None else None, log_time_order=True):
        name = (channel.topic, schema.name if schema else "")
        cid = ids.get(name)
        if cid is None:
            cid = ids[name] = len(ids)
            names[cid] = name
        parts.append(message.data)
        times.append(message.log_time)
        cids.append(cid)
        pubs.append(message.publish_time)
        if len(parts) >= _READER_BLOCK:
            yield block()
            parts, times, cids, pubs = [], [], [], []
    if parts:
        yield block()


def _file_blocks(path: Path, topics: set[str] | None) -> Iterator[_Block]:
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            try:
                summary = reader.get_summary()
            except (McapError, struct.error, ValueError, EOFError):
                summary = None
            chunks = _chunks_in_order(summary, topics)
            if chunks is not None:
                yield from _chunk_blocks(f, summary, chunks, topics)
            else:
                yield from _reader_blocks(reader, topics)
    except FileNotFoundError as err:
        raise BagError(f"bag {path} does not exist") from err
    except (McapError, ZstdError, struct.error, ValueError, EOFError) as err:
        raise BagError(f"bag {path} cannot be read ({type(err).__name__}: {err}); if its writer was "
                       f"killed, run `indoor-loc bag recover {path} FIXED.mcap`") from err


def _iter_file(path: Path, topics: set[str] | None) -> Iterator[tuple[int, int, RawMessage]]:
    for b in _file_blocks(path, topics):
        buf, names = b.buf, b.names
        for t, cid, a, e, pub in zip(b.times, b.cids, b.starts, b.ends, b.pubs):
            topic, type_name = names[cid]
            yield t, 0, RawMessage(topic, type_name, t, buf[a:e], pub)


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
    def stream(i: int, p: Path) -> Iterator[tuple[int, int, int, RawMessage]]:
        return ((t, i, k, m) for k, (t, _, m) in enumerate(_iter_file(p, wanted)))

    for _, _, _, m in heapq.merge(*(stream(i, p) for i, p in enumerate(files))):
        yield m


class RawRun:
    """Consecutive stored messages of one topic in replay order (:func:`read_runs`): log times
    (``stamps``, ns) and CDR bytes, kept in the buffer they were read into until asked for."""
    __slots__ = ("topic", "type", "stamps", "_buf", "_starts", "_ends")

    def __init__(self, topic: str, type_name: str, stamps: list[int], buf: bytes, starts: list[int],
                 ends: list[int]) -> None:
        self.topic, self.type, self.stamps = topic, type_name, stamps
        self._buf, self._starts, self._ends = buf, starts, ends

    def __len__(self) -> int:
        return len(self.stamps)

    def part(self, a: int, b: int) -> RawRun:
        """Messages ``a`` to ``b - 1``."""
        return RawRun(self.topic, self.type, self.stamps[a:b], self._buf, self._starts[a:b], self._ends[a:b])

    def data(self, i: int) -> bytes:
        """CDR bytes of message ``i``."""
        return self._buf[self._starts[i]:self._ends[i]]

    def records(self) -> Any:
        """The messages as an (N, size) uint8 array when they all have one size (a view of the
        buffer when they lie evenly spaced in it), else None."""
        return _records(self._buf, self._starts, self._ends)


def _records(buf: bytes, starts: list[int], ends: list[int]) -> Any:
    import numpy as np
    n = len(starts)
    if not n:
        return None
    size = ends[0] - starts[0]
    s = np.asarray(starts, np.int64)
    if n > 1 and np.any(np.asarray(ends, np.int64) - s != size):
        return None
    a = np.frombuffer(buf, np.uint8)
    stride = starts[1] - starts[0] if n > 1 else size
    if stride >= size and (n == 1 or starts[-1] - starts[0] == stride * (n - 1)) and np.all(s[1:] - s[:-1] == stride):
        return np.lib.stride_tricks.as_strided(a[starts[0]:], shape=(n, size), strides=(stride, 1), writeable=False)
    return a[s[:, None] + np.arange(size)]


def records_of(runs: list[RawRun]) -> Any:
    """The messages of consecutive runs of one topic as one (N, size) uint8 array, or None when
    they do not all have one size (:meth:`RawRun.records`)."""
    import numpy as np
    groups: list[tuple[bytes, list[int], list[int]]] = []
    for r in runs:                      # runs read from one buffer (chunk) are gathered together
        if groups and groups[-1][0] is r._buf:
            groups[-1][1].extend(r._starts)
            groups[-1][2].extend(r._ends)
        else:
            groups.append((r._buf, list(r._starts), list(r._ends)))
    mats = [_records(*g) for g in groups]
    if any(m is None for m in mats) or len({m.shape[1] for m in mats}) != 1:
        return None
    return mats[0] if len(mats) == 1 else np.concatenate(mats)


def read_runs(paths: str | os.PathLike | Iterable[str | os.PathLike],
              topics: Iterable[str] | None = None) -> Iterator[RawRun]:
    """:func:`read_raw`'s messages, in the same order, as runs of consecutive messages of one topic
    (a run may end at a chunk boundary even if the topic goes on): no object per message."""
    wanted = set(topics) if topics is not None else None
    files = bag_files(paths)
    streams = [_file_blocks(p, wanted) for p in files]
    heads: list[tuple[int, int, _Block, int]] = []    # (time of the next message, file, block, position)
    for i, st in enumerate(streams):
        b = next(st, None)
        if b is not None:
            heads.append((b.times[0], i, b, 0))
    heapq.heapify(heads)
    while heads:
        # the file whose next message comes first (ties: file order) gives every message before the
        # next message of any other file (at the same time: only if it comes first in file order)
        _, i, b, pos = heapq.heappop(heads)
        times, cids, names = b.times, b.cids, b.names
        stop = len(times)
        if heads:
            t_o, j = heads[0][0], heads[0][1]
            stop = (bisect.bisect_right if i < j else bisect.bisect_left)(times, t_o, pos, stop)
        a = pos
        while a < stop:
            cid = cids[a]
            e = a + 1
            while e < stop and cids[e] == cid:
                e += 1
            topic, type_name = names[cid]
            yield RawRun(topic, type_name, times[a:e], b.buf, b.starts[a:e], b.ends[a:e])
            a = e
        if stop < len(times):
            heapq.heappush(heads, (times[stop], i, b, stop))
            continue
        nb = next(streams[i], None)
        if nb is not None:
            heapq.heappush(heads, (nb.times[0], i, nb, 0))


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
