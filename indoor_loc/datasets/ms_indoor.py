"""Microsoft Indoor Location Competition 2.0 traces (pure Python/numpy, no ROS).

The format (location-competition/indoor-location-competition-20, MIT licence): one walk per text
file (``.txt`` or ``.txt.gz``), ``#`` header lines (``startTime``, ``SiteID``/``SiteName``,
``FloorId``/``FloorName``, ``Brand``/``Model``/``AndroidName``/``APILevel``, one ``type:… name:…``
line per sensor, ``endTime``), then tab-separated rows ``unix_ms TYPE values…`` **not sorted by
time**:

==============================  ==============================================================
``TYPE_ACCELEROMETER``          x y z m/s² (incl. gravity), accuracy
``TYPE_GYROSCOPE``              x y z rad/s, accuracy
``TYPE_MAGNETIC_FIELD``         x y z µT, accuracy
``TYPE_*_UNCALIBRATED``         x y z, bias x y z, accuracy
``TYPE_ROTATION_VECTOR``        x y z (w = sqrt(1 - x² - y² - z²)), accuracy
``TYPE_WAYPOINT``               x y m: the surveyed position at that instant (linear in between)
``TYPE_WIFI``                   ssid bssid rssi_dbm frequency_mhz last_seen_unix_ms
``TYPE_BEACON``                 iBeacon: uuid major minor tx_power rssi distance mac [time]
                                (``Trace.ble``: :mod:`indoor_loc.datasets.ms_indoor_ble`)
==============================  ==============================================================

Other row types (Bluetooth ``TYPE_BLUE``/``TYPE_BLU4``, ``TYPE_DIST1``…) are counted, not used.
WiFi rows with the same first-column time are one scan; a BSSID listed twice in a scan (hidden and
named SSID) keeps its most recently seen reading. ``last_seen`` earlier than the scan time marks a
cached result: ``age_ms = scan time − last_seen`` (clamped at 0; a later ``last_seen`` is counted
as an oddity).

Frames and time: the floor plan spans ``[0, width] × [0, height]`` metres (``floor_info.json``),
y up, so waypoints are already ENU-like map coordinates (x right, y up on the plan); floors of one
site share that frame. ``z`` = the floor's storey index × ``storey_height_m``. Times are Unix
milliseconds in the files and int nanoseconds here.
"""
from __future__ import annotations

import gzip
import math
import re
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from indoor_loc.datasets.ms_indoor_ble import beacon_row, beacon_scans
from indoor_loc.errors import DatasetError
from indoor_loc.wifi.ble import BleScan
from indoor_loc.wifi.types import WifiScan


#: row type -> (attribute, number of values used)
_SENSORS = {
    "TYPE_ACCELEROMETER": ("acc", 3),
    "TYPE_GYROSCOPE": ("gyro", 3),
    "TYPE_MAGNETIC_FIELD": ("mag", 3),
    "TYPE_ACCELEROMETER_UNCALIBRATED": ("acc_uncal", 6),
    "TYPE_GYROSCOPE_UNCALIBRATED": ("gyro_uncal", 6),
    "TYPE_MAGNETIC_FIELD_UNCALIBRATED": ("mag_uncal", 6),
    "TYPE_ROTATION_VECTOR": ("rotvec", 3),
}
#: default storey height used for z (m); malls have tall storeys, 5 m is typical.
STOREY_HEIGHT_M = 5.0


@dataclass(frozen=True)
class Series:
    """Time series of one sensor: ``t_ns`` (N,) int64 sorted, ``values`` (N, C) float."""
    t_ns: np.ndarray
    values: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)

    @staticmethod
    def empty(c: int) -> "Series":
        return Series(np.zeros(0, np.int64), np.zeros((0, c)))


