"""Write GetSensorData logfiles from bags in the message contract (``indoor-loc bag to-getsensordata``,
``indoor-loc sim --format getsensordata``), so every line type the importer reads is exercised.

One log per user namespace of the bag: ``ACCE`` + ``GYRO`` (``imu/data_raw``), ``MAGN`` (``imu/mag``, T ->
µT), ``AHRS`` (``imu/data`` orientation: pitch, roll, yaw in degrees and the rotation vector x, y, z),
``PRES`` (``baro/pressure``, Pa -> hPa), ``WIFI`` (``wifi/scan``, one line per AP), ``BLE4`` (``ble/scan``:
``iBeacon`` lines for ids of the form ``<uuid>-<major>-<minor>``, ``Eddystone`` with the id as instance
otherwise) and ``POSI`` (``ground_truth`` poses — or a truth CSV with a ``floor`` column — as latitude,
longitude and floor id: ENU at the given origin, floor = round(z / storey height)).

Clocks as the app writes them: AppTimestamp = stamp − t0 (t0 = the user's first stamp, whole seconds,
written as the header's ``Date of creation`` in UTC); SensorTimestamp = AppTimestamp + a boot offset
(:data:`BOOT_OFFSET_S`, the sensors' clock since boot). A WiFi line's SensorTimestamp is its result time:
the scan's minus the AP's ``age_ms``. Precision is the format's: 4 decimals of seconds (0.1 ms), 5 of the
inertial values, 4 of hPa (0.01 Pa), 9 of degrees (0.1 mm).
"""
from __future__ import annotations

import csv
import datetime as dt
import math
import re
from pathlib import Path
from typing import IO, Any

import numpy as np

from indoor_loc.datasets.geodesy import enu_to_geodetic

#: SensorTimestamp - AppTimestamp of every written sensor line, s (a phone booted ~52 min before logging)
BOOT_OFFSET_S = 3125.0
_IBEACON = re.compile(r"^([0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12})-(\d+)-(\d+)$")

HEADER = """% LogFile created by the 'GetSensorData' App for Android.
% Date of creation: {date}
% Written by indoor_loc (indoor-loc bag to-getsensordata) from {source}
% Version 2.21 July 2021 (format)
%
% Phone used for this logfile:
% Manufacturer:            	indoor_loc
% Model:                   	{model}
%
% LogFile Data format:
% Accelerometer data: 	'ACCE;AppTimestamp(s);SensorTimestamp(s);Acc_X(m/s^2);Acc_Y(m/s^2);Acc_Z(m/s^2);Accuracy(integer)'
% Gyroscope data:     	'GYRO;AppTimestamp(s);SensorTimestamp(s);Gyr_X(rad/s);Gyr_Y(rad/s);Gyr_Z(rad/s);Accuracy(integer)'
% Magnetometer data:  	'MAGN;AppTimestamp(s);SensorTimestamp(s);Mag_X(uT);;Mag_Y(uT);Mag_Z(uT);Accuracy(integer)'
% Pressure data:      	'PRES;AppTimestamp(s);SensorTimestamp(s);Pres(mbar);Accuracy(integer)'
% Orientation data:   	'AHRS;AppTimestamp(s);SensorTimestamp(s);PitchX(deg);RollY(deg);YawZ(deg);Quat(2);Quat(3);Quat(4);Accuracy(int)'
% WIFI data:          	'WIFI;AppTimestamp(s);SensorTimeStamp(s);Name_SSID;MAC_BSSID;Frequency;RSS(dBm);'
% BLE 4.0 data:       	'BLE4;AppTimestamp(s);iBeacon;MAC;RSSI(dBm);Power;MajorID;MinorID;UUID'
% BLE 4.0 data:       	'BLE4;AppTimestamp(s);Eddystone;MAC;RSSI(dBm);instanceID;OptionalTelemetry[voltaje;temperature;uptime;count]
% POSI Reference:    		'POSI;Timestamp(s);Counter;Latitude(degrees); Longitude(degrees);floor ID(0,1,2..4);Building ID(0,1,2..3);'
%
"""


def header_date(t0_s: int) -> str:
    """``Thu Jan 01 00:00:00 GMT+00:00 2026``-style text of a Unix time (UTC), as the app writes it."""
    t = dt.datetime.fromtimestamp(t0_s, tz=dt.timezone.utc)
    return t.strftime("%a %b %d %H:%M:%S GMT+00:00 %Y")


