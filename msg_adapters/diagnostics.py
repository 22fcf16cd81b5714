"""Stage health -> diagnostic_msgs/DiagnosticArray for ``/diagnostics`` (live and offline), and the
reverse lookups tools and tests use."""
from __future__ import annotations

import struct
from typing import Any, NamedTuple, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from msg_adapters.time import stamp_from_ns


class StatusSummary(NamedTuple):
    """One DiagnosticStatus as plain values: level (0 OK, 1 WARN, 2 ERROR, 3 STALE)."""
    name: str
    level: int
    message: str
    hardware_id: str
    values: dict[str, str]


#: A rejection or a loss keeps the status at WARN (ERROR for internal errors) this long, ns;
#: afterwards the status returns to OK and only the cumulative counters remember it.
RECENT_NS = 10_000_000_000


def status_array(name: str, level: int, message: str, values: dict[str, str], now_ns: int,
                 hardware_id: str = "") -> DiagnosticArray:
    """A DiagnosticArray with one status (level 0 OK, 1 WARN, 2 ERROR) for nodes without a stage
    (recorder, player)."""
    arr = DiagnosticArray()
    arr.header.stamp = stamp_from_ns(now_ns)
    st = DiagnosticStatus()
    st.name, st.message, st.hardware_id = name, message, hardware_id or "/"
    st.level = bytes([int(level)])
    st.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
    arr.status = [st]
    return arr


def _recent(event_ns: int | None, now_ns: int) -> bool:
    return event_ns is not None and now_ns - event_ns <= RECENT_NS


def stage_diagnostics(name: str, stage, now_ns: int) -> DiagnosticArray:
    """One DiagnosticStatus for a stage: input counts/rates/last stamps, outputs, rejections,
    messages lost before reaching the stage (``lost.<topic>``).

    Level: ERROR when the stage reports a standing ``error`` (e.g. no radio map) or a message
    raised an internal error in the last ``RECENT_NS``; WARN when a message was rejected or lost in
    that window, or the stage reports a standing ``warning`` (e.g. scans not fitting the radio map);
    else OK (the counters stay cumulative). A rejection with no clock (offline without a stamp) counts
    as recent.
    """
    arr = DiagnosticArray()
    arr.header.stamp = stamp_from_ns(now_ns)
    st = DiagnosticStatus()
    st.name = name
    st.hardware_id = stage.namespace or "/"
    d = stage.diag
    rejected = sum(d.rejected.values())
    lost = sum(d.lost.values()) if hasattr(d, "lost") else 0
    recent_reject = rejected > 0 and (d.last_reject_ns is None or _recent(d.last_reject_ns, now_ns))
    recent_loss = lost > 0 and _recent(d.last_loss_ns, now_ns)
    errors = d.rejected.get("internal_error", 0)
    st.level = DiagnosticStatus.OK
    parts = []
    if recent_reject:
        internal = errors > 0 and (d.last_internal_ns is None or _recent(d.last_internal_ns, now_ns))
        st.level = DiagnosticStatus.ERROR if internal else DiagnosticStatus.WARN
        parts.append(f"{rejected} messages rejected (last: {d.last_error_reason})")
    if recent_loss:
        st.level = max(st.level, DiagnosticStatus.WARN)
        parts.append(f"{lost} input messages lost (" + ", ".join(f"{t} {n}" for t, n in sorted(d.lost.items())) + ")")
    st.message = "; ".join(parts) if parts else "ok"
    kv = dict(d.summary())
    extra = stage.extra_diagnostics()
    kv.update(extra)
    if extra.get("warning") and st.level < DiagnosticStatus.WARN:   # a standing warning (e.g. map mismatch)
        st.level = DiagnosticStatus.WARN
        st.message = str(extra["warning"]) + (f"; {st.message}" if parts else "")
    if extra.get("error"):
        st.level = DiagnosticStatus.ERROR
        st.message = str(extra["error"]) + (f"; {st.message}" if parts else "")
    st.values = [KeyValue(key=str(k), value=str(v)) for k, v in kv.items()]
    arr.status = [st]
    return arr


