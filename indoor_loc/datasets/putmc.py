"""PUTMC dataset (Nowicki & Skrzypczyński, Sensors 2019; GPLv3): pure parsing, no ROS.

Layout (see ``datasets/README.md`` beside the data)::

    GT/N/nodes.map                          ground-truth route of walk N (small graph, image frame)
    PUTMC_Floor3_Xperia_map/positions.map   114 survey scan positions ``id x y``
    PUTMC_Floor3_Xperia_map/wifi.map        114 survey scans (``-1 locId nAP`` blocks)
    PUTMC_Floor3_Xperia_trajs/xperia_trajN[_JW]/{acc,orient,wifi,positions}.map   walk N

Frames. The files use an image-style frame: metres, x right, y *down* over ``map.png`` (3049×1049
px, origin top-left, 28.50518 px/m). It is mirrored with respect to ENU (REP 103). Everything
returned here is in the package's ENU map frame::

    x = x_img_m,   y = PUTMC_Y0 - y_img_m,   PUTMC_Y0 = 1049 / 28.50518 = 36.8004 m

so ``map.png`` has its bottom-left corner at map (0, 0), like a nav2 map, and a left turn in the
world is a counter-clockwise turn in the map frame (the dataset authors' code, which works in the
image frame, negates the phone's yaw changes instead).

Orientation. ``orient.map`` holds the Android rotation-vector quaternion (x, y, z, w): the rotation
device -> local ENU (x east, y magnetic north, z up). It is already right-handed ENU, so the mirror
above needs no change of handedness; the only difference to the map frame is a constant rotation
about z (the building's orientation w.r.t. magnetic north, lumped together with how the phone was
held). :func:`estimate_map_yaw` measures it from the walks' true scan positions;
:data:`PUTMC_MAP_YAW_RAD` is that estimate over all 24 walks, and :func:`to_map_quat` applies it so
that the yaw (ZYX, CCW from map x) of the rotated quaternion is the walking direction in the map
frame (``heading_offset_rad = 0``). Indoors the magnetic heading wanders: per-walk estimates
spread over about ±50° around the pooled value.

Time. acc, orient and the WiFi scan headers share one integer-nanosecond clock since device boot
(it restarts between recording sessions); it is kept as the time base, unchanged, so bag stamps
equal the file stamps. The per-AP timestamps of the WiFi lines are µs on another clock and are
ignored. 19 recordings begin with a few stale samples then a long gap before the walk; they are
dropped by default (``keep_stale=True`` keeps them) and reported as oddities.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from indoor_loc.datasets.text_table import read_table, read_text
from indoor_loc.errors import DatasetError
from indoor_loc.imu import quaternion
from indoor_loc.wifi.types import RadioMap, WifiScan

PUTMC_SCALE_PX_PER_M = 28.50518            #: ``scale.map`` at the dataset root, px per metre
PUTMC_IMAGE_SIZE_PX = (3049, 1049)         #: ``map.png`` width, height in pixels
PUTMC_Y0 = 1049 / 28.50518                 #: m; y_enu = PUTMC_Y0 - y_img
#: Map-frame yaw minus Android-ENU yaw of the walking direction, rad: circular mean over all 24
#: walks of (direction between consecutive true scan positions >= 2 m apart) - (circular mean of
#: the device yaw between those scans). Re-derive with :func:`estimate_map_yaw`.
PUTMC_MAP_YAW_RAD = math.radians(7.8)
START_GAP_S = 5.0          #: a gap longer than this, s, ends the stale samples at a recording's start
DROPOUT_S = 0.05           #: a gap longer than this, s (~10 nominal periods), inside a walk is reported
OFF_ROUTE_M = 1.5          #: a true scan position farther than this from the GT route, m, is reported
HEADING_UNRELIABLE_RAD = 1.0   #: headingAcc at or above this, rad, is reported (Android gives π)

TRAJ_DIR = "PUTMC_Floor3_Xperia_trajs"
MAP_DIR = "PUTMC_Floor3_Xperia_map"
_FOLDER_RE = re.compile(r"^xperia_traj(\d+)(_JW)?$")
_BSSID_RE = re.compile(r"[0-9a-f]{2}(:[0-9a-f]{2}){5}")
_BSSIDS_RE = re.compile(r"(?:[0-9a-f]{2}(?::[0-9a-f]{2}){5}\n)*")     #: ``_BSSID_RE`` per line


class Oddity(NamedTuple):
    """Something unusual in the data: ``walk`` (0 = survey map / whole dataset), a short stable
    ``kind`` slug, a human-readable ``detail``, and ``count`` of affected items."""
    walk: int
    kind: str
    detail: str
    count: int = 1


@dataclass(frozen=True)
class Route:
    """Ground-truth route of one walk: node_xy (K, 2) m ENU map frame, links (L, 2) int (i < j)."""
    walk: int
    node_xy: np.ndarray
    links: np.ndarray

    @property
    def segments(self) -> np.ndarray:
        """(L, 2, 2) m: segment l runs from segments[l, 0] to segments[l, 1]."""
        return self.node_xy[self.links]

    @property
    def length_m(self) -> float:
        s = self.segments
        return float(np.linalg.norm(s[:, 1] - s[:, 0], axis=1).sum())


@dataclass
class Walk:
    """One walk, ENU map frame, device-boot clock (int ns).

    acc_t (N,) int64 ns, acc (N, 3) m/s^2 incl. gravity, device frame;
    ori_t (M,) int64 ns, quat_xyzw (M, 4) Android rotation vector device -> ENU (as in the file,
    see :func:`to_map_quat`), heading_acc (M,) rad;
    scans: WiFi scans (header stamps), scan_xy (S, 2) m their true positions, scan_idx (S,) int;
    raw_counts: lines/scans in the files; dropped: samples dropped as stale per stream;
    oddities: what the parser noticed.
    """
    walk: int
    folder: str
    acc_t: np.ndarray
    acc: np.ndarray
    ori_t: np.ndarray
    quat_xyzw: np.ndarray
    heading_acc: np.ndarray
    scans: list[WifiScan]
    scan_xy: np.ndarray
    scan_idx: np.ndarray
    raw_counts: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    oddities: list[Oddity] = field(default_factory=list)

    @property
    def name(self) -> str:
        """``walkNN`` (two digits): the namespace / user name of this walk."""
        return walk_name(self.walk)

    @property
    def start_ns(self) -> int:
        firsts = [int(a[0]) for a in (self.acc_t, self.ori_t) if len(a)]
        firsts += [self.scans[0].stamp_ns] if self.scans else []
        return min(firsts)

    @property
    def end_ns(self) -> int:
        lasts = [int(a[-1]) for a in (self.acc_t, self.ori_t) if len(a)]
        lasts += [self.scans[-1].stamp_ns] if self.scans else []
        return max(lasts)

    @property
    def scan_t(self) -> np.ndarray:
        return np.array([s.stamp_ns for s in self.scans], dtype=np.int64)


def walk_name(walk: int) -> str:
    return f"walk{int(walk):02d}"


def image_to_enu(xy_img) -> np.ndarray:
    """Image-frame metres (x right, y down) -> ENU map frame, (N, 2) -> (N, 2)."""
    p = np.asarray(xy_img, dtype=np.float64).reshape(-1, 2).copy()
    p[:, 1] = PUTMC_Y0 - p[:, 1]
    return p


def map_extent() -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) m of ``map.png`` in the map frame (for ``imshow(extent=...)``)."""
    w, h = PUTMC_IMAGE_SIZE_PX
    return 0.0, w / PUTMC_SCALE_PX_PER_M, 0.0, h / PUTMC_SCALE_PX_PER_M