@dataclass
class Trace:
    """One walk. Sensors as :class:`Series` (empty when absent), ``waypoints`` (t_ns (K,),
    xy (K, 2) m), WiFi ``scans`` sorted by stamp (``age_ms`` per AP), ``row_counts`` per row type,
    ``oddities`` (human-readable strings)."""
    trace_id: str
    path: Path
    header: dict[str, str]
    sensors: list[dict[str, str]]
    acc: Series
    gyro: Series
    mag: Series
    acc_uncal: Series
    gyro_uncal: Series
    mag_uncal: Series
    rotvec: Series
    waypoint_t: np.ndarray
    waypoint_xy: np.ndarray
    scans: list[WifiScan]
    beacons: int = 0
    #: the ``TYPE_BEACON`` rows as BLE scans (:mod:`indoor_loc.datasets.ms_indoor_ble`)
    ble: list[BleScan] = field(default_factory=list)
    row_counts: Counter = field(default_factory=Counter)
    oddities: list[str] = field(default_factory=list)
    dropped: Counter = field(default_factory=Counter)

    @property
    def floor(self) -> str:
        return self.header.get("FloorName", "")

    @property
    def device(self) -> str:
        return f"{self.header.get('Brand', '?')} {self.header.get('Model', '?')}".strip()

    @property
    def start_ns(self) -> int:
        ts = [s.t_ns[0] for s in (self.acc, self.gyro, self.mag, self.rotvec) if len(s)]
        ts += [self.waypoint_t[0]] if len(self.waypoint_t) else []
        ts += [self.scans[0].stamp_ns] if self.scans else []
        return int(min(ts)) if ts else 0

    @property
    def end_ns(self) -> int:
        ts = [s.t_ns[-1] for s in (self.acc, self.gyro, self.mag, self.rotvec) if len(s)]
        ts += [self.waypoint_t[-1]] if len(self.waypoint_t) else []
        ts += [self.scans[-1].stamp_ns] if self.scans else []
        return int(max(ts)) if ts else 0

    def quaternions_xyzw(self) -> np.ndarray:
        """(N, 4) unit quaternions (x, y, z, w) device→ENU from the rotation vector."""
        v = self.rotvec.values[:, :3]
        w = np.sqrt(np.clip(1.0 - (v * v).sum(axis=1), 0.0, 1.0))
        q = np.column_stack([v, w])
        return q / np.linalg.norm(q, axis=1, keepdims=True)

    def truth_at(self, t_ns) -> tuple[np.ndarray, np.ndarray]:
        """(xy (N, 2), inside (N,) bool): positions interpolated between waypoints; NaN outside
        the waypoint span."""
        t = np.asarray(t_ns, np.int64)
        out = np.full((len(t), 2), np.nan)
        if len(self.waypoint_t) == 0:
            return out, np.zeros(len(t), bool)
        w0 = self.waypoint_t[0]
        inside = (t >= w0) & (t <= self.waypoint_t[-1])
        tr = (t[inside] - w0).astype(float)
        wr = (self.waypoint_t - w0).astype(float)
        for k in range(2):
            out[inside, k] = np.interp(tr, wr, self.waypoint_xy[:, k])
        return out, inside


def _open_text(path: Path):
    if path.suffix == ".gz":
        return gzip.open(path, "rt", encoding="utf-8", errors="replace")
    return open(path, encoding="utf-8", errors="replace")


def trace_id_of(path: Path) -> str:
    name = path.name
    for suf in (".txt.gz", ".txt"):
        if name.endswith(suf):
            return name[: -len(suf)]
    return path.stem


