"""Stage health -> diagnostic_msgs/DiagnosticArray for ``/diagnostics`` (live and offline), and the
reverse lookups tools and tests use."""
from __future__ import annotations

from typing import NamedTuple

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from msg_adapters.time import stamp_from_ns


class StatusSummary(NamedTuple):
    """One DiagnosticStatus as plain values: level (0 OK, 1 WARN, 2 ERROR, 3 STALE)."""
    name: str
    level: int
    message: str
    hardware_id: str
    values: dict[str, str]


def stage_diagnostics(name: str, stage, now_ns: int) -> DiagnosticArray:
    """One DiagnosticStatus for a stage: input counts/rates/last stamps, outputs, rejections.

    Level: ERROR when a message raised an internal error or the stage reports a standing ``error``
    (e.g. no radio map), WARN when any message was rejected, else OK.
    """
    arr = DiagnosticArray()
    arr.header.stamp = stamp_from_ns(now_ns)
    st = DiagnosticStatus()
    st.name = name
    st.hardware_id = stage.namespace or "/"
    rejected = sum(stage.diag.rejected.values())
    errors = stage.diag.rejected.get("internal_error", 0)
    st.level = DiagnosticStatus.ERROR if errors else (DiagnosticStatus.WARN if rejected else DiagnosticStatus.OK)
    st.message = f"{rejected} messages rejected (last: {stage.diag.last_error_reason})" if rejected else "ok"
    kv = dict(stage.diag.summary())
    extra = stage.extra_diagnostics()
    kv.update(extra)
    if extra.get("error"):
        st.level = DiagnosticStatus.ERROR
        st.message = str(extra["error"]) + (f"; {st.message}" if rejected else "")
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