# ---------------------------------------------------------------------------------------------
# low-level readers
# ---------------------------------------------------------------------------------------------
def read_wifi_blocks(path: Path) -> list[tuple[list[str], list[list[str]]]]:
    """WiFi blocks: (header tokens, AP lines split at TAB: BSSID, SSID, RSSI, freq, apTimestamp)."""
    blocks: list[tuple[list[str], list[list[str]]]] = []
    for i, ln in enumerate(read_text(path).splitlines()):
        if not ln.strip():
            continue
        if "\t" in ln:
            if not blocks:
                raise DatasetError(f"{path}: line {i + 1}: AP line before any scan header")
            cols = ln.split("\t")
            if len(cols) != 5:
                raise DatasetError(f"{path}: line {i + 1}: expected 5 TAB-separated fields, got {len(cols)}")
            blocks[-1][1].append(cols)
        else:
            head = ln.split()
            if len(head) != 3:
                raise DatasetError(f"{path}: line {i + 1}: expected a 3-field scan header, got {ln!r}")
            blocks.append((head, []))
    for head, aps in blocks:
        if int(head[2]) != len(aps):
            raise DatasetError(f"{path}: scan {head[:2]} announces {head[2]} APs, has {len(aps)}")
    return blocks


def _scan_from_block(stamp_ns: int, aps: list[list[str]], frame_id: str, source: str,
                     where: str, oddities: list[Oddity], walk: int) -> WifiScan:
    seen: dict[str, int] = {}
    bssid, ssid, rssi, freq = [], [], [], []
    for cols in aps:
        b = cols[0].strip().lower().replace("-", ":")
        if not _BSSID_RE.fullmatch(b):
            raise DatasetError(f"{where}: bad BSSID {cols[0]!r}")
        try:
            r, f = float(cols[2]), float(cols[3])
        except ValueError as err:
            raise DatasetError(f"{where}: AP {b}: RSSI/frequency not numbers: {cols[2:4]}") from err
        if b in seen:      # keep the stronger reading (none in the published data)
            oddities.append(Oddity(walk, "duplicate_bssid", f"{where}: {b} twice, kept the stronger"))
            j = seen[b]
            rssi[j] = max(rssi[j], r)
            continue
        seen[b] = len(bssid)
        bssid.append(b)
        ssid.append(cols[1])
        rssi.append(r)
        freq.append(f)
    return WifiScan(stamp_ns=int(stamp_ns), bssid=tuple(bssid), rssi_dbm=np.array(rssi), freq_mhz=np.array(freq),
                    ssid=tuple(ssid), frame_id=frame_id, source=source)


