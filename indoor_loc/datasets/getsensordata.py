"""GetSensorData logfiles (the IPIN competitions' smartphone tracks), pure Python/numpy, no ROS.

The format (``../shared/formats/getsensordata.md``; every log's own ``%`` header restates it): text,
``;``-separated, one record per line, the first field the record type:

=========================  ===================================================================
``ACCE`` ``GYRO`` ``MAGN``  AppTimestamp s; SensorTimestamp s; x; y; z (m/s², rad/s, µT); accuracy
``PRES``                    AppTimestamp; SensorTimestamp; pressure (mbar = hPa); accuracy
``AHRS``                    AppTimestamp; SensorTimestamp; pitch, roll, yaw (deg); rotation vector
                            x, y, z (the header's Quat(2..4)); accuracy
``WIFI``                    AppTimestamp; SensorTimestamp; SSID; BSSID; frequency MHz; RSS dBm
``BLE4``                    AppTimestamp; ``iBeacon``; MAC; RSSI; tx power; major; minor; UUID —
                            or AppTimestamp; ``Eddystone``; MAC; RSSI; instance id; [telemetry]
``POSI``                    AppTimestamp; counter; latitude; longitude (deg); floor id; building id
``GNSS`` ``LIGH`` ``PROX``  read and counted, not converted (no topic of the message contract)
``HUMI`` ``TEMP`` ``SOUN``
``BLUE`` ``RFID`` ``IMU*``
=========================  ===================================================================

Clocks: AppTimestamp (s since logging started, one reference for every line, jittered by when the app
read the sample) and SensorTimestamp (the sensor's own clock; its differences are the true sampling
intervals; its origin differs from the app clock and between sensors). A sensor's samples are stamped
``SensorTimestamp + offset`` with its offset onto the app clock estimated as the *least* read delay:
``offset = min(App - Sensor)`` over the sensor's samples (the app reads a sample after it is taken, so
``App - Sensor - offset >= 0`` is the read delay). When that does not hold — the read delays of a sensor
spread beyond :data:`MAX_READ_DELAY_S` at the 99th percentile (its clock jumped or drifted) — the
sensor is stamped on the app clock instead and the report says so. Lines need not be sorted: each
stream is sorted (inertial series by SensorTimestamp, the rest by AppTimestamp) and the disorder is
reported; an exact duplicate line is dropped and counted; two samples of a sensor with one
SensorTimestamp keep the first.

WiFi: a scan is the ``WIFI`` lines sharing one AppTimestamp, stamped there. The SensorTimestamp of each
line is that AP's own result time (it can differ within a scan): ``age_ms`` = the scan's newest result
time minus the AP's (a lower bound of its age; 0 where all are equal; unknown beyond an hour, the
contract's bound: a result time of another clock). A BSSID twice in one scan keeps
its newest result. BLE: the ``BLE4`` lines sharing one AppTimestamp form one BLE scan; beacon ids are
``<uuid>-<major>-<minor>`` (iBeacon, lower case), the instance id (Eddystone) or else the MAC; a tx
power of 0 is "not given" (no beacon radiates a 0 dBm at 1 m calibration).

Every record the parser cannot read is counted by reason (``dropped``), never fatal; a log without any
record raises :class:`~indoor_loc.errors.DatasetError`.
"""
from __future__ import annotations

import calendar
import gzip
import math
import re
import zlib
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from indoor_loc.contract import BOUNDS
from indoor_loc.errors import DatasetError
from indoor_loc.wifi.ble import BleScan
from indoor_loc.wifi.types import WifiScan

#: line types converted to the message contract, with the number of values after the two timestamps
SENSOR_TYPES = {"ACCE": 3, "GYRO": 3, "MAGN": 3, "PRES": 1, "AHRS": 6}
#: line types read and counted but not converted (no topic of the message contract)
KNOWN_UNUSED = ("GNSS", "LIGH", "PROX", "HUMI", "TEMP", "SOUN", "BLUE", "RFID", "IMUX", "IMUL", "IMUI")
#: a sensor whose read delays (App - Sensor - offset) exceed this at the 99th percentile has no
#: usable constant offset: it is stamped on the app clock, s
MAX_READ_DELAY_S = 0.5
#: AppTimestamps outside [0, this] s are not a log's (115 days): such a record is dropped (``app_time_range``)
MAX_APP_S = 1e7
#: the bag time of AppTimestamp 0 when the header gives no creation date (2020-01-01T00:00:00Z), ns
DEFAULT_T0_NS = 1_577_836_800_000_000_000
_BSSID_RE = re.compile(r"^[0-9a-f]{2}([:-][0-9a-f]{2}){5}$")
_MONTHS = {m: i for i, m in enumerate(("jan", "feb", "mar", "apr", "may", "jun", "jul", "aug", "sep", "oct",
                                       "nov", "dec"), start=1)}