def _euler_deg(q: np.ndarray) -> tuple[float, float, float]:
    """(pitch about x, roll about y, yaw about z) in degrees of a quaternion (x, y, z, w), Android's
    getOrientation order (azimuth about z, pitch about x, roll about y) in the ENU frame."""
    from scipy.spatial.transform import Rotation
    r = Rotation.from_quat(q)
    yaw, pitch, roll = r.as_euler("ZXY", degrees=True)
    return float(pitch), float(roll), float(yaw)


class LogWriter:
    """Collects one user's records (AppTimestamp, type order, text) and writes them sorted by time."""

    def __init__(self, t0_ns: int) -> None:
        self.t0_ns = int(t0_ns)
        self.records: list[tuple[float, int, int, str]] = []
        self.counts: dict[str, int] = {}

    def app(self, stamp_ns: int) -> float:
        return (int(stamp_ns) - self.t0_ns) * 1e-9

    def add(self, app_s: float, typ: str, text: str, order: int = 0) -> None:
        self.records.append((round(app_s, 4), order, len(self.records), text))
        self.counts[typ] = self.counts.get(typ, 0) + 1

    def sensor(self, typ: str, stamp_ns: int, values: list[float], fmt: str = "{:.5f}", accuracy: int = 3) -> None:
        a = self.app(stamp_ns)
        vals = ";".join(fmt.format(v) for v in values)
        self.add(a, typ, f"{typ};{a:.4f};{a + BOOT_OFFSET_S:.4f};{vals};{accuracy}")

    def wifi(self, stamp_ns: int, bssid: str, ssid: str, freq_mhz: float, rssi_dbm: float, age_ms: float) -> None:
        a = self.app(stamp_ns)
        result = a + BOOT_OFFSET_S - (age_ms if math.isfinite(age_ms) else 0.0) * 1e-3
        ssid = ssid.replace("\n", " ")
        self.add(a, "WIFI", f"WIFI;{a:.4f};{result:.4f};{ssid};{bssid};"
                             f"{int(round(freq_mhz))};{int(round(rssi_dbm))}", 1)

    def ble(self, stamp_ns: int, beacon_id: str, mac: str, rssi_dbm: float, tx_power_dbm: float) -> None:
        a = self.app(stamp_ns)
        m = _IBEACON.match(beacon_id)
        tx = 0 if not math.isfinite(tx_power_dbm) else int(round(tx_power_dbm))
        mac = mac or "00:00:00:00:00:00"
        if m:
            self.add(a, "BLE4", f"BLE4;{a:.4f};iBeacon;{mac};{int(round(rssi_dbm))};{tx};{m.group(2)};{m.group(3)};"
                                f"{m.group(1).upper()}", 2)
        else:
            self.add(a, "BLE4", f"BLE4;{a:.4f};Eddystone;{mac};{int(round(rssi_dbm))};{beacon_id}", 2)

    def posi(self, stamp_ns: int, counter: int, lat: float, lon: float, floor: int, building: int = 0) -> None:
        a = self.app(stamp_ns)
        self.add(a, "POSI", f"POSI;{a:.4f};{counter};{lat:.12f};{lon:.12f};{floor};{building}", 3)

    def write(self, fh: IO[str], *, source: str, model: str) -> None:
        fh.write(HEADER.format(date=header_date(self.t0_ns // 1_000_000_000), source=source, model=model))
        for _, _, _, text in sorted(self.records):
            fh.write(text + "\n")


def _user_of(topic: str, rel: str) -> str | None:
    from indoor_loc.contract import namespace_of_topic
    ns = namespace_of_topic(topic, rel)
    return None if ns is None else ns.strip("/")


_RELS = ("imu/data_raw", "imu/mag", "imu/data", "baro/pressure", "wifi/scan", "ble/scan", "ground_truth")


def bag_to_logs(bag: str | Path, out_dir: str | Path, *, origin: tuple[float, float], storey_height_m: float,
                truth_dir: str | Path | None = None, posi_period_s: float = 0.0) -> dict[str, dict[str, Any]]:
    """Write one ``<user>.txt`` per user namespace of ``bag`` into ``out_dir``; returns per user the lines
    per type and the file. ``truth_dir``: ``<user>.csv`` files (``stamp_ns, x, y, z, floor, ...``, as
    ``indoor-loc sim`` writes) give the ``POSI`` points instead of ``ground_truth``; ``posi_period_s``:
    at most one ``POSI`` per this many seconds (0 = every pose)."""
    from indoor_loc.bag.reader import read_bag
    from msg_adapters.ble_scan import ble_from_msg
    from msg_adapters.pressure import pressure_from_msg
    from msg_adapters.imu import imu_from_msg, mag_from_msg
    from msg_adapters.wifi_scan import scan_from_msg

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    users: dict[str, LogWriter] = {}
    truth: dict[str, list[tuple[int, float, float, float]]] = {}
    for m in read_bag(bag):
        rel = next((r for r in _RELS if _user_of(m.topic, r) is not None), None)
        if rel is None:
            continue
        user = _user_of(m.topic, rel) or "user"
        if rel == "ground_truth":
            truth[user] = [(int(p.header.stamp.sec) * 1_000_000_000 + int(p.header.stamp.nanosec),
                            p.pose.position.x, p.pose.position.y, p.pose.position.z) for p in m.msg.poses]
            continue
        w = users.get(user)
        if w is None:
            w = users[user] = LogWriter((m.stamp_ns // 1_000_000_000) * 1_000_000_000)
        if rel in ("imu/data_raw", "imu/data"):
            s = imu_from_msg(m.msg)
            if rel == "imu/data":
                if s.quat_xyzw is None:
                    continue
                q = np.asarray(s.quat_xyzw, float)
                q = q * (1.0 if q[3] >= 0 else -1.0)        # the rotation vector form has w >= 0
                w.sensor("AHRS", s.stamp_ns, [*_euler_deg(q), *q[:3].tolist()], fmt="{:.6f}")
                continue
            w.sensor("ACCE", s.stamp_ns, list(map(float, s.acc)))
            if s.gyro is not None:
                w.sensor("GYRO", s.stamp_ns, list(map(float, s.gyro)), accuracy=0)
        elif rel == "imu/mag":
            t, field_t = mag_from_msg(m.msg)
            w.sensor("MAGN", t, [float(v) * 1e6 for v in field_t], fmt="{:.4f}")
        elif rel == "baro/pressure":
            t, pa, _, _ = pressure_from_msg(m.msg)
            w.sensor("PRES", t, [pa / 100.0], fmt="{:.4f}")
        elif rel == "wifi/scan":
            sc = scan_from_msg(m.msg)
            ages = sc.age_ms if sc.age_ms is not None else np.zeros(len(sc))
            for i, b in enumerate(sc.bssid):
                w.wifi(sc.stamp_ns, b, sc.ssid[i] if sc.ssid else "", float(sc.freq_mhz[i]), float(sc.rssi_dbm[i]),
                       float(ages[i]))
        elif rel == "ble/scan":
            bs = ble_from_msg(m.msg)
            age = bs.age_ms if bs.age_ms is not None else np.zeros(len(bs))
            for i, b in enumerate(bs.beacon_id):
                at = bs.stamp_ns - int(round((age[i] if math.isfinite(age[i]) else 0.0) * 1e6))
                w.ble(at, b, bs.name[i] if bs.name else "", float(bs.rssi_dbm[i]), float(bs.tx_power_dbm[i]))
    if truth_dir is not None:
        for user in users:
            f = Path(truth_dir) / f"{user}.csv"
            if f.exists():
                with open(f, newline="") as fh:
                    truth[user] = [(int(r["stamp_ns"]), float(r["x"]), float(r["y"]),
                                    float(r["floor"]) * storey_height_m) for r in csv.DictReader(fh)]
    result: dict[str, dict[str, Any]] = {}
    for user, w in users.items():
        pts = sorted(truth.get(user, []))
        last = -math.inf
        k = 0
        if pts:
            lat, lon = enu_to_geodetic(np.array([[p[1], p[2]] for p in pts]), *origin)
            for (t, _x, _y, z), la, lo in zip(pts, lat.tolist(), lon.tolist()):
                if t < w.t0_ns or (t - last) * 1e-9 < posi_period_s - 1e-9:
                    continue
                k += 1
                last = t
                w.posi(t, k, la, lo, int(round(z / storey_height_m)))
        path = out / f"{user or 'user'}.txt"
        with open(path, "w", encoding="utf-8") as fh:
            w.write(fh, source=str(bag), model=f"simulated phone of {user}")
        result[user] = {"file": path, "lines": dict(w.counts)}
    return result
