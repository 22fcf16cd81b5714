"""Radio map files (save/load), online growth and a few summaries (pure Python/numpy).

On-disk format ``indoor_loc.radiomap`` version 1: a directory holding

``radiomap.yaml`` — the manifest, small and human-readable::

    format: indoor_loc.radiomap
    version: 1
    frame_id: map                  # positions are in this frame (ENU, metres)
    units: {position: m, rssi: dBm, frequency: MHz, stamp: ns}
    counts: {scans: M, aps: A, readings: R}
    bounds_m: {x: [min, max], y: [min, max]}
    sources: {survey: 114, walk07: 12}
    files: {aps: aps.csv, fingerprints: fingerprints.csv}
    created: {utc: ..., by: ..., inputs: [...]}

``aps.csv`` — one row per AP column of the map, in column order: ``column, bssid, ssid, freq_mhz``
(kept separately so the column order and APs never heard at all survive a round trip).

``fingerprints.csv`` — long format, one row per reading, rows of one scan consecutive, scans in map
row order: ``scan_id, stamp_ns, x, y, source, bssid, ssid, rssi_dbm, freq_mhz``. A scan without any
reading is one row with empty ``bssid``/``rssi_dbm`` so it is not lost.

Why CSV and not ``.npz``: the map is sparse (PUTMC: 114 scans x 119 APs, ~22 readings per scan), so
the long format stays modest (~85 bytes a reading with full-precision positions and SSIDs: PUTMC's
2498 readings are 209 kB; 10 000 scans of 25 APs would be ~20 MB and load in a few seconds); it is
diffable, appendable by hand or by other tools (pandas, a spreadsheet, a phone survey app exporting
CSV), carries SSIDs and free-text sources without pickling, and stays readable
when the package is not installed. The manifest's counts are checked on load, so a truncated file
is reported instead of silently giving a smaller map.

Version 2 (written when a map spans several floors or carries reading ages) appends two columns to
``fingerprints.csv``: ``z`` (the scan's floor height, m) and ``age_ms`` (how old the reading was
when its scan was taken — a cached result; empty = unknown), and a ``floors: {name: z_m}`` block to
the manifest. Single-floor maps without ages are still written as version 1; both are read.

A manifest with another ``format`` or a ``version`` this code does not know raises
:class:`~indoor_loc.errors.MapError`; readers of newer versions must bump ``FORMAT_VERSION``.
"""
from __future__ import annotations

import csv
import datetime as _dt
import math
from collections import Counter
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike
import yaml

from indoor_loc.errors import MapError
from indoor_loc.wifi.types import RadioMap, WifiScan

FORMAT_NAME = "indoor_loc.radiomap"
FORMAT_VERSION = 2
READ_VERSIONS = (1, 2)
MANIFEST = "radiomap.yaml"
APS_FILE = "aps.csv"
FINGERPRINTS_FILE = "fingerprints.csv"
FP_COLUMNS = ("scan_id", "stamp_ns", "x", "y", "source", "bssid", "ssid", "rssi_dbm", "freq_mhz")
FP_COLUMNS_V2 = FP_COLUMNS + ("z", "age_ms")
AP_COLUMNS = ("column", "bssid", "ssid", "freq_mhz")


# ----------------------------------------------------------------------------------------------
# checks and summaries
# ----------------------------------------------------------------------------------------------
def check_radiomap(rm: RadioMap) -> None:
    """Raise MapError unless ``rm`` is consistent: positions (M, 2) finite, rssi (M, A) with NaN or
    finite values in [-120, 0] dBm, A unique BSSIDs, per-row arrays of length M, unique scan ids."""
    pos = np.asarray(rm.positions, float)
    m = len(pos)
    if pos.shape != (m, 2):
        raise MapError(f"radio map: positions must have shape (M, 2), got {pos.shape}")
    if not np.all(np.isfinite(pos)):
        raise MapError("radio map: positions contain NaN/inf")
    rss = np.asarray(rm.rssi_dbm, float)
    a = len(rm.bssids)
    if rss.shape != (m, a):
        raise MapError(f"radio map: rssi_dbm must have shape (M, A) = ({m}, {a}), got {rss.shape}")
    heard = ~np.isnan(rss)
    if np.any(np.isinf(rss)) or np.any((rss[heard] < -120.0) | (rss[heard] > 0.0)):
        raise MapError("radio map: rssi_dbm values must be NaN (not heard) or in [-120, 0] dBm")
    if len(set(rm.bssids)) != a:
        dup = [b for b, c in Counter(rm.bssids).items() if c > 1]
        raise MapError(f"radio map: duplicate BSSID columns {dup[:5]}")
    if len(np.asarray(rm.freq_mhz)) != a or len(rm.ssids) != a:
        raise MapError(f"radio map: freq_mhz and ssids need one entry per AP ({a})")
    for name, arr in (("scan_ids", rm.scan_ids), ("stamps_ns", rm.stamps_ns), ("source", rm.source)):
        if len(arr) != m:
            raise MapError(f"radio map: {name} needs one entry per scan ({m}), got {len(arr)}")
    if len(set(int(i) for i in rm.scan_ids)) != m:
        raise MapError("radio map: scan_ids must be unique")
    z = np.asarray(rm.z_m, float)
    if z.shape != (m,) or not np.all(np.isfinite(z)):
        raise MapError(f"radio map: z_m must be ({m},) finite floor heights, got shape {z.shape}")
    if rm.age_ms is not None:
        age = np.asarray(rm.age_ms, float)
        if age.shape != (m, a) or np.any(age[~np.isnan(age)] < 0):
            raise MapError(f"radio map: age_ms must be ({m}, {a}) with NaN or values >= 0 ms")