def _scans_from_blocks(blocks: list[tuple[list[str], list[list[str]]]], stamps: list[int], frame_id: str,
                       source: str, wheres: list[str], oddities: list[Oddity], walk: int) -> list[WifiScan] | None:
    """:func:`_scan_from_block` of every block, the BSSIDs checked by one regular expression over all
    of them and the numbers converted in one pass; a block with a repeated BSSID goes through
    :func:`_scan_from_block` (its entry of ``wheres`` names it). ``None`` if a BSSID or a number is
    malformed: the caller then takes the blocks one at a time, which names the first fault."""
    rows = [cols for _, aps in blocks for cols in aps]
    bssid = [cols[0].strip().lower().replace("-", ":") for cols in rows]
    if rows and not _BSSIDS_RE.fullmatch("\n".join(bssid) + "\n"):
        return None
    try:
        rssi = list(map(float, [cols[2] for cols in rows]))
        freq = list(map(float, [cols[3] for cols in rows]))
    except ValueError:
        return None
    scans, s = [], 0
    for (_, aps), stamp, where in zip(blocks, stamps, wheres):
        e = s + len(aps)
        ids = bssid[s:e]
        if len(set(ids)) < len(ids):
            scans.append(_scan_from_block(stamp, aps, frame_id, source, where, oddities, walk))
        else:
            scans.append(WifiScan(stamp_ns=stamp, bssid=tuple(ids), rssi_dbm=np.array(rssi[s:e]),
                                  freq_mhz=np.array(freq[s:e]), ssid=tuple(cols[1] for cols in aps),
                                  frame_id=frame_id, source=source))
        s = e
    return scans


