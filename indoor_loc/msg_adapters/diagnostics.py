"""Stage health -> diagnostic_msgs/DiagnosticArray for ``/diagnostics`` (live and offline)."""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from indoor_loc.msg_adapters.time import stamp_from_ns


def stage_diagnostics(name: str, stage, now_ns: int) -> DiagnosticArray:
    """One DiagnosticStatus for a stage: input counts/rates/last stamps, outputs, rejections."""
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
    kv.update(stage.extra_diagnostics())
    st.values = [KeyValue(key=str(k), value=str(v)) for k, v in kv.items()]
    arr.status = [st]
    return arr