def radiomap_summary(rm: RadioMap) -> dict[str, Any]:
    """Counts, bounds and per-source scan counts (the manifest's descriptive part)."""
    heard = ~np.isnan(np.asarray(rm.rssi_dbm, float))
    pos = np.asarray(rm.positions, float)
    bounds = ({"x": [float(pos[:, 0].min()), float(pos[:, 0].max())],
               "y": [float(pos[:, 1].min()), float(pos[:, 1].max())]} if len(pos) else {"x": [], "y": []})
    per_scan = heard.sum(axis=1)
    return {
        "counts": {"scans": rm.n_scans, "aps": rm.n_aps, "readings": int(heard.sum())},
        "bounds_m": bounds,
        "aps_per_scan": ({"min": int(per_scan.min()), "mean": round(float(per_scan.mean()), 2),
                          "max": int(per_scan.max())} if len(per_scan) else {}),
        "sources": dict(sorted(Counter(rm.source).items())),
        **({"floors": {str(k): float(v) for k, v in rm.floors.items()}} if rm.floors else {}),
    }


# ----------------------------------------------------------------------------------------------
# save / load
# ----------------------------------------------------------------------------------------------
def _num(v: float) -> str:
    return repr(float(v)) if float(v) != int(v) or abs(v) >= 1e15 else str(int(v))