# ---------------------------------------------------------------------------------------------
# ground truth, survey map
# ---------------------------------------------------------------------------------------------
def read_route(path: Path, walk: int = 0, oddities: list[Oddity] | None = None) -> Route:
    """``GT/N/nodes.map``: K, then per node ``x y`` / neighbour count / neighbour indices.
    Links are the pairs (i, j), j > i, deduplicated; self-loops are dropped (and reported)."""
    tok = read_text(path).split()
    try:
        k = int(tok[0])
        pos = 1
        xy = np.empty((k, 2))
        links: set[tuple[int, int]] = set()
        loops: set[int] = set()
        for i in range(k):
            xy[i] = float(tok[pos]), float(tok[pos + 1])
            n = int(tok[pos + 2])
            nb = [int(t) for t in tok[pos + 3: pos + 3 + n]]
            if len(nb) != n:
                raise DatasetError(f"{path}: node {i}: truncated neighbour list")
            pos += 3 + n
            for j in nb:
                if not 0 <= j < k:
                    raise DatasetError(f"{path}: node {i}: neighbour {j} outside [0, {k})")
                if j == i:
                    loops.add(i)
                    continue
                links.add((min(i, j), max(i, j)))
    except (IndexError, ValueError) as err:
        raise DatasetError(f"{path}: not a route graph: {err}") from err
    if pos != len(tok):
        raise DatasetError(f"{path}: {len(tok) - pos} trailing tokens")
    if loops and oddities is not None:
        oddities.append(Oddity(walk, "gt_self_loop", f"GT/{path.parent.name}/{path.name}: node(s) {sorted(loops)} "
                                                     "link to themselves; dropped", len(loops)))
    return Route(walk=walk, node_xy=image_to_enu(xy), links=np.array(sorted(links), dtype=np.int64).reshape(-1, 2))


def read_routes(root: Path, oddities: list[Oddity] | None = None) -> dict[int, Route]:
    """All ``GT/N/nodes.map`` routes by walk number."""
    gt = Path(root) / "GT"
    if not gt.is_dir():
        raise DatasetError(f"{root}: no GT/ directory (is this the PUTMC dataset?)")
    out = {}
    for d in sorted(gt.iterdir()):
        if d.is_dir() and d.name.isdigit() and (d / "nodes.map").exists():
            out[int(d.name)] = read_route(d / "nodes.map", int(d.name), oddities)
    return out


def read_survey_map(root: Path, oddities: list[Oddity] | None = None) -> RadioMap:
    """The 114-scan survey radio map (positions ENU, RSSI NaN where not heard, source "survey").

    APs are ordered by BSSID; an AP's frequency is the one of its first reading."""
    mdir = Path(root) / MAP_DIR
    ids, xy = read_table(mdir / "positions.map", 3)
    pos_of = {int(i): p for i, p in zip(ids, image_to_enu(xy))}
    blocks = read_wifi_blocks(mdir / "wifi.map")
    odd: list[Oddity] = [] if oddities is None else oddities
    prefix = f"{mdir.name}/wifi.map loc "
    try:
        locs = [int(head[1]) for head, _ in blocks]
    except ValueError:
        locs = None
    batch = None if locs is None or not all(loc in pos_of for loc in locs) else \
        _scans_from_blocks(blocks, [0] * len(blocks), "map", "survey", [f"{prefix}{loc}" for loc in locs], odd, 0)
    if batch is None:       # a malformed block or an unknown location: one at a time, the first fault raised
        scans, scan_ids = [], []
        for head, aps in blocks:
            loc = int(head[1])
            if loc not in pos_of:
                raise DatasetError(f"{mdir}/wifi.map: scan of location {loc} has no entry in positions.map")
            scans.append(_scan_from_block(0, aps, "map", "survey", f"{prefix}{loc}", odd, 0))
            scan_ids.append(loc)
    else:
        scans, scan_ids = batch, locs or []
    positions = [pos_of[loc] for loc in scan_ids]
    missing = sorted(set(pos_of) - set(scan_ids))
    if missing:
        odd.append(Oddity(0, "survey_position_without_scan", f"positions.map ids without a scan: {missing}",
                          len(missing)))
    hidden = sum(s == "" for sc in scans for s in sc.ssid)
    if hidden:
        odd.append(Oddity(0, "hidden_ssid", "survey readings with an empty SSID (hidden networks)", hidden))
    bssids = sorted({b for sc in scans for b in sc.bssid})
    col = {b: j for j, b in enumerate(bssids)}
    rssi = np.full((len(scans), len(bssids)), np.nan)
    freq = np.zeros(len(bssids))
    ssids = [""] * len(bssids)
    for i, sc in enumerate(scans):
        for b, r, f, s in zip(sc.bssid, sc.rssi_dbm, sc.freq_mhz, sc.ssid):
            j = col[b]
            rssi[i, j] = r
            if freq[j] == 0:
                freq[j], ssids[j] = f, s
    return RadioMap(positions=np.array(positions).reshape(-1, 2), bssids=bssids, rssi_dbm=rssi, freq_mhz=freq,
                    ssids=ssids, scan_ids=np.array(scan_ids, dtype=np.int64),
                    stamps_ns=np.zeros(len(scans), dtype=np.int64), source=["survey"] * len(scans))