def read_trace(path: str | Path, *, imu: bool = True) -> Trace:
    """Parse one trace file (``.txt`` or ``.txt.gz``). ``imu=False`` skips the inertial rows
    (faster when only WiFi and waypoints are needed). Raises DatasetError if unreadable or
    without any row."""
    path = Path(path)
    header: dict[str, str] = {}
    sensors: list[dict[str, str]] = []
    rows: dict[str, list] = {k: [] for k in _SENSORS}
    wp: list[tuple[int, float, float]] = []
    wifi: list[tuple[int, str, str, float, float, int | None]] = []
    counts: Counter = Counter()
    dropped: Counter = Counter()
    oddities: list[str] = []
    beacons = run_on = no_freq = no_seen = 0
    beacon_rows: list = []
    try:
        fh = _open_text(path)
        with fh:
            for raw in fh:
                raw = raw.rstrip("\r\n").lstrip("\ufeff")
                if not raw:
                    continue
                records = _split_run_on(raw)
                if len(records) > 1:
                    run_on += 1
                for line in records:
                    if line.startswith("#"):
                        kv = _header_fields(line)
                        if "type" in kv:
                            sensors.append(kv)
                        else:
                            header.update(kv)
                        continue
                    f = line.split("\t")
                    if len(f) < 2:
                        dropped["malformed"] += 1
                        continue
                    typ = f[1].strip()
                    counts[typ] += 1
                    try:
                        t = int(f[0])
                    except ValueError:
                        dropped["malformed"] += 1
                        continue
                    if not 0 <= t <= _MAX_STAMP_MS:           # its ns would not fit the int64 stamps
                        dropped["stamp_range"] += 1
                        continue
                    spec = _SENSORS.get(typ)
                    if spec is not None:
                        if not imu:
                            continue
                        n = spec[1]
                        try:
                            vals = [float(x) for x in f[2:2 + n]]
                        except ValueError:
                            dropped[f"malformed_{spec[0]}"] += 1
                            continue
                        if len(vals) != n or not all(math.isfinite(v) for v in vals):
                            dropped[f"malformed_{spec[0]}"] += 1
                            continue
                        rows[typ].append((t, vals))
                    elif typ == "TYPE_WIFI":
                        got = _wifi_fields(f)
                        if isinstance(got, str):
                            dropped[got] += 1
                            continue
                        bssid, ssid, rssi, freq, seen = got
                        if freq is None:
                            no_freq += 1
                        if seen is None:
                            no_seen += 1
                        if not (math.isfinite(rssi) and -120.0 <= rssi <= 0.0):
                            dropped["rssi_range"] += 1
                            continue
                        wifi.append((t, bssid, ssid, rssi, 0.0 if freq is None else freq, seen))
                    elif typ == "TYPE_WAYPOINT":
                        try:
                            x, y = float(f[2]), float(f[3])
                        except (ValueError, IndexError):
                            dropped["malformed_waypoint"] += 1
                            continue
                        if not (math.isfinite(x) and math.isfinite(y)):
                            dropped["malformed_waypoint"] += 1
                            continue
                        wp.append((t, x, y))
                    elif typ == "TYPE_BEACON":
                        beacons += 1
                        row = beacon_row(t, f)
                        if isinstance(row, str):
                            dropped[row] += 1
                        else:
                            beacon_rows.append(row)
    except (OSError, EOFError, zlib.error) as err:          # (gzip.BadGzipFile is an OSError)
        raise DatasetError(f"cannot read trace {path}: {err}") from err
    if not counts:
        raise DatasetError(f"trace {path} has no data rows")

    def series(typ: str) -> Series:
        r = rows[typ]
        n = _SENSORS[typ][1]
        if not r:
            return Series.empty(n)
        t = np.array([a for a, _ in r], np.int64) * 1_000_000
        v = np.array([b for _, b in r], float)
        o = np.argsort(t, kind="stable")
        t, v = t[o], v[o]
        # exact duplicate stamps: keep the last row of each stamp
        keep = np.r_[t[1:] != t[:-1], True]
        if not keep.all():
            dropped[f"duplicate_stamp_{_SENSORS[typ][0]}"] += int((~keep).sum())
        return Series(t[keep], v[keep])

    sers = {_SENSORS[k][0]: series(k) for k in _SENSORS}
    wp.sort(key=lambda r: r[0])
    wt = np.array([r[0] for r in wp], np.int64) * 1_000_000
    wxy = np.array([[r[1], r[2]] for r in wp], float).reshape(-1, 2)
    if len(wt) > 1 and np.any(np.diff(wt) == 0):
        keep = np.r_[True, np.diff(wt) != 0]
        oddities.append(f"{int((~keep).sum())} waypoints share a stamp with the previous one (kept the first)")
        wt, wxy = wt[keep], wxy[keep]
    scans, dup, future = _group_scans(wifi, trace_id_of(path))
    if dup:
        oddities.append(f"{dup} duplicate BSSID readings within scans (kept the most recently seen)")
    if future:
        oddities.append(f"{future} WiFi readings last seen after their scan time (age clamped to 0)")
    if run_on:
        oddities.append(f"{run_on} lines held records run together (a missing line end): split into their records")
    if no_freq:
        oddities.append(f"{no_freq} WiFi readings without a frequency (kept as 0 = unknown)")
    if no_seen:
        oddities.append(f"{no_seen} WiFi readings without a last-seen time (age unknown)")
    if not len(wt):
        oddities.append("no waypoints: nothing to score or map")
    elif len(wt) < 2:
        oddities.append("one waypoint: no span to interpolate the truth over, nothing to score or map")
    for k, v in sorted(dropped.items()):
        oddities.append(f"{v} rows dropped: {k}")
    for name, s in sers.items():
        if name in ("acc", "gyro", "mag", "rotvec") and imu and len(s) == 0:
            oddities.append(f"no {name} rows (sensor missing)")
    unknown = sorted(t for t in counts if t not in _SENSORS and t not in ("TYPE_WIFI", "TYPE_WAYPOINT", "TYPE_BEACON"))
    if unknown:
        oddities.append("rows not used: " + ", ".join(f"{t} {counts[t]}" for t in unknown))
    return Trace(trace_id=trace_id_of(path), path=path, header=header, sensors=sensors, waypoint_t=wt,
                 waypoint_xy=wxy, scans=scans, beacons=beacons, ble=beacon_scans(beacon_rows, trace_id_of(path)),
                 row_counts=counts, oddities=oddities,
                 dropped=dropped, **sers)


