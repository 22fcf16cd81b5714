"""Radio map files: a versioned, documented, human-readable directory format (pure; no ROS).

Layout of a radio map directory ``DIR/``::

    DIR/radiomap.yaml      manifest: format "indoor_loc.radiomap", version 1, frame_id, units,
                           counts (scans, aps), created_by, free-form notes
    DIR/fingerprints.csv   one row per (scan, AP) reading, long format:
                           scan_id,stamp_ns,x,y,source,bssid,ssid,rssi_dbm,freq_mhz

- ``x``, ``y``: metres in ``frame_id`` (ENU map frame). ``stamp_ns``: 0 for a pre-surveyed map,
  else when the fingerprint was taken. ``source``: "survey" or the user/bag it was learnt from.
- A scan with no AP above threshold still has one row with empty bssid (its position is kept).
- CSV rather than a binary array file: maps are small (10 000 scans x 30 APs = 300 000 rows, a
  few MB), users edit and inspect them with any tool, and diffs stay readable.
Reading rejects unknown formats/versions with :class:`MapError` and says which version it read.
"""
from __future__ import annotations

import csv
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from indoor_loc.errors import MapError
from indoor_loc.wifi.types import RadioMap, WifiScan

FORMAT = "indoor_loc.radiomap"
VERSION = 1
MANIFEST = "radiomap.yaml"
FINGERPRINTS = "fingerprints.csv"
COLUMNS = ("scan_id", "stamp_ns", "x", "y", "source", "bssid", "ssid", "rssi_dbm", "freq_mhz")