# ---------------------------------------------------------------------------------------------
# walks
# ---------------------------------------------------------------------------------------------
def walk_folders(root: Path) -> dict[int, Path]:
    """{walk number: folder} of ``PUTMC_Floor3_Xperia_trajs/xperia_trajN[_JW]``."""
    tdir = Path(root) / TRAJ_DIR
    if not tdir.is_dir():
        raise DatasetError(f"{root}: no {TRAJ_DIR}/ directory (is this the PUTMC dataset?)")
    out: dict[int, Path] = {}
    for d in sorted(tdir.iterdir()):
        m = _FOLDER_RE.match(d.name)
        if m and d.is_dir():
            n = int(m.group(1))
            if n in out:
                raise DatasetError(f"{tdir}: two folders for walk {n}: {out[n].name}, {d.name}")
            out[n] = d
    return out


def start_gap(stamps: np.ndarray, *, gap_s: float = START_GAP_S) -> int:
    """Index of the first sample after the largest gap if that gap is longer than ``gap_s`` and
    lies in the first half of the recording (stale samples before it), else 0."""
    if len(stamps) < 2:
        return 0
    d = np.diff(stamps)
    i = int(np.argmax(d))
    return i + 1 if d[i] > gap_s * 1e9 and i < len(stamps) // 2 else 0


def _clean_stamps(name: str, stamps: np.ndarray, walk: int, odd: list[Oddity]) -> np.ndarray | slice:
    """Indices that make ``stamps`` strictly increasing: stable sort if out of order, first of each
    duplicate kept (both reported); ``slice(None)`` (no copy) when they already increase."""
    step = np.diff(stamps)
    if (step > 0).all():
        return slice(None)
    idx = np.arange(len(stamps))
    back = int(np.sum(step < 0))
    if back:
        odd.append(Oddity(walk, "non_monotonic", f"{name}: {back} stamps go backwards; sorted (stable)", back))
        idx = np.argsort(stamps, kind="stable")
    dup = np.r_[False, np.diff(stamps[idx]) == 0]
    if dup.any():
        odd.append(Oddity(walk, "duplicate_stamp", f"{name}: {int(dup.sum())} repeated stamps; first kept",
                          int(dup.sum())))
        idx = idx[~dup]
    return idx


def _kept_from(stamps: np.ndarray, cut: int, n_before: int) -> np.ndarray | slice:
    """Which samples have ``stamps >= cut`` (``n_before`` of them do not): a slice (no copy) when
    those are the last ones, as in a recording sorted in time, else a mask."""
    keep = stamps >= cut
    return slice(n_before, None) if keep[n_before:].all() else keep


def _report_dropouts(name: str, stamps: np.ndarray, walk: int, odd: list[Oddity]) -> None:
    if len(stamps) < 2:
        return
    d = np.diff(stamps) * 1e-9
    m = (d > DROPOUT_S) & (d <= START_GAP_S)
    if m.any():
        odd.append(Oddity(walk, "dropout", f"{name}: {int(m.sum())} gaps > {DROPOUT_S * 1e3:.0f} ms "
                                           f"(longest {d[m].max() * 1e3:.0f} ms)", int(m.sum())))
    big = np.flatnonzero(d > START_GAP_S)
    for i in big:
        odd.append(Oddity(walk, "gap", f"{name}: {d[i]:.1f} s gap after sample {i}"))