#: the latest Unix-ms stamp whose ns fit an int64 (the year 2262)
_MAX_STAMP_MS = (2 ** 63 - 1) // 1_000_000
#: a record's start inside a line: a 13-digit Unix-ms stamp and a row type, or a header key
_RECORD_START = re.compile(r"\d{13}\tTYPE_|#\t[A-Za-z]+:")
#: header keys of the format, by lower-case spelling (files differ in case and separators)
_HEADER_KEYS = {k.lower(): k for k in (
    "startTime", "endTime", "SiteID", "SiteName", "FloorId", "FloorName", "Brand", "Model", "AndroidName",
    "APILevel", "VersionName", "VersionCode", "type", "name", "version", "vendor", "resolution", "power",
    "maximumRange")}
_HEADER_SPLIT = re.compile(r"\t|\s+(?=(?:" + "|".join(_HEADER_KEYS.values()) + r"):)", re.IGNORECASE)
_MAC_RE = re.compile(r"^[0-9a-f]{2}([:-][0-9a-f]{2}){5}$")


def _split_run_on(line: str) -> list[str]:
    """A line as its records. In some of the competition's files a line lacks its end, so the next
    record (a 13-digit Unix-ms stamp then ``TYPE_…``, or a ``#`` header) follows on the same line, its
    stamp glued to the previous record's last field (or to text that is no record); each record starts
    where such a start is found, and what comes before the first is a (malformed) record of its own."""
    if line.count("TYPE_") <= 1 and "#" not in line[1:] and (line[:1].isdigit() or line[:1] == "#"):
        return [line]                        # one record from the start of the line: the usual case
    cuts = [m.start() for m in _RECORD_START.finditer(line) if m.start() > 0]
    if not cuts:
        return [line]
    return [line[a:b] for a, b in zip([0, *cuts], [*cuts, len(line)])]


def _header_fields(line: str) -> dict[str, str]:
    """``key:value`` fields of a ``#`` line: tab-separated as the format writes them, or separated by
    spaces before a known key; known keys take the format's spelling whatever their case."""
    out = {}
    for tok in _HEADER_SPLIT.split(line.lstrip("#")):
        tok = (tok or "").strip()
        if ":" in tok:
            k, v = tok.split(":", 1)
            k = k.strip()
            out[_HEADER_KEYS.get(k.lower(), k)] = v.strip()
    return out


def _wifi_fields(f: list[str]) -> tuple[str, str, float, float | None, int | None] | str:
    """(bssid, ssid, rssi, freq or None, last_seen or None) of a ``TYPE_WIFI`` row split at tabs, or
    the reason it is dropped. The BSSID is the rightmost field shaped like a MAC address (an SSID may
    hold tabs); after it come the RSSI, then the frequency (MHz) and the last-seen Unix ms, either of
    which older files leave out: a 13-digit number is a time, a smaller one a frequency."""
    at = next((i for i in range(len(f) - 1, 1, -1) if _MAC_RE.match(f[i].strip().lower())), -1)
    if at < 0:
        return "bad_bssid" if len(f) >= 5 else "malformed_wifi"
    bssid = f[at].strip().lower().replace("-", ":")
    ssid = "\t".join(f[2:at])
    tail = [x.strip() for x in f[at + 1:] if x.strip()]
    if not tail or len(tail) > 3:
        return "malformed_wifi"
    try:
        rssi = float(tail[0])
        nums = [float(x) for x in tail[1:]]
    except ValueError:
        return "malformed_wifi"
    if not all(math.isfinite(v) and v >= 0 for v in nums):
        return "malformed_wifi"
    freq: float | None = None
    seen: int | None = None
    if len(nums) == 2:                          # the format's own order
        freq, seen = nums[0], int(nums[1])
    elif nums and nums[0] >= 1e11:
        seen = int(nums[0])
    elif nums:
        freq = nums[0]
    return bssid, ssid, rssi, freq, seen