_DATE_RE = re.compile(r"(?:\w{3}\s+)?(\w{3})\s+(\d{1,2})\s+(\d{1,2}):(\d{2}):(\d{2})\s+(\S+)?\s*(\d{4})")


@dataclass(frozen=True)
class SensorSeries:
    """One sensor's samples sorted by its own clock: ``stamp_s`` (N,) on the app clock (the sensor
    clock plus the estimated offset, see module doc), ``sensor_s`` and ``app_s`` (N,) as logged,
    ``values`` (N, C), ``accuracy`` (N,)."""
    stamp_s: np.ndarray
    sensor_s: np.ndarray
    app_s: np.ndarray
    values: np.ndarray
    accuracy: np.ndarray

    def __len__(self) -> int:
        return len(self.stamp_s)


@dataclass(frozen=True)
class BleReading:
    """One BLE advertisement: app time s, beacon id, ``kind`` (``ibeacon``/``eddystone``), MAC, RSSI
    dBm, tx power dBm (NaN = not given)."""
    app_s: float
    beacon_id: str
    kind: str
    mac: str
    rssi_dbm: float
    tx_power_dbm: float


@dataclass(frozen=True)
class Posi:
    """Reference points: ``app_s`` (K,), ``counter`` (K,), ``lat``/``lon`` (K,) deg, ``floor`` (K,) int,
    ``building`` (K,) int, sorted by time."""
    app_s: np.ndarray
    counter: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    floor: np.ndarray
    building: np.ndarray

    def __len__(self) -> int:
        return len(self.app_s)


@dataclass
class GsdLog:
    """One parsed logfile. ``t0_ns``: the bag time of AppTimestamp 0 (header creation date, else
    :data:`DEFAULT_T0_NS`); ``sensors`` by line type (only those present); ``wifi`` rows
    ``(app_s, sensor_s, ssid, bssid, freq_mhz, rssi_dbm)``; ``counts`` lines per type as read;
    ``oddities`` what was odd, in words; ``clock`` per sensor: offset, read delay and rate figures."""
    path: Path
    header: dict[str, str]
    t0_ns: int
    sensors: dict[str, SensorSeries]
    wifi: list[tuple[float, float, str, str, float, float]]
    ble: list[BleReading]
    posi: Posi
    counts: Counter = field(default_factory=Counter)
    unknown: Counter = field(default_factory=Counter)
    dropped: Counter = field(default_factory=Counter)
    oddities: list[str] = field(default_factory=list)
    clock: dict[str, dict[str, float]] = field(default_factory=dict)

    def ns(self, app_s: float | np.ndarray) -> np.ndarray:
        """Bag stamps (int64 ns) of app-clock seconds (rounded to the microsecond: the logs carry 0.1 ms)."""
        return self.t0_ns + np.round(np.asarray(app_s, float) * 1e6).astype(np.int64) * 1000

    @property
    def duration_s(self) -> float:
        ts = [s.stamp_s[[0, -1]] for s in self.sensors.values() if len(s)]
        ts += [np.array([r[0] for r in self.wifi[:1] + self.wifi[-1:]])] if self.wifi else []
        ts += [self.posi.app_s[[0, -1]]] if len(self.posi) else []
        a = np.concatenate(ts) if ts else np.zeros(0)
        return float(a.max() - a.min()) if len(a) else 0.0


def _open_text(path: Path):
    with open(path, "rb") as fh:
        gz = fh.read(2) == b"\x1f\x8b"
    if gz:
        return gzip.open(path, "rt", encoding="utf-8", errors="replace")
    return open(path, encoding="utf-8", errors="replace")


