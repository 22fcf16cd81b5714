"""Zero the padding bytes of a serialised ROS 2 message, so the same message gives the same bytes.

rclpy's serialiser aligns each field (CDR: a primitive of size n at an offset multiple of n, counted
from after the 4-byte encapsulation header; 8-byte types at 8) but leaves whatever its buffer held in
the bytes it skips, and in the trailing bytes that round the payload up to 4: the same message
serialised twice can differ (25 850 of 27 053 messages of one simulated bag did), so a bag written
twice from the same seed was not the same file. :func:`zero_padding` walks the message's type
(rosidl introspection: ``SLOT_TYPES``) through the bytes and zeroes every byte that is not data. A
payload it cannot walk (a type it does not know, a length beyond the data) is returned unchanged.
"""
from __future__ import annotations

import importlib
import struct
from functools import lru_cache
from typing import Any

_SIZES = {"boolean": 1, "octet": 1, "char": 1, "uint8": 1, "int8": 1, "wchar": 2, "int16": 2, "uint16": 2,
          "float": 4, "int32": 4, "uint32": 4, "double": 8, "int64": 8, "uint64": 8, "long double": 16}
_HEADER = 4


@lru_cache(maxsize=None)
def _fields(cls: type) -> tuple[Any, ...]:
    return tuple(cls.SLOT_TYPES)


@lru_cache(maxsize=None)
def _nested_class(namespaces: tuple[str, ...], name: str) -> type:
    return getattr(importlib.import_module(".".join(namespaces)), name)


class _Walker:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.out = bytearray(len(data))
        self.pos = _HEADER
        self.out[:_HEADER] = data[:_HEADER]

    def align(self, n: int) -> None:
        n = min(n, 8)
        self.pos += (-(self.pos - _HEADER)) % n       # the skipped bytes stay zero in ``out``

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise ValueError("beyond the data")
        chunk = self.data[self.pos:self.pos + n]
        self.out[self.pos:self.pos + n] = chunk
        self.pos += n
        return chunk

    def length(self) -> int:
        self.align(4)
        n, = struct.unpack("<I", self.take(4))
        return n

    def value(self, t: Any) -> None:
        from rosidl_parser import definition as d
        if isinstance(t, d.BasicType):
            size = _SIZES.get(t.typename)
            if size is None:
                raise ValueError(t.typename)
            self.align(size)
            self.take(size)
        elif isinstance(t, d.AbstractString):
            self.take(self.length())                     # characters and the terminating NUL
        elif isinstance(t, d.AbstractWString):
            self.take(2 * self.length())
        elif isinstance(t, d.NamespacedType):
            self.message(_nested_class(tuple(t.namespaces), t.name))
        elif isinstance(t, d.Array):
            self.items(t.value_type, t.size)
        elif isinstance(t, d.AbstractSequence):
            self.items(t.value_type, self.length())
        else:
            raise ValueError(type(t).__name__)

    def items(self, t: Any, n: int) -> None:
        from rosidl_parser import definition as d
        if isinstance(t, d.BasicType) and t.typename in _SIZES:
            size = _SIZES[t.typename]
            if n:
                self.align(size)
                self.take(size * n)
            return
        for _ in range(n):
            self.value(t)

    def message(self, cls: type) -> None:
        fields = _fields(cls)
        if not fields:                  # an empty message is serialised as one uint8
            self.take(1)
        for t in fields:
            self.value(t)


def zero_padding(data: bytes, msg_class: type) -> bytes:
    """``data`` (a little- or big-endian CDR payload of ``msg_class``) with every padding byte zeroed."""
    if len(data) < _HEADER or data[0] != 0 or data[1] not in (0, 1):
        return data
    walker = _Walker(data)
    try:
        if data[1] == 0:               # big endian: lengths read the other way
            return data
        walker.message(msg_class)
    except (ValueError, struct.error, ImportError, AttributeError):
        return data
    return bytes(walker.out)


def canonical_cdr(msg: Any) -> bytes:
    """``msg`` serialised with its padding zeroed: the same message gives the same bytes, whatever the
    serialiser's buffer held (compare these, never :func:`rclpy.serialization.serialize_message`'s
    own bytes, when two messages must be equal byte for byte)."""
    from rclpy.serialization import serialize_message
    return zero_padding(serialize_message(msg), type(msg))