def _group_scans(rows: list, source: str) -> tuple[list[WifiScan], int, int]:
    """WiFi rows -> scans (one per first-column time), duplicates resolved; returns
    (scans sorted by stamp, duplicate readings dropped, readings seen after their scan)."""
    by_t: dict[int, dict[str, tuple]] = {}
    dup = future = 0
    for t, b, ssid, rssi, freq, seen in rows:
        scan = by_t.setdefault(t, {})
        old = scan.get(b)
        if old is not None:
            dup += 1
            # keep the most recently seen reading; on a tie keep the one with an SSID
            if (seen or 0) < (old[3] or 0) or ((seen or 0) == (old[3] or 0) and not ssid):
                continue
        scan[b] = (ssid, rssi, freq, seen)
    out = []
    for t in sorted(by_t):
        aps = by_t[t]
        bs = tuple(aps)
        seen = [aps[b][3] for b in bs]
        if all(s is None for s in seen):
            age = None
        else:
            age = np.array([t - s if s is not None else np.nan for s in seen], float)
            future += int(np.sum(age < 0))
            age = np.maximum(age, 0.0)
        out.append(WifiScan(stamp_ns=t * 1_000_000, bssid=bs, rssi_dbm=np.array([aps[b][1] for b in bs], float),
                            freq_mhz=np.array([aps[b][2] for b in bs], float),
                            ssid=tuple(aps[b][0] for b in bs), age_ms=age, source=source))
    return out, dup, future


_WAYPOINT_STAMP = re.compile(r"(\d{1,13})\tTYPE_WAYPOINT\t")      # a stamp glued to digits before it: its own 13


def has_truth_span(path: Path) -> bool:
    """Whether a trace file holds ``TYPE_WAYPOINT`` rows at two or more distinct times, a span over
    which the true position interpolates (read until the second; unreadable: False). A walk with one
    waypoint has no truth to score or map with."""
    seen: set[str] = set()
    try:
        with _open_text(Path(path)) as fh:
            for line in fh:
                seen.update(_WAYPOINT_STAMP.findall(line))
                if len(seen) > 1:
                    return True
    except (OSError, EOFError, zlib.error):
        return False
    return False


def split_map_test(trace_ids: list[str]) -> tuple[list[str], list[str]]:
    """The usual interleaved split of one floor: ids sorted; in every block of five the 1st, 3rd
    and 5th build the radio map, the 2nd and 4th are positioned (60/40, interleaved in time)."""
    ids = sorted(trace_ids)
    m = [t for i, t in enumerate(ids) if i % 5 in (0, 2, 4)]
    t = [t for i, t in enumerate(ids) if i % 5 in (1, 3)]
    return m, t


def scans_with_truth(trace: Trace) -> tuple[list[WifiScan], np.ndarray]:
    """The trace's scans inside the waypoint span and their interpolated true positions (N, 2)."""
    if not trace.scans:
        return [], np.zeros((0, 2))
    xy, inside = trace.truth_at([s.stamp_ns for s in trace.scans])
    return [s for s, k in zip(trace.scans, inside) if k], xy[inside]


def heading_offsets(trace: Trace, *, min_step_m: float = 2.0) -> np.ndarray:
    """Map-frame walking direction minus the phone's yaw (rad, wrapped) per pair of consecutive
    waypoints at least ``min_step_m`` apart: atan2 of the surveyed displacement minus the circular mean
    of the rotation vector's yaw between the two waypoints. Their circular mean over a site is the
    ``heading_offset_rad`` that turns Android's (magnetic-north ENU, device-axis) yaw into the walking
    direction in the floor plans' frame."""
    from indoor_loc.imu.quaternion import quat_yaw
    if len(trace.rotvec) == 0 or len(trace.waypoint_t) < 2:
        return np.zeros(0)
    yaw = quat_yaw(trace.quaternions_xyzw()[:, [3, 0, 1, 2]])     # quat_yaw takes (w, x, y, z)
    t = trace.rotvec.t_ns
    out = []
    for i in range(len(trace.waypoint_t) - 1):
        dp = trace.waypoint_xy[i + 1] - trace.waypoint_xy[i]
        m = (t >= trace.waypoint_t[i]) & (t < trace.waypoint_t[i + 1])
        if np.hypot(*dp) < min_step_m or not m.any():
            continue
        dev = np.angle(np.mean(np.exp(1j * yaw[m])))
        out.append(float(np.angle(np.exp(1j * (math.atan2(dp[1], dp[0]) - dev)))))
    return np.array(out)