def _num(text: str, commas: list[int]) -> float:
    """A number; a decimal comma (some locales) is read as a point and counted."""
    try:
        return float(text)
    except ValueError:
        if "," in text:
            v = float(text.replace(",", "."))
            commas[0] += 1
            return v
        raise


def parse_header_date(text: str) -> int | None:
    """Unix ns of a ``Date of creation`` value such as ``Wed May 25 12:42:42 GMT+02:00 2022`` (a zone
    ``GMT±hh:mm`` / ``UTC±hhmm`` is applied; a named zone is taken as UTC); None if unreadable."""
    m = _DATE_RE.search(text)
    if not m:
        return None
    mon = _MONTHS.get(m.group(1).lower()[:3])
    if mon is None:
        return None
    day, hh, mm, ss, year = int(m.group(2)), int(m.group(3)), int(m.group(4)), int(m.group(5)), int(m.group(7))
    try:
        t = calendar.timegm((year, mon, day, hh, mm, ss, 0, 0, 0))
    except (ValueError, OverflowError):
        return None
    z = re.search(r"([+-])(\d{1,2}):?(\d{2})?", m.group(6) or "")
    if z:
        off = int(z.group(2)) * 3600 + int(z.group(3) or 0) * 60
        t -= off if z.group(1) == "+" else -off
    return int(t) * 1_000_000_000


def beacon_id_of(kind: str, mac: str, uuid: str = "", major: str = "", minor: str = "", instance: str = "") -> str:
    """The beacon's id: ``<uuid>-<major>-<minor>`` (iBeacon), the instance id (Eddystone), else the MAC;
    lower case."""
    if kind == "ibeacon" and uuid.strip():
        return f"{uuid.strip()}-{major.strip() or '0'}-{minor.strip() or '0'}".lower()
    if kind == "eddystone" and instance.strip():
        return instance.strip().lower()
    return mac.strip().lower()


def read_log(path: str | Path, *, t0_ns: int | None = None) -> GsdLog:
    """Parse one logfile (plain or gzip-compressed). ``t0_ns`` overrides the header's creation date as
    the bag time of AppTimestamp 0. Raises DatasetError when unreadable or without any record."""
    path = Path(path)
    header: dict[str, str] = {}
    raw: dict[str, list[tuple]] = defaultdict(list)
    wifi: list[tuple[float, float, str, str, float, float]] = []
    ble: list[BleReading] = []
    posi: list[tuple] = []
    counts: Counter = Counter()
    unknown: Counter = Counter()
    dropped: Counter = Counter()
    seen: set[str] = set()
    dup_lines: Counter = Counter()
    commas = [0]
    try:
        with _open_text(path) as fh:
            for line in fh:
                line = line.strip().lstrip("\ufeff")
                if not line:
                    continue
                if line.startswith("%"):
                    k, sep, v = line[1:].partition(":")
                    if sep and k.strip() and "'" not in k:
                        header.setdefault(k.strip(), v.strip())
                    continue
                f = line.split(";")
                typ = f[0].strip()
                counts[typ] += 1
                if line in seen:
                    dup_lines[typ] += 1
                    continue
                seen.add(line)
                try:
                    _record(typ, f, raw, wifi, ble, posi, unknown, dropped, commas)
                except (ValueError, IndexError, OverflowError):
                    dropped[f"malformed_{typ.lower() or 'line'}"] += 1
    except (OSError, EOFError, zlib.error, UnicodeError) as err:
        raise DatasetError(f"cannot read GetSensorData log {path}: {err}") from err
    if not counts:
        raise DatasetError(f"GetSensorData log {path} has no records (only a header, or empty)")
    oddities: list[str] = []
    clock: dict[str, dict[str, float]] = {}
    sensors = {typ: _series(typ, rows, oddities, clock) for typ, rows in raw.items() if rows}
    wifi, ble_out, posi_out = _sorted_rest(wifi, ble, posi, oddities)
    hdr_t0 = parse_header_date(header.get("Date of creation", ""))
    if t0_ns is None:
        if hdr_t0 is None:
            oddities.append(f"no readable 'Date of creation' in the header: AppTimestamp 0 is put at "
                            f"{DEFAULT_T0_NS // 10 ** 9} s Unix time")
        t0_ns = hdr_t0 if hdr_t0 is not None else DEFAULT_T0_NS
    log = GsdLog(path=path, header=header, t0_ns=int(t0_ns), sensors=sensors, wifi=wifi, ble=ble_out,
                 posi=posi_out, counts=counts, unknown=unknown, dropped=dropped, oddities=oddities, clock=clock)
    _report_oddities(log, dup_lines, commas[0])
    return log