def read_walk(folder: Path, walk: int, *, keep_stale: bool = False) -> Walk:
    """Parse one walk folder. Stale samples (before the start gap of the accelerometer or the
    orientation stream; WiFi scans before the end of that gap) are dropped unless ``keep_stale``."""
    folder = Path(folder)
    odd: list[Oddity] = []
    acc_t, acc = read_table(folder / "acc.map", 4)
    ori_t, ori = read_table(folder / "orient.map", 6)
    blocks = read_wifi_blocks(folder / "wifi.map")
    pidx, pxy = read_table(folder / "positions.map", 3)
    raw = {"acc": len(acc_t), "orient": len(ori_t), "wifi": len(blocks), "positions": len(pidx),
           "wifi_aps": sum(len(a) for _, a in blocks)}
    name = walk_name(walk)

    # stale samples: cut at the end of the start gap (earliest stream resuming)
    ia, io = start_gap(acc_t), start_gap(ori_t)
    dropped = {"acc": 0, "orient": 0, "wifi": 0}
    if ia or io:
        cut = min(int(acc_t[ia]) if ia else int(acc_t[0]), int(ori_t[io]) if io else int(ori_t[0]))
        n_a, n_o = int(np.sum(acc_t < cut)), int(np.sum(ori_t < cut))
        n_w = sum(int(h[0]) < cut for h, _ in blocks)
        gap = (acc_t[ia] - acc_t[ia - 1]) * 1e-9 if ia else (ori_t[io] - ori_t[io - 1]) * 1e-9
        odd.append(Oddity(walk, "start_gap", f"{gap:.1f} s gap before the walk"))
        what = "dropped" if not keep_stale else "kept (--keep-stale)"
        odd.append(Oddity(walk, "stale_samples", f"{n_a} acc, {n_o} orient, {n_w} wifi samples before the "
                                                 f"start gap: {what}", n_a + n_o + n_w))
        if not keep_stale:
            ka, ko = _kept_from(acc_t, cut, n_a), _kept_from(ori_t, cut, n_o)
            acc_t, acc, ori_t, ori = acc_t[ka], acc[ka], ori_t[ko], ori[ko]
            blocks = [b for b in blocks if int(b[0][0]) >= cut]
            dropped = {"acc": n_a, "orient": n_o, "wifi": n_w}

    ka = _clean_stamps("acc", acc_t, walk, odd)
    acc_t, acc = acc_t[ka], acc[ka]
    ko = _clean_stamps("orient", ori_t, walk, odd)
    ori_t, ori = ori_t[ko], ori[ko]
    _report_dropouts("acc", acc_t, walk, odd)
    _report_dropouts("orient", ori_t, walk, odd)

    quat = ori[:, :4]
    qn = quat[:, 0] * quat[:, 0]                         # |q|, summed x, y, z, w in turn (as numpy's
    for j in (1, 2, 3):                                  # norm(axis=1) does) without an (M, 4) temporary
        qn += quat[:, j] * quat[:, j]
    np.sqrt(qn, out=qn)
    if np.any(np.abs(qn - 1) > 1e-3):
        bad = int(np.sum(np.abs(qn - 1) > 1e-3))
        odd.append(Oddity(walk, "quat_norm", f"orient: {bad} quaternions with |q| off 1 by > 1e-3; normalised", bad))
    quat = quat / qn[:, None]
    hacc = ori[:, 4]
    unrel = int(np.sum(hacc >= HEADING_UNRELIABLE_RAD))
    if unrel:
        odd.append(Oddity(walk, "heading_unreliable", f"orient: {unrel} samples with headingAcc >= "
                                                      f"{HEADING_UNRELIABLE_RAD:g} rad (max {hacc.max():.3g})", unrel))
    before = int(np.sum(acc_t < ori_t[0])) if len(ori_t) else len(acc_t)
    if before:
        odd.append(Oddity(walk, "acc_before_orientation", f"{before} acc samples precede the first orientation "
                                                          "(imu/data without orientation)", before))

    # WiFi scans and their true positions
    frame = f"{name}/wifi_link"
    prefix = f"{folder.name}/wifi.map scan "
    try:
        heads = [(int(h[0]), int(h[1])) for h, _ in blocks]
    except ValueError:
        heads = None
    batch = None if heads is None else _scans_from_blocks(blocks, [t for t, _ in heads], frame, "putmc",
                                                          [prefix + h[1] for h, _ in blocks], odd, walk)
    if batch is None:       # a malformed block: one at a time, so that the first fault is the one raised
        scans, scan_idx = [], []
        for head, aps in blocks:
            scans.append(_scan_from_block(int(head[0]), aps, frame, "putmc", prefix + head[1], odd, walk))
            scan_idx.append(int(head[1]))
    else:
        scans, scan_idx = batch, [i for _, i in heads or ()]
    st = np.array([s.stamp_ns for s in scans], dtype=np.int64)
    if np.any(np.diff(st) <= 0):
        n = int(np.sum(np.diff(st) <= 0))
        odd.append(Oddity(walk, "non_monotonic", f"wifi: {n} scan stamps not increasing; sorted", n))
        order = np.argsort(st, kind="stable")
        scans, scan_idx = [scans[i] for i in order], [scan_idx[i] for i in order]
    pos_of = {int(i): p for i, p in zip(pidx, image_to_enu(pxy))}
    missing = [i for i in scan_idx if i not in pos_of]
    if missing:
        raise DatasetError(f"{folder}: scans {missing} have no true position in positions.map")
    hidden = sum(s == "" for sc in scans for s in sc.ssid)
    if hidden:
        odd.append(Oddity(walk, "hidden_ssid", f"wifi: {hidden} readings with an empty SSID", hidden))
    scan_xy = np.array([pos_of[i] for i in scan_idx]).reshape(-1, 2)
    if scans and len(acc_t) and scans[-1].stamp_ns < acc_t[-1] - 10e9:
        odd.append(Oddity(walk, "wifi_ends_early", f"last WiFi scan {(acc_t[-1] - scans[-1].stamp_ns) * 1e-9:.1f} s "
                                                   "before the last acc sample"))
    scale = (folder / "scale.map")
    if scale.exists():
        s = float(read_text(scale).split()[0])
        if abs(s - PUTMC_SCALE_PX_PER_M) > 1e-6:
            odd.append(Oddity(walk, "folder_scale", f"{folder.name}/scale.map = {s:g} px/m (unused; root scale "
                                                    f"{PUTMC_SCALE_PX_PER_M:g})"))
    return Walk(walk=walk, folder=folder.name, acc_t=acc_t, acc=acc, ori_t=ori_t, quat_xyzw=quat,
                heading_acc=hacc, scans=scans, scan_xy=scan_xy, scan_idx=np.array(scan_idx, dtype=np.int64),
                raw_counts=raw, dropped=dropped, oddities=odd)