def diagnostics_from_msg(arr: DiagnosticArray) -> dict[str, StatusSummary]:
    """{status name: StatusSummary} of a DiagnosticArray (a later duplicate name wins)."""
    out: dict[str, StatusSummary] = {}
    for st in arr.status:
        level = st.level if isinstance(st.level, int) else int.from_bytes(st.level, "little")
        out[st.name] = StatusSummary(st.name, level, st.message, st.hardware_id,
                                     {kv.key: kv.value for kv in st.values})
    return out


def with_inputs(arr: DiagnosticArray, inputs: Sequence[Any], now_ns: int) -> DiagnosticArray:
    """Add each input's liveness (``inputs``: ``InputReport`` of ``indoor_loc.nodes.liveness``) to the
    status of ``arr`` (:func:`stage_diagnostics`): ``in.<topic>.state`` (waiting, flowing, stalled;
    received for an occasional input), ``.age_s`` (node clock since its last message), ``.stall_after_s``,
    ``.upstream_restarts``, and once they happened ``.last_gap_s`` (the latest stall that ended: time
    without input) and ``.resubscribed``. A stalled input makes the status WARN, or ERROR if the stage
    requires it; an upstream restart keeps it at WARN for ``RECENT_NS``."""
    st = arr.status[0]
    level = st.level
    parts = []
    values = []
    for r in inputs:
        key = f"in.{r.topic}"
        values += [KeyValue(key=f"{key}.state", value=r.state),
                   KeyValue(key=f"{key}.age_s", value="" if r.age_s is None else f"{r.age_s:.2f}"),
                   KeyValue(key=f"{key}.stall_after_s", value=f"{r.stall_after_s:.2f}"),
                   KeyValue(key=f"{key}.upstream_restarts", value=str(r.restarts))]
        if r.last_gap_s is not None:
            values.append(KeyValue(key=f"{key}.last_gap_s", value=f"{r.last_gap_s:.2f}"))
        if r.resubscribed:
            values.append(KeyValue(key=f"{key}.resubscribed", value=str(r.resubscribed)))
        if r.state == "stalled":
            level = max(level, DiagnosticStatus.ERROR if r.required else DiagnosticStatus.WARN)
            parts.append(f"{r.topic} stalled (no message for {r.age_s:.1f} s)")
        if r.restarts and _recent(r.last_restart_ns, now_ns):
            level = max(level, DiagnosticStatus.WARN)
            gap = f"; {r.last_gap_s:.1f} s without input" if r.last_gap_s is not None else ""
            parts.append(f"{r.topic}: upstream restarted ({r.restarts}{gap})")
    st.values = list(st.values) + values
    if parts:
        st.message = "; ".join(parts) + ("" if st.message == "ok" else f"; {st.message}")
    st.level = level
    return arr


_U32 = struct.Struct("<I")


def status_names_cdr(data: bytes) -> list[str]:
    """The ``name`` of every status of a serialised (CDR, little endian) ``DiagnosticArray``, read
    without building the message (a node watching who reports what on ``/diagnostics`` skips the
    values of hundreds of statuses a second). Raises ``ValueError`` on bytes that are not one."""
    if len(data) < 4 or data[:2] != b"\x00\x01":
        raise ValueError("not a little-endian CDR message")
    pos = 4 + 8                                          # encapsulation, header.stamp

    def string(pos: int) -> tuple[str, int]:
        pos += (-(pos - 4)) % 4
        (n,) = _U32.unpack_from(data, pos)
        end = pos + 4 + n
        if n < 1 or end > len(data):
            raise ValueError("truncated string")
        return data[pos + 4:end - 1].decode(), end

    def u32(pos: int) -> tuple[int, int]:
        pos += (-(pos - 4)) % 4
        return _U32.unpack_from(data, pos)[0], pos + 4

    _, pos = string(pos)                                 # header.frame_id
    count, pos = u32(pos)
    names = []
    for _ in range(count):
        pos += 1                                         # level (octet)
        name, pos = string(pos)
        names.append(name)
        _, pos = string(pos)                             # message
        _, pos = string(pos)                             # hardware_id
        n_values, pos = u32(pos)
        for _ in range(2 * n_values):                    # key, value
            _, pos = string(pos)
    return names