def _record(typ: str, f: list[str], raw, wifi, ble, posi, unknown, dropped, commas) -> None:
    """Parse one record into the collections (ValueError/IndexError: malformed, counted by the caller)."""
    n = SENSOR_TYPES.get(typ)
    if typ in SENSOR_TYPES or typ in ("WIFI", "BLE4", "POSI"):
        app = _num(f[1], commas)
        if not 0.0 <= app <= MAX_APP_S:          # NaN fails too
            dropped["app_time_range"] += 1
            return
    if n is not None:
        vals = [x for x in f[1:] if x.strip() != ""]       # MAGN's header shows a doubled ';'
        app, sensor = _num(vals[0], commas), _num(vals[1], commas)
        v = [_num(x, commas) for x in vals[2:2 + n]]
        acc = int(_num(vals[2 + n], commas)) if len(vals) > 2 + n else -1
        if len(v) != n or not all(math.isfinite(x) and abs(x) < 1e12 for x in (app, sensor, *v)):
            raise ValueError(typ)
        raw[typ].append((app, sensor, v, acc))
    elif typ == "WIFI":
        tail = [x.strip() for x in f[1:]]
        while tail and tail[-1] == "":
            tail.pop()
        app, sensor = _num(tail[0], commas), _num(tail[1], commas)
        bssid, freq, rssi = tail[-3].lower().replace("-", ":"), _num(tail[-2], commas), _num(tail[-1], commas)
        ssid = ";".join(tail[2:-3])                          # an SSID may hold ';'
        if len(tail) < 6 or not _BSSID_RE.match(bssid):
            dropped["wifi_bad_bssid"] += 1
            return
        if not (math.isfinite(app) and math.isfinite(rssi) and -120.0 <= rssi <= 0.0):
            dropped["wifi_rssi_range"] += 1
            return
        if not (math.isfinite(freq) and (freq == 0 or 700 <= freq <= 75000)):
            freq = 0.0
            dropped["wifi_frequency_unknown (kept as 0)"] += 1
        wifi.append((app, sensor, ssid, bssid, float(freq), float(rssi)))
    elif typ == "BLE4":
        app = _num(f[1], commas)
        kind = f[2].strip().lower()
        mac, rssi = f[3].strip(), _num(f[4], commas)
        if kind == "ibeacon":
            tx = _num(f[5], commas) if len(f) > 5 and f[5].strip() else math.nan
            bid = beacon_id_of(kind, mac, f[8] if len(f) > 8 else "", f[6] if len(f) > 6 else "",
                               f[7] if len(f) > 7 else "")
        elif kind == "eddystone":
            tx = math.nan
            bid = beacon_id_of(kind, mac, instance=f[5] if len(f) > 5 else "")
        else:
            dropped["ble4_unknown_kind"] += 1
            return
        if not bid or not (math.isfinite(app) and math.isfinite(rssi) and -120.0 <= rssi <= 0.0):
            dropped["ble4_rssi_range"] += 1
            return
        ble.append(BleReading(app, bid, kind, mac.lower(), float(rssi), math.nan if tx == 0 else float(tx)))
    elif typ == "POSI":
        app, cnt = _num(f[1], commas), int(_num(f[2], commas))
        lat, lon = _num(f[3], commas), _num(f[4], commas)
        floor = int(round(_num(f[5], commas)))
        bld = int(round(_num(f[6], commas))) if len(f) > 6 and f[6].strip() else 0
        if not (math.isfinite(app) and -90 <= lat <= 90 and -180 <= lon <= 180):
            dropped["posi_out_of_range"] += 1
            return
        posi.append((app, cnt, lat, lon, floor, bld))
    elif typ not in KNOWN_UNUSED:
        unknown[typ or "(empty type)"] += 1