# ---------------------------------------------------------------------------------------------
# orientation helpers
# ---------------------------------------------------------------------------------------------
def quat_yaw(q_xyzw: np.ndarray) -> np.ndarray:
    """Yaw (ZYX Euler, CCW from world x), rad, of (N, 4) quaternions x, y, z, w."""
    q = np.asarray(q_xyzw, dtype=np.float64).reshape(-1, 4)
    return quaternion.quat_yaw(q[:, [3, 0, 1, 2]])


def to_map_quat(q_xyzw: np.ndarray, map_yaw_rad: float = PUTMC_MAP_YAW_RAD) -> np.ndarray:
    """Android device->ENU quaternions (N, 4) -> device->map: q_map = Rz(map_yaw) ⊗ q_enu.
    Roll and pitch are unchanged; yaw grows by ``map_yaw_rad``."""
    return np.ascontiguousarray(_map_quat_wxyz(q_xyzw, map_yaw_rad)[[1, 2, 3, 0]].T)


def map_yaw(q_xyzw: np.ndarray, map_yaw_rad: float = PUTMC_MAP_YAW_RAD) -> np.ndarray:
    """``quat_yaw(to_map_quat(q_xyzw, map_yaw_rad))`` without the (N, 4) arrays in between: the
    heading of each sample in the map frame, rad."""
    return quaternion.quat_yaw(_map_quat_wxyz(q_xyzw, map_yaw_rad).T)