def save_radiomap(rm: RadioMap, directory: str | Path, *, notes: str = "", created_by: str = "indoor_loc") -> Path:
    """Write ``rm`` into ``directory`` (created if needed). Returns the directory path."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    manifest = {"format": FORMAT, "version": VERSION, "frame_id": rm.frame_id,
                "units": {"x": "m", "y": "m", "rssi_dbm": "dBm", "freq_mhz": "MHz", "stamp_ns": "ns"},
                "scans": rm.n_scans, "aps": rm.n_aps, "created_by": created_by, "notes": notes}
    with open(d / FINGERPRINTS, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS)
        for i in range(rm.n_scans):
            heard = np.flatnonzero(np.isfinite(rm.rssi_dbm[i]))
            sid, st, (x, y), src = int(rm.scan_ids[i]), int(rm.stamps_ns[i]), rm.positions[i], rm.source[i]
            if len(heard) == 0:
                w.writerow([sid, st, repr(float(x)), repr(float(y)), src, "", "", "", ""])
            for j in heard:
                w.writerow([sid, st, repr(float(x)), repr(float(y)), src, rm.bssids[j], rm.ssids[j],
                            repr(float(rm.rssi_dbm[i, j])), repr(float(rm.freq_mhz[j]))])
    (d / MANIFEST).write_text(yaml.safe_dump(manifest, sort_keys=False))
    return d


def load_radiomap(directory: str | Path) -> RadioMap:
    """Read a radio map directory written by :func:`save_radiomap`."""
    d = Path(directory)
    try:
        manifest = yaml.safe_load((d / MANIFEST).read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise MapError(f"cannot read radio map manifest {d / MANIFEST}: {err}") from err
    if manifest.get("format") != FORMAT:
        raise MapError(f"{d / MANIFEST}: expected format {FORMAT!r}, got {manifest.get('format')!r}")
    if manifest.get("version") != VERSION:
        raise MapError(f"{d / MANIFEST}: radio map version {manifest.get('version')!r} is not supported "
                       f"(this indoor_loc reads version {VERSION})")
    scans: dict[int, dict] = {}
    ap_index: dict[str, int] = {}
    ssids: list[str] = []
    freqs: list[float] = []
    try:
        with open(d / FINGERPRINTS, newline="") as fh:
            r = csv.reader(fh)
            header = next(r)
            if tuple(header) != COLUMNS:
                raise MapError(f"{d / FINGERPRINTS}: expected columns {COLUMNS}, got {tuple(header)}")
            for lineno, row in enumerate(r, start=2):
                if len(row) != len(COLUMNS):
                    raise MapError(f"{d / FINGERPRINTS}:{lineno}: expected {len(COLUMNS)} fields, got {len(row)}")
                sid = int(row[0])
                s = scans.setdefault(sid, {"stamp": int(row[1]), "xy": (float(row[2]), float(row[3])),
                                           "source": row[4], "readings": {}})
                if row[5]:
                    j = ap_index.get(row[5])
                    if j is None:
                        j = ap_index[row[5]] = len(ssids)
                        ssids.append(row[6])
                        freqs.append(float(row[8]) if row[8] else 0.0)
                    s["readings"][j] = float(row[7])
    except OSError as err:
        raise MapError(f"cannot read {d / FINGERPRINTS}: {err}") from err
    except ValueError as err:
        raise MapError(f"{d / FINGERPRINTS}: malformed value: {err}") from err
    ids = sorted(scans)
    rssi = np.full((len(ids), len(ssids)), np.nan)
    for i, sid in enumerate(ids):
        for j, v in scans[sid]["readings"].items():
            rssi[i, j] = v
    positions = np.array([scans[s]["xy"] for s in ids], float).reshape(-1, 2)
    if not np.all(np.isfinite(positions)):
        raise MapError(f"{d}: non-finite fingerprint position")
    return RadioMap(positions=positions, bssids=list(ap_index), rssi_dbm=rssi, freq_mhz=np.array(freqs),
                    ssids=ssids, scan_ids=np.array(ids, np.int64),
                    stamps_ns=np.array([scans[s]["stamp"] for s in ids], np.int64),
                    source=[scans[s]["source"] for s in ids], frame_id=str(manifest.get("frame_id", "map")))


def add_fingerprints(rm: RadioMap, positions: np.ndarray, scans: Sequence[WifiScan], *,
                     source: str | Sequence[str] = "learnt") -> RadioMap:
    """A new map with the scans added as fingerprints at ``positions`` (K, 2) m (the back-end grows
    the map from users' optimised trajectories). New BSSIDs become new columns."""
    positions = np.asarray(positions, float).reshape(-1, 2)
    if len(positions) != len(scans):
        raise MapError(f"add_fingerprints: {len(positions)} positions for {len(scans)} scans")
    if not np.all(np.isfinite(positions)):
        raise MapError("add_fingerprints: non-finite position")
    bssids, ssids, freqs = list(rm.bssids), list(rm.ssids), list(rm.freq_mhz)
    cols = {b: j for j, b in enumerate(bssids)}
    for s in scans:
        for k, b in enumerate(s.bssid):
            if b not in cols:
                cols[b] = len(bssids)
                bssids.append(b)
                ssids.append(s.ssid[k] if k < len(s.ssid) else "")
                freqs.append(float(s.freq_mhz[k]))
    rssi = np.full((rm.n_scans + len(scans), len(bssids)), np.nan)
    rssi[: rm.n_scans, : rm.n_aps] = rm.rssi_dbm
    for i, s in enumerate(scans):
        for b, r in zip(s.bssid, s.rssi_dbm):
            rssi[rm.n_scans + i, cols[b]] = r
    srcs = [source] * len(scans) if isinstance(source, str) else list(source)
    next_id = int(rm.scan_ids.max()) + 1 if rm.n_scans else 0
    return RadioMap(positions=np.vstack([rm.positions, positions]), bssids=bssids, rssi_dbm=rssi,
                    freq_mhz=np.array(freqs), ssids=ssids,
                    scan_ids=np.concatenate([rm.scan_ids, np.arange(next_id, next_id + len(scans))]),
                    stamps_ns=np.concatenate([rm.stamps_ns, np.array([s.stamp_ns for s in scans], np.int64)]),
                    source=list(rm.source) + srcs, frame_id=rm.frame_id)