def save_radiomap(rm: RadioMap, directory: str | Path, *, created_by: str = "indoor_loc",
                  inputs: Sequence[str] = ()) -> Path:
    """Write ``rm`` to ``directory`` (created; existing map files are replaced). Returns the
    directory. ``created_by`` and ``inputs`` go to the manifest's ``created`` block."""
    check_radiomap(rm)
    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
        rss = np.asarray(rm.rssi_dbm, float)
        freq = np.asarray(rm.freq_mhz, float)
        z = np.asarray(rm.z_m, float)
        v2 = bool(rm.floors) or rm.age_ms is not None or bool(np.any(z != 0))
        age = np.asarray(rm.age_ms, float) if rm.age_ms is not None else None
        with open(d / APS_FILE, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(AP_COLUMNS)
            for j, (b, s, f) in enumerate(zip(rm.bssids, rm.ssids, freq)):
                w.writerow([j, b, s, _num(f)])
        with open(d / FINGERPRINTS_FILE, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(FP_COLUMNS_V2 if v2 else FP_COLUMNS)
            for i in range(rm.n_scans):
                head = [int(rm.scan_ids[i]), int(rm.stamps_ns[i]), repr(float(rm.positions[i, 0])),
                        repr(float(rm.positions[i, 1])), rm.source[i]]
                cols = np.flatnonzero(~np.isnan(rss[i]))
                if len(cols) == 0:
                    w.writerow(head + ["", "", "", ""] + ([_num(z[i]), ""] if v2 else []))
                for col in cols:
                    j = int(col)
                    row = head + [rm.bssids[j], rm.ssids[j], _num(rss[i, j]), _num(freq[j])]
                    if v2:
                        a = age[i, j] if age is not None else math.nan
                        row += [_num(z[i]), "" if math.isnan(a) else _num(a)]
                    w.writerow(row)
        manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION if v2 else 1,
            "frame_id": rm.frame_id,
            "units": {"position": "m", "rssi": "dBm", "frequency": "MHz", "stamp": "ns"},
            **radiomap_summary(rm),
            "files": {"aps": APS_FILE, "fingerprints": FINGERPRINTS_FILE},
            "created": {"utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                        "by": created_by, "inputs": [str(x) for x in inputs]},
        }
        (d / MANIFEST).write_text("# WiFi radio map (see indoor_loc/wifi/radiomap.py for the format)\n"
                                  + yaml.safe_dump(manifest, sort_keys=False), encoding="utf-8")
    except OSError as err:
        raise MapError(f"cannot write radio map to {d}: {err}") from err
    return d


def read_manifest(directory: str | Path) -> dict[str, Any]:
    """The checked manifest of a radio map directory (MapError if missing, foreign or too new)."""
    d = Path(directory)
    path = d / MANIFEST
    if not d.is_dir():
        raise MapError(f"radio map directory {d} does not exist")
    try:
        man = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        raise MapError(f"cannot read radio map manifest {path}: {err}") from err
    if not isinstance(man, dict) or man.get("format") != FORMAT_NAME:
        got = man.get("format") if isinstance(man, dict) else type(man).__name__
        raise MapError(f"{path}: not a radio map manifest (format {got!r}, expected {FORMAT_NAME!r})")
    if man.get("version") not in READ_VERSIONS:
        raise MapError(f"{path}: radio map format version {man.get('version')!r} is not supported "
                       f"(this code reads versions {list(READ_VERSIONS)})")
    return man


def _fresh_labels(labels: list[str]) -> list[str]:
    """The same labels as new strings made through one large buffer; empties ``labels`` (unless a label
    holds a NUL, the buffer's separator: then a copy of them as they are). Strings parsed
    among 10^5 rows sit in the rows' freed memory and keep it from the system (the pooled four-floor
    ms_site2 map: about 300 MB of the process's resident memory)."""
    names = sorted(set(labels))
    blob = "\0".join(names)
    if blob.count("\0") != max(len(names) - 1, 0):      # a label holding a NUL (csv reads one): as they are
        return list(labels)
    index = {s: i for i, s in enumerate(names)}
    idx = [index[s] for s in labels]
    labels.clear()
    del names, index
    fresh = blob.split("\0")
    return [fresh[i] for i in idx]


def load_radiomap(directory: str | Path) -> RadioMap:
    """Read a radio map directory written by :func:`save_radiomap` (MapError on any problem)."""
    d = Path(directory)
    man = read_manifest(d)
    files = man.get("files") or {}
    try:
        aps_path = d / files.get("aps", APS_FILE)
        ap_rows: list[dict[str, Any]] = []
        if aps_path.exists():   # maps written before aps.csv existed derive columns from the readings
            with open(aps_path, newline="", encoding="utf-8") as fh:
                ap_rows = list(csv.DictReader(fh))
        with open(d / files.get("fingerprints", FINGERPRINTS_FILE), newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            expected = FP_COLUMNS if man.get("version") == 1 else FP_COLUMNS_V2
            if tuple(reader.fieldnames or ()) != expected:
                raise MapError(f"{d}: fingerprints columns {reader.fieldnames}, expected {list(expected)}")
            fp_rows = list(reader)
    except OSError as err:
        raise MapError(f"cannot read radio map {d}: {err}") from err
    except csv.Error as err:            # e.g. a quote never closed: the rest of the file one huge field
        raise MapError(f"{d}: malformed radio map file: {err}") from err
    try:
        if not ap_rows:
            seen: dict[str, dict[str, Any]] = {}
            for r in fp_rows:
                if r["bssid"] and r["bssid"] not in seen:
                    seen[r["bssid"]] = {"bssid": r["bssid"], "ssid": r["ssid"], "freq_mhz": r["freq_mhz"] or 0}
            ap_rows = list(seen.values())
        bssids = [r["bssid"] for r in ap_rows]
        ssids = [r["ssid"] for r in ap_rows]
        freq = np.array([float(r["freq_mhz"]) for r in ap_rows], float)
        col = {b: j for j, b in enumerate(bssids)}
        ids: list[int] = []
        stamps: list[int] = []
        pos: list[tuple[float, float]] = []
        src: list[str] = []
        zs: list[float] = []
        cells: list[tuple[int, int, float]] = []
        ages: list[float] = []
        for r in fp_rows:
            sid = int(r["scan_id"])
            if not ids or ids[-1] != sid:
                ids.append(sid)
                stamps.append(int(r["stamp_ns"]))
                pos.append((float(r["x"]), float(r["y"])))
                src.append(r["source"])
                zs.append(float(r.get("z") or 0.0))
            if r["bssid"]:
                j = col.get(r["bssid"])
                if j is None:
                    raise MapError(f"{d}: reading of {r['bssid']!r} (scan {sid}) has no column in {APS_FILE}")
                cells.append((len(ids) - 1, j, float(r["rssi_dbm"])))
                ages.append(float(r["age_ms"]) if r.get("age_ms") else math.nan)
    except (KeyError, ValueError, TypeError) as err:
        raise MapError(f"{d}: malformed radio map row: {err}") from err
    del fp_rows
    src = _fresh_labels(src)
    rss = np.full((len(ids), len(bssids)), np.nan)
    age = None
    if cells:
        ii, jj, vv = (np.array(c) for c in zip(*cells))
        rss[ii.astype(int), jj.astype(int)] = vv
        if not all(math.isnan(a) for a in ages):
            age = np.full(rss.shape, np.nan)
            age[ii.astype(int), jj.astype(int)] = ages
    floors = {str(k): float(v) for k, v in (man.get("floors") or {}).items()}
    rm = RadioMap(positions=np.array(pos, float).reshape(-1, 2), bssids=bssids, rssi_dbm=rss, freq_mhz=freq,
                  ssids=ssids, scan_ids=np.array(ids, np.int64), stamps_ns=np.array(stamps, np.int64),
                  source=src, frame_id=str(man.get("frame_id", "map")), z_m=np.array(zs, float),
                  floors=floors, age_ms=age)
    counts = man.get("counts") or {k: man[k] for k in ("scans", "aps") if k in man}
    got = {"scans": rm.n_scans, "aps": rm.n_aps, "readings": len(cells)}
    for key, n in got.items():
        if key in counts and int(counts[key]) != n:
            raise MapError(f"{d}: manifest says {counts[key]} {key}, files hold {n} (truncated or edited?)")
    check_radiomap(rm)
    return rm


# ----------------------------------------------------------------------------------------------
# building and growing
# ----------------------------------------------------------------------------------------------
def empty_radiomap(frame_id: str = "map") -> RadioMap:
    """A map with no scans and no APs (grow it with :func:`add_fingerprints`)."""
    return RadioMap(positions=np.zeros((0, 2)), bssids=[], rssi_dbm=np.zeros((0, 0)), freq_mhz=np.zeros(0),
                    ssids=[], scan_ids=np.zeros(0, np.int64), stamps_ns=np.zeros(0, np.int64), source=[],
                    frame_id=frame_id)


def add_fingerprints(rm: RadioMap, positions: ArrayLike, scans: Sequence[WifiScan],
                     source: str | Iterable[str] = "online", *, scan_ids: Iterable[int] | None = None,
                     z_m: float | ArrayLike = 0.0,
                     floors: dict[str, float] | None = None) -> RadioMap:
    """A new map: ``rm`` plus one fingerprint per scan at ``positions`` (N, 2) m (map frame).

    New BSSIDs become new columns (NaN in the old rows). ``source`` is one label for all or one per
    scan; stamps come from the scans; ``scan_ids`` default to ``max(existing) + 1 ...``. ``rm`` is
    not modified (positioners re-``fit`` on the returned map). ``z_m``: the floor height of the new
    scans (one value or one per scan); ``floors`` names heights (merged into the map's). The scans'
    ``age_ms`` are kept (the map's ``age_ms`` exists as soon as one reading has an age).
    """
    pos = np.asarray(positions, float).reshape(-1, 2)
    scans = list(scans)
    if len(pos) != len(scans):
        raise MapError(f"add_fingerprints: {len(pos)} positions for {len(scans)} scans")
    if not np.all(np.isfinite(pos)):
        raise MapError("add_fingerprints: positions contain NaN/inf")
    srcs = [source] * len(scans) if isinstance(source, str) else list(source)
    if len(srcs) != len(scans):
        raise MapError(f"add_fingerprints: {len(srcs)} source labels for {len(scans)} scans")
    bssids, ssids = list(rm.bssids), list(rm.ssids)
    freq = list(np.asarray(rm.freq_mhz, float))
    col = {b: j for j, b in enumerate(bssids)}
    for sc in scans:
        for b, s, f in zip(sc.bssid, sc.ssid or [""] * len(sc), sc.freq_mhz):
            if b not in col:
                col[b] = len(bssids)
                bssids.append(b)
                ssids.append(s)
                freq.append(float(f))
    m0, n = rm.n_scans, len(scans)
    rss = np.full((m0 + n, len(bssids)), np.nan)
    rss[:m0, :rm.n_aps] = rm.rssi_dbm
    any_age = rm.age_ms is not None or any(sc.age_ms is not None for sc in scans)
    age = np.full(rss.shape, np.nan) if any_age else None
    if age is not None and rm.age_ms is not None:
        age[:m0, :rm.n_aps] = rm.age_ms
    for i, sc in enumerate(scans):
        cs = np.fromiter((col[b] for b in sc.bssid), np.int64, count=len(sc.bssid))
        rss[m0 + i, cs] = sc.rssi_dbm
        if age is not None and sc.age_ms is not None:
            age[m0 + i, cs] = sc.age_ms
    zn = np.broadcast_to(np.asarray(z_m, float), (n,)).astype(float)
    if scan_ids is None:
        start = int(np.max(rm.scan_ids)) + 1 if m0 else 0
        new_ids = np.arange(start, start + n, dtype=np.int64)
    else:
        new_ids = np.asarray(list(scan_ids), np.int64)
    out = RadioMap(positions=np.vstack([np.asarray(rm.positions, float).reshape(-1, 2), pos]), bssids=bssids,
                   rssi_dbm=rss, freq_mhz=np.array(freq, float), ssids=ssids,
                   scan_ids=np.concatenate([np.asarray(rm.scan_ids, np.int64), new_ids]),
                   stamps_ns=np.concatenate([np.asarray(rm.stamps_ns, np.int64),
                                             np.array([s.stamp_ns for s in scans], np.int64)]),
                   source=list(rm.source) + srcs, frame_id=rm.frame_id,
                   z_m=np.concatenate([np.asarray(rm.z_m, float), zn]), floors={**rm.floors, **(floors or {})},
                   age_ms=age)
    check_radiomap(out)
    return out


def map_scans(rm: RadioMap) -> list[WifiScan]:
    """The map's fingerprints as WifiScan objects (stamps from the map; source from the map)."""
    out = []
    rss = np.asarray(rm.rssi_dbm, float)
    for i in range(rm.n_scans):
        cols = np.flatnonzero(~np.isnan(rss[i]))
        out.append(WifiScan(stamp_ns=int(rm.stamps_ns[i]), bssid=tuple(rm.bssids[j] for j in cols),
                            rssi_dbm=rss[i, cols].copy(), freq_mhz=np.asarray(rm.freq_mhz, float)[cols],
                            age_ms=None if rm.age_ms is None else np.asarray(rm.age_ms, float)[i, cols],
                            ssid=tuple(rm.ssids[j] for j in cols), frame_id=rm.frame_id, source=rm.source[i]))
    return out


def interpolate_positions(stamps_ns: ArrayLike, path_stamps_ns: ArrayLike,
                          path_xy: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Positions at ``stamps_ns`` (N,) linearly interpolated along a time-stamped path
    (T,) ns / (T, 2) m. Returns (xy (N, 2), inside (N,) bool); stamps outside the path's time span
    (or any stamp when T == 0) are not inside and get NaN. Path stamps need not be sorted."""
    t = np.asarray(stamps_ns, np.int64)
    pt = np.asarray(path_stamps_ns, np.int64)
    pxy = np.asarray(path_xy, float).reshape(-1, 2)
    out = np.full((len(t), 2), np.nan)
    if len(pt) == 0:
        return out, np.zeros(len(t), bool)
    order = np.argsort(pt, kind="stable")
    pt, pxy = pt[order], pxy[order]
    inside = (t >= pt[0]) & (t <= pt[-1])
    # relative seconds keep float64 exact enough for boot-clock stamps
    tr = (t - pt[0]).astype(float) * 1e-9
    ptr = (pt - pt[0]).astype(float) * 1e-9
    for k in range(2):
        out[inside, k] = np.interp(tr[inside], ptr, pxy[:, k])
    return out, inside


def nominal_spacing_m(rm: RadioMap) -> float:
    """Survey spacing: median distance from a surveyed position to the nearest other surveyed position
    on its floor, m. Scans repeated at one position count once (a survey point scanned ten times is one
    point, not ten at 0 m); NaN when no floor has two distinct positions."""
    p = np.asarray(rm.positions, float)
    z = np.asarray(rm.z_m, float)
    best: list[np.ndarray] = []
    for level in np.unique(z):
        q = np.unique(p[z == level], axis=0)
        for s in range(0, len(q) if len(q) > 1 else 0, 512):
            d = np.linalg.norm(q[s:s + 512, None, :] - q[None, :, :], axis=2)
            d[np.arange(len(d)), np.arange(s, s + len(d))] = np.inf
            best.append(d.min(axis=1))
    return float(np.median(np.concatenate(best))) if best else math.nan
