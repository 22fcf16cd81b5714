"""Scan and recover MCAP bags whose writer died (no summary, maybe a partial last chunk)."""
from __future__ import annotations

import io
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import breakup_chunk

try:
    from zstandard import ZstdError
except ImportError:                      # without zstandard the mcap library reads no zstd chunk anyway
    ZstdError = McapError                # type: ignore[misc,assignment]

from indoor_loc.bag.writer import DEFAULT_CHUNK_SIZE, BagWriter
from indoor_loc.errors import BagError

_MAGIC = b"\x89MCAP0\r\n"
_OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 2, 3, 4, 5, 6


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