def _series(typ: str, rows: list[tuple], oddities: list[str], clock: dict) -> SensorSeries:
    """One sensor's rows -> a series sorted by its own clock and stamped on the app clock (module doc)."""
    app = np.array([r[0] for r in rows], float)
    sen = np.array([r[1] for r in rows], float)
    val = np.array([r[2] for r in rows], float)
    acc = np.array([r[3] for r in rows], np.int64)
    if np.any(np.diff(app) < 0):
        oddities.append(f"{typ}: {int(np.sum(np.diff(app) < 0))} lines out of AppTimestamp order (sorted)")
    o = np.lexsort((app, sen))
    app, sen, val, acc = app[o], sen[o], val[o], acc[o]
    keep = np.r_[True, np.diff(sen) != 0]
    if not keep.all():
        oddities.append(f"{typ}: {int((~keep).sum())} samples repeat the previous SensorTimestamp (kept the first)")
        app, sen, val, acc = app[keep], sen[keep], val[keep], acc[keep]
    back = int(np.sum(np.diff(app) < -MAX_READ_DELAY_S))
    if back:
        oddities.append(f"{typ}: in SensorTimestamp order the AppTimestamp goes back more than "
                        f"{MAX_READ_DELAY_S:g} s {back} times (the clocks disagree)")
    delay = app - sen
    offset = float(delay.min())
    delay = delay - offset
    p99 = float(np.percentile(delay, 99))
    dt = np.diff(sen)
    med = float(np.median(dt)) if len(dt) else math.nan
    info = {"samples": float(len(sen)), "offset_s": offset, "read_delay_median_ms": float(np.median(delay)) * 1e3,
            "read_delay_p99_ms": p99 * 1e3, "rate_hz": 1.0 / med if med > 0 else math.nan,
            "app_clock": 0.0}
    if len(dt) and med > 0:
        gaps = dt > 5 * med
        if gaps.any():
            oddities.append(f"{typ}: {int(gaps.sum())} gaps longer than 5 sampling intervals "
                            f"({med * 1e3:.1f} ms), the longest {float(dt.max()):.2f} s")
    if len(sen) > 20:           # drift: the offset of the first and last thirds
        k = len(sen) // 3
        d_first = float((app[:k] - sen[:k]).min())
        d_last = float((app[-k:] - sen[-k:]).min())
        span = float(sen[-k:].mean() - sen[:k].mean())
        if span > 0:
            info["drift_ppm"] = (d_last - d_first) / span * 1e6
            if abs(d_last - d_first) > 0.05:
                oddities.append(f"{typ}: the sensor clock drifts {info['drift_ppm']:.0f} ppm against the app "
                                f"clock ({(d_last - d_first) * 1e3:.0f} ms over {span:.0f} s)")
    if p99 > MAX_READ_DELAY_S:
        oddities.append(f"{typ}: read delays spread to {p99:.2f} s (99th percentile) after the best offset: "
                        f"no constant offset to the app clock, stamped on AppTimestamp instead")
        o = np.argsort(app, kind="stable")
        app, sen, val, acc = app[o], sen[o], val[o], acc[o]
        stamp = app.copy()
        info["app_clock"] = 1.0
    else:
        stamp = sen + offset
    clock[typ] = info
    return SensorSeries(stamp_s=stamp, sensor_s=sen, app_s=app, values=val.reshape(len(sen), -1), accuracy=acc)


def _sorted_rest(wifi, ble, posi, oddities):
    for name, rows, key in (("WIFI", wifi, lambda r: r[0]), ("BLE4", ble, lambda r: r.app_s),
                            ("POSI", posi, lambda r: r[0])):
        t = [key(r) for r in rows]
        back = sum(1 for a, b in zip(t, t[1:]) if b < a)
        if back:
            oddities.append(f"{name}: {back} lines out of AppTimestamp order (sorted)")
    wifi = sorted(wifi, key=lambda r: r[0])
    ble = sorted(ble, key=lambda r: r.app_s)
    posi = sorted(posi, key=lambda r: r[0])
    cols = list(zip(*posi)) if posi else [()] * 6
    p = Posi(app_s=np.array(cols[0], float), counter=np.array(cols[1], np.int64), lat=np.array(cols[2], float),
             lon=np.array(cols[3], float), floor=np.array(cols[4], np.int64), building=np.array(cols[5], np.int64))
    if len(p) > 1 and np.any(np.diff(p.app_s) == 0):
        keep = np.r_[True, np.diff(p.app_s) != 0]
        oddities.append(f"POSI: {int((~keep).sum())} reference points share a time with the previous one "
                        f"(kept the first)")
        p = Posi(*(a[keep] for a in (p.app_s, p.counter, p.lat, p.lon, p.floor, p.building)))
    if len(p) > 1 and np.any(np.diff(p.counter) <= 0):
        oddities.append("POSI: the counter does not increase with time")
    if len(set(p.building.tolist())) > 1:
        oddities.append(f"POSI: several building ids {sorted(set(p.building.tolist()))}")
    return wifi, ble, p