def _map_quat_wxyz(q_xyzw: np.ndarray, map_yaw_rad: float) -> np.ndarray:
    """:func:`to_map_quat` as a (4, N) array, one row per component w, x, y, z (normalised)."""
    q = np.asarray(q_xyzw, dtype=np.float64).reshape(-1, 4)
    c, s = math.cos(map_yaw_rad / 2), math.sin(map_yaw_rad / 2)
    x, y, z, w = q.T
    out = np.empty((4, len(q)))
    mw, mx, my, mz = out
    # (0, 0, s, c) ⊗ (x, y, z, w)
    np.subtract(c * w, s * z, out=mw)
    np.subtract(c * x, s * y, out=mx)
    np.add(c * y, s * x, out=my)
    np.add(c * z, s * w, out=mz)
    n = mx * mx                                   # |q|: x, y, z, w summed in turn, as a norm over rows x, y, z, w
    n += my * my
    n += mz * mz
    n += mw * mw
    np.sqrt(n, out=n)
    out /= n
    return out


def causal_index(t_query: np.ndarray, t_ref: np.ndarray) -> np.ndarray:
    """For each query stamp, the index of the latest reference stamp at or before it (-1: none)."""
    return np.searchsorted(np.asarray(t_ref), np.asarray(t_query), side="right") - 1


def estimate_map_yaw(walks: list[Walk], *, min_step_m: float = 2.0) -> tuple[float, dict[int, float]]:
    """Map-frame walking direction minus Android yaw, rad: (pooled circular mean, per walk).

    Per pair of consecutive scans at least ``min_step_m`` apart: atan2 of the true displacement
    minus the circular mean of the device yaw between the two scan stamps."""
    pooled: list[float] = []
    per: dict[int, float] = {}
    for w in walks:
        yaw = quat_yaw(w.quat_xyzw)
        st, d = w.scan_t, []
        for i in range(len(st) - 1):
            dp = w.scan_xy[i + 1] - w.scan_xy[i]
            m = (w.ori_t >= st[i]) & (w.ori_t < st[i + 1])
            if np.hypot(*dp) < min_step_m or not m.any():
                continue
            dev = np.angle(np.mean(np.exp(1j * yaw[m])))
            d.append(float(np.angle(np.exp(1j * (math.atan2(dp[1], dp[0]) - dev)))))
        if d:
            per[w.walk] = float(np.angle(np.mean(np.exp(1j * np.array(d)))))
            pooled += d
    if not pooled:
        raise DatasetError("estimate_map_yaw: no pair of scans far enough apart")
    return float(np.angle(np.mean(np.exp(1j * np.array(pooled))))), per


# ---------------------------------------------------------------------------------------------
# whole dataset
# ---------------------------------------------------------------------------------------------
class Putmc:
    """The dataset at ``root``: ``routes``, ``survey_map()``, ``walk(n)``, ``walks()``, ``oddities``."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"PUTMC dataset directory {self.root} does not exist")
        self.oddities: list[Oddity] = []
        self.folders = walk_folders(self.root)
        self.routes = read_routes(self.root, self.oddities)
        no_gt = sorted(set(self.folders) - set(self.routes))
        if no_gt:
            raise DatasetError(f"{self.root}: walks {no_gt} have no GT/N/nodes.map")

    @property
    def walk_numbers(self) -> list[int]:
        return sorted(self.folders)

    def survey_map(self) -> RadioMap:
        return read_survey_map(self.root, self.oddities)

    def walk(self, n: int, *, keep_stale: bool = False) -> Walk:
        """Walk ``n`` (see :func:`read_walk`), plus a check of its true scan positions against its route."""
        from indoor_loc.eval.metrics import point_segment_distance

        if n not in self.folders:
            raise DatasetError(f"PUTMC has no walk {n}; walks are {self.walk_numbers}")
        w = read_walk(self.folders[n], n, keep_stale=keep_stale)
        if len(w.scan_xy):
            d = point_segment_distance(w.scan_xy, self.routes[n].segments)
            far = np.flatnonzero(d > OFF_ROUTE_M)
            if far.size:
                w.oddities.append(Oddity(n, "scan_off_route", f"positions.map: scan(s) {w.scan_idx[far].tolist()} lie "
                                                              f"{', '.join(f'{v:.2f}' for v in d[far])} m from the GT "
                                                              "route", int(far.size)))
        return w

    def map_png(self) -> Path:
        return self.root / "map.png"
