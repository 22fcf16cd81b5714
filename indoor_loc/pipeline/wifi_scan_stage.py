"""WifiScanStage: scans from topics or from the local interface -> normalised ``wifi/scan``.

Inputs (``source: topic``): ``wifi/scan_raw`` (diagnostic_msgs/DiagnosticArray in the
``wifi_scan.v1`` schema, e.g. a phone driver) and ``wifi/scan_json`` (std_msgs/String, CMU cabot
style JSON, see :mod:`indoor_loc.wifi.parsers`). With ``source: iw`` or ``nmcli`` the stage scans
the machine's interface instead: :meth:`WifiScanStage.acquire` runs the command (blocking; the
node calls it from a background thread at ``scan_period_s``) and the attempt is handed back through
:meth:`Stage.process` on the :data:`IFACE_INPUT` input, so counting, error containment and
publishing are the same as for topic input. Bags: ``indoor-loc run BAG --nodes wifi_scan`` replays
recorded ``wifi/scan_raw`` / ``wifi/scan_json`` through the same handlers.

Output: ``wifi/scan`` (schema ``wifi_scan.v1``), normalised by :func:`indoor_loc.wifi.normalize`
(lower-case unique BSSIDs, RSSI range, random-MAC / allow / deny / band / threshold filters).
A scan left empty by the filters is not published (counted as ``scans.empty``). Failed scan
commands are rejections with reason ``scan_<reason>`` (``scan_permission``, ``scan_timeout``...),
so ``/diagnostics`` shows them with the command's hint.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

from indoor_loc import params
from indoor_loc.contract import Qos
from indoor_loc.errors import InvalidMessageError
from msg_adapters.wifi_json import parse_json_msg
from msg_adapters.wifi_scan import scan_from_msg, scan_to_msg
from indoor_loc.params import require
from indoor_loc.pipeline.stage import Output, Port, Stage, rate_hz
from indoor_loc.pipeline.time_policy import TimeParams
from indoor_loc.errors import ScanCommandError
from indoor_loc.wifi.iface import TOOLS, InterfaceScanner, ScanAttempt, build_command
from indoor_loc.wifi.normalize import NormalizeParams, normalize_report
from indoor_loc.wifi.parsers import SIGNAL_MAPPINGS, ParseResult
from indoor_loc.wifi.types import WifiScan

SOURCES = ("topic",) + TOOLS
IFACE_INPUT = "iface"
"""Name of the internal input carrying :class:`ScanAttempt` objects (no subscription is made)."""

@dataclass(frozen=True)
class WifiScanParams:
    """Parameters of ``wifi_scan_node`` (see config/wifi_scan_node.yaml)."""
    source: str = params.field("topic", "where scans come from: 'topic' (wifi/scan_raw + wifi/scan_json), "
                                        "'iw' or 'nmcli' (scan the local interface)")
    interface: str = params.field("wlan0", "wireless interface scanned with source iw/nmcli")
    scan_period_s: float = params.field(5.0, "time between interface scans, s (start to start)")
    scan_timeout_s: float = params.field(10.0, "a scan command running longer is killed, s")
    frame_id: str = params.field("", "frame_id of published scans; '' keeps the input's, or "
                                     "'<namespace>/wifi_link' for interface scans")
    iw_command: str = params.field("", "command for source iw ('' = `iw dev {interface} scan`); "
                                       "{interface} is replaced")
    nmcli_command: str = params.field("", "command for source nmcli ('' = `nmcli -t -f BSSID,SSID,FREQ,SIGNAL,"
                                          "CHAN dev wifi list ifname {interface} --rescan auto`)")
    iw_dump_fallback: bool = params.field(True, "when `iw ... scan` is not permitted (no CAP_NET_ADMIN), use "
                                                "`iw ... scan dump` (cached results of the last system scan)")
    signal_mapping: str = params.field("nm", "0-100 quality -> dBm for nmcli: 'nm' (dBm = 0.6 q - 100, "
                                             "NetworkManager's scale) or 'half' (dBm = q/2 - 100)")
    normalize: NormalizeParams = params.group(NormalizeParams, "how readings are cleaned, for every source "
                                                               "(indoor_loc/wifi/normalize.py; normalize.*)")
    time: TimeParams = params.group(TimeParams, "which stamps are taken, clock jumps "
                                                "(indoor_loc/pipeline/time_policy.py)")

    def validate(self) -> None:
        o = type(self).__name__
        require(self.source in SOURCES, o, "source", f"one of {list(SOURCES)}", self.source)
        require(bool(self.interface.strip()) or self.source == "topic", o, "interface",
                "an interface name (e.g. 'wlan0')", self.interface)
        require(math.isfinite(self.scan_period_s) and self.scan_period_s > 0, o, "scan_period_s",
                "a period > 0 s", self.scan_period_s)
        require(math.isfinite(self.scan_timeout_s) and self.scan_timeout_s > 0, o, "scan_timeout_s",
                "a timeout > 0 s", self.scan_timeout_s)
        require(self.signal_mapping in SIGNAL_MAPPINGS, o, "signal_mapping", f"one of {list(SIGNAL_MAPPINGS)}",
                self.signal_mapping)
        params.validate_groups(self)


class WifiScanStage(Stage):
    """WiFi scan ingestion: topic / iw / nmcli scans -> normalised wifi/scan (schema wifi_scan.v1)."""
    NODE_NAME = "wifi_scan_node"
    PARAMS = WifiScanParams

    def __init__(self, p: WifiScanParams, *, namespace: str = "") -> None:
        super().__init__(p, namespace=namespace)
        self.params: WifiScanParams = p
        self._norm = p.normalize
        self.dropped: Counter = Counter()           # AP readings dropped by normalisation, by reason
        self.scans_published = 0
        self.scans_empty = 0
        self.scans_truncated = 0
        self.entries_skipped = 0
        self.aps_in = 0
        self.aps_out = 0
        self.last_aps = 0
        self._first_out_ns: int | None = None
        self._last_out_ns: int | None = None
        self.last_attempt: ScanAttempt | None = None
        self._json: tuple[Any, ParseResult] | None = None    # the JSON scan parsed for its stamp (stamp_of)
        self.scanner: InterfaceScanner | None = None
        if p.source != "topic":
            override = p.iw_command if p.source == "iw" else p.nmcli_command
            self.scanner = InterfaceScanner(
                p.source, p.interface, command=build_command(p.source, p.interface, override),
                timeout_s=p.scan_timeout_s, dump_fallback=p.iw_dump_fallback, signal_mapping=p.signal_mapping)
        self.on("wifi/scan_raw", self._on_raw)
        self.on("wifi/scan_json", self._on_json)
        self.on(IFACE_INPUT, self._on_attempt)

    def inputs(self) -> list[Port]:
        if self.params.source != "topic":
            return []
        # Scans are few and large (a 10 000-AP scan is ~1 MB, many UDP fragments): taken reliably, so
        # none is lost in DDS. A best-effort driver does not match a reliable subscription; the node
        # reports it (incompatible_qos) and qos_overrides.<topic>.subscription.reliability adapts.
        return [Port("wifi/scan_raw", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE),
                Port("wifi/scan_json", "std_msgs/msg/String", Qos.RELIABLE)]

    def outputs(self) -> list[Port]:
        return [Port("wifi/scan", "diagnostic_msgs/msg/DiagnosticArray", Qos.RELIABLE)]

    # -- interface scans ---------------------------------------------------------------------------
    def acquire(self, clock_ns) -> ScanAttempt:
        """Run the interface scan command once (blocking, up to ``scan_timeout_s``). Touches no stage
        counters, so a background thread may call it while the executor runs :meth:`process`."""
        if self.scanner is None:
            raise RuntimeError("acquire() needs source 'iw' or 'nmcli'")
        try:
            return self.scanner.scan(clock_ns)
        except Exception as err:  # noqa: BLE001 - the scan thread must outlive any bug; reported as a rejection
            return ScanAttempt(clock_ns(), self.scanner.tool, tuple(self.scanner.active_command()), 0.0,
                               error=ScanCommandError("internal", f"{type(err).__name__}: {err}"))

    def _on_attempt(self, attempt: ScanAttempt, recv_ns: int) -> list[Output]:
        self.last_attempt = attempt
        if attempt.error is not None:
            raise InvalidMessageError(f"scan_{attempt.error.reason}", str(attempt.error))
        assert attempt.result is not None
        return self._publish(attempt.result, self._frame(""), attempt.stamp_ns)

    # -- topic input ---------------------------------------------------------------------------------
    def _on_raw(self, msg: Any, recv_ns: int) -> list[Output]:
        scan = scan_from_msg(msg)       # raises InvalidMessageError -> counted by reason
        return self._publish(ParseResult(scan), self._frame(scan.frame_id), scan.stamp_ns)

    def stamp_of(self, topic: str, msg: Any) -> int | None:
        """A JSON scan's stamp is inside its text (or its reception time): parsed once, here, for the
        time policy, and kept for :meth:`_on_json`."""
        if topic != "wifi/scan_json":
            return super().stamp_of(topic, msg)
        self._json = (msg, parse_json_msg(msg, stamp_ns=self.diag.now_ns or 0,
                                          signal_mapping=self.params.signal_mapping))
        return self._json[1].scan.stamp_ns

    def _on_json(self, msg: Any, recv_ns: int) -> list[Output]:
        parsed = getattr(self, "_json", None)
        result = parsed[1] if parsed is not None and parsed[0] is msg else \
            parse_json_msg(msg, stamp_ns=recv_ns, signal_mapping=self.params.signal_mapping)
        self._json = None
        return self._publish(result, self._frame(result.scan.frame_id), result.scan.stamp_ns)

    # -- common ------------------------------------------------------------------------------------------
    def _frame(self, incoming: str) -> str:
        if self.params.frame_id:
            return self.params.frame_id
        if incoming:
            return incoming
        ns = self.namespace.strip("/")
        return f"{ns}/wifi_link" if ns else "wifi_link"

    def _publish(self, result: ParseResult, frame_id: str, stamp_ns: int) -> list[Output]:
        self.scans_truncated += int(result.truncated)
        self.entries_skipped += result.skipped
        raw = result.scan
        rep = normalize_report(raw, self._norm)
        self.dropped.update(rep.dropped)
        self.aps_in += len(raw)
        if len(rep.scan) == 0:
            self.scans_empty += 1
            return []
        scan = WifiScan(stamp_ns=int(stamp_ns), bssid=rep.scan.bssid, rssi_dbm=rep.scan.rssi_dbm,
                        freq_mhz=rep.scan.freq_mhz, ssid=rep.scan.ssid, age_ms=rep.scan.age_ms,
                        frame_id=frame_id, source=rep.scan.source or "topic")
        msg = scan_to_msg(scan)
        self.scans_published += 1
        self.aps_out += len(scan)
        self.last_aps = len(scan)
        self._first_out_ns = stamp_ns if self._first_out_ns is None else self._first_out_ns
        self._last_out_ns = stamp_ns if self._last_out_ns is None else max(self._last_out_ns, stamp_ns)
        return [("wifi/scan", msg)]

    def scans_per_s(self) -> float:
        """Published scans per second of scan time (0 before two scans)."""
        return rate_hz(self.scans_published, self._first_out_ns, self._last_out_ns)

    def extra_diagnostics(self) -> dict[str, str]:
        out = {
            "source": self.params.source,
            "scans.published": str(self.scans_published),
            "scans.empty": str(self.scans_empty),
            "scans.truncated": str(self.scans_truncated),
            "scans_per_s": f"{self.scans_per_s():.3f}",
            "aps_per_scan.in_mean": f"{self.aps_in / max(self.scans_published + self.scans_empty, 1):.1f}",
            "aps_per_scan.mean": f"{self.aps_out / max(self.scans_published, 1):.1f}",
            "aps_per_scan.last": str(self.last_aps),
            "entries_skipped": str(self.entries_skipped),
        }
        out.update({f"dropped.{k}": str(v) for k, v in sorted(self.dropped.items())})
        if self.scanner is not None:
            out["iface.command"] = " ".join(self.scanner.active_command())
            out["iface.mode"] = "scan dump (fallback)" if self.scanner.using_dump else "scan"
            if self.scanner.fallback_reason:
                out["iface.fallback_reason"] = self.scanner.fallback_reason
            a = self.last_attempt
            if a is not None:
                out["iface.last_duration_s"] = f"{a.duration_s:.2f}"
                out["iface.last_error"] = str(a.error) if a.error is not None else ""
        return out