def _report_oddities(log: GsdLog, dup_lines: Counter, commas: int) -> None:
    odd = log.oddities
    if dup_lines:
        odd.append("duplicated lines dropped: " + ", ".join(f"{k} {v}" for k, v in sorted(dup_lines.items())))
    if commas:
        odd.append(f"{commas} numbers written with a decimal comma (read as a point)")
    for k, v in sorted(log.dropped.items()):
        odd.append(f"{v} records dropped: {k}")
    missing = [t for t in ("ACCE", "GYRO", "MAGN", "PRES") if t not in log.sensors]
    if missing:
        odd.append("sensors missing: " + ", ".join(missing))
    if not log.wifi:
        odd.append("no WIFI lines")
    if len(log.posi) == 0:
        odd.append("no POSI reference points: no ground truth, no radio-map contribution")
    elif len(log.posi) == 1:
        odd.append("one POSI reference point: no span to interpolate positions over")
    if log.unknown:
        odd.append("unknown line types: " + ", ".join(f"{k} {v}" for k, v in sorted(log.unknown.items())))


def wifi_scans(log: GsdLog, *, source: str = "getsensordata") -> tuple[list[WifiScan], int]:
    """The log's WiFi scans (module doc), stamped in bag ns, and the number of BSSIDs dropped as
    repeated within a scan."""
    by_t: dict[float, dict[str, tuple]] = {}
    dup = 0
    for app, sensor, ssid, bssid, freq, rssi in log.wifi:
        scan = by_t.setdefault(app, {})
        old = scan.get(bssid)
        if old is not None:
            dup += 1
            if old[0] >= sensor:
                continue
        scan[bssid] = (sensor, ssid, freq, rssi)
    out = []
    for app in sorted(by_t):
        aps = by_t[app]
        bs = tuple(aps)
        sen = np.array([aps[b][0] for b in bs], float)
        age = np.round((sen.max() - sen) * 1e3, 3)
        age[~(age <= BOUNDS["age"].hi)] = np.nan          # a result time of another clock: age unknown
        out.append(WifiScan(stamp_ns=int(log.ns(app)), bssid=bs, rssi_dbm=np.array([aps[b][3] for b in bs], float),
                            freq_mhz=np.array([aps[b][2] for b in bs], float), ssid=tuple(aps[b][1] for b in bs),
                            age_ms=age, source=source))
    return out, dup


def ble_scans(log: GsdLog, *, source: str = "getsensordata") -> list[BleScan]:
    """The log's BLE scans: the ``BLE4`` readings sharing one AppTimestamp (a beacon twice keeps the last)."""
    by_t: dict[float, dict[str, BleReading]] = {}
    for r in log.ble:
        by_t.setdefault(r.app_s, {})[r.beacon_id] = r
    out = []
    for app in sorted(by_t):
        rs = list(by_t[app].values())
        out.append(BleScan(stamp_ns=int(log.ns(app)), beacon_id=tuple(r.beacon_id for r in rs),
                           rssi_dbm=np.array([r.rssi_dbm for r in rs], float),
                           tx_power_dbm=np.array([r.tx_power_dbm for r in rs], float),
                           name=tuple(r.mac for r in rs), source=source))
    return out


def rotation_quaternions(ahrs: SensorSeries) -> np.ndarray:
    """(N, 4) unit quaternions (x, y, z, w) device -> ENU of ``AHRS`` samples: the logged rotation
    vector (x, y, z) and ``w = sqrt(1 - |v|^2)`` (Android's rotation vector convention)."""
    v = ahrs.values[:, 3:6]
    w = np.sqrt(np.clip(1.0 - (v * v).sum(axis=1), 0.0, 1.0))
    q = np.column_stack([v, w])
    return q / np.linalg.norm(q, axis=1, keepdims=True)
