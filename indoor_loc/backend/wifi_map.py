"""The evolving WiFi map of the back-end: fixed survey fingerprints plus users' scans.

Each row is a fingerprint with a *position reference*: ``ref < 0`` is the fixed position
``fixed_xy[-1 - ref]`` (a pre-surveyed scan, or a learnt one loaded from a saved map), ``ref >= 0``
is a pose variable of the graph (a user's scan, whose position the optimiser moves). Matching is by
RSS alone (WKNN, :class:`indoor_loc.wifi.wknn.Wknn`), so which rows a scan matches does not depend on
the current position estimates; the graph turns each match into a hyperedge whose neighbour
positions are those references.

RSS is kept in one dense (rows, APs) array with spare capacity in both dimensions (appending a row
or a new AP is amortised O(1)); a query builds a :class:`RadioMap` view of the rows it may use (the
survey and, in the joint configuration, other users' scans) and fits WKNN's inverted index on it.
The number of user rows is capped (``max_rows``): the oldest learnt rows are dropped first.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from indoor_loc.errors import MapError
from indoor_loc.measurements import Fix
from indoor_loc.wifi.radiomap import FINGERPRINTS_FILE, FP_COLUMNS, FP_COLUMNS_V2, read_manifest
from indoor_loc.wifi.types import RadioMap, WifiScan
from indoor_loc.wifi.wknn import Wknn, WknnParams, neighbour_fix

SURVEY = -1      # user index of fixed rows


@dataclass(frozen=True)
class Match:
    """A localised scan: WKNN fix, the matched rows' position references (k,) and weights (k,)."""
    fix: Fix
    refs: np.ndarray
    weights: np.ndarray
    n_from_users: int          # how many of the k neighbours are other users' scans


class EvolvingMap:
    """Fingerprints with position references (see module docstring)."""

    def __init__(self, wknn: WknnParams, *, max_rows: int = 20000) -> None:
        self.wknn_params = wknn
        self.max_rows = int(max_rows)
        self.bssids: list[str] = []
        self.ssids: list[str] = []
        self.freq: list[float] = []
        self._col: dict[str, int] = {}
        self._rss = np.full((64, 64), np.nan)
        self.n = 0
        self.ref = np.zeros(64, np.int64)
        self.user = np.zeros(64, np.int64)
        self.stamp = np.zeros(64, np.int64)
        self.fixed_xy = np.zeros((0, 2))
        self.fixed_source: list[str] = []
        self.n_loaded_fixed = 0          # fixed positions from add_fixed (the rest: pinned poses)
        self._cov_floor = (wknn.cov_floor_m ** 2) * np.eye(2)
        self.dropped_rows = 0
        self._n_user_rows = 0            # rows with user != SURVEY
        # the fitted WKNN index is reused while the rows a query may use are unchanged: fixed rows
        # and drops change every query's rows (epoch); a user's own appended rows never enter its
        # own queries, so only other users' appends count (in the sequential order a walk's scans
        # all use one index)
        self._epoch = 0
        self._appends = 0
        self._own_appends: dict[int, int] = {}
        self._fitted: tuple[tuple, np.ndarray, Wknn] | None = None

    # ------------------------------------------------------------------------------------------
    def _columns(self, scan: WifiScan) -> np.ndarray:
        cols = np.empty(len(scan.bssid), np.int64)
        for i, b in enumerate(scan.bssid):
            j = self._col.get(b)
            if j is None:
                j = self._col[b] = len(self.bssids)
                self.bssids.append(b)
                self.ssids.append(scan.ssid[i] if i < len(scan.ssid) else "")
                self.freq.append(float(scan.freq_mhz[i]))
            cols[i] = j
        if len(self.bssids) > self._rss.shape[1]:
            grown = np.full((self._rss.shape[0], 2 * len(self.bssids)), np.nan)
            grown[:, :self._rss.shape[1]] = self._rss
            self._rss = grown
        return cols

    def _append(self, cols: np.ndarray, rssi: np.ndarray, ref: int, user: int, stamp: int) -> int:
        if self.n == len(self.ref):
            cap = 2 * len(self.ref)
            grown = np.full((cap, self._rss.shape[1]), np.nan)
            grown[:self.n] = self._rss[:self.n]
            self._rss = grown
            for name in ("ref", "user", "stamp"):
                a = getattr(self, name)
                b = np.zeros(cap, a.dtype)
                b[:self.n] = a[:self.n]
                setattr(self, name, b)
        i = self.n
        if user == SURVEY:
            self._epoch += 1
        else:
            self._appends += 1
            self._n_user_rows += 1
            self._own_appends[user] = self._own_appends.get(user, 0) + 1
        self._rss[i] = np.nan
        self._rss[i, cols] = rssi
        self.ref[i], self.user[i], self.stamp[i] = ref, user, stamp
        self.n += 1
        return i

    def add_fixed(self, radio_map: RadioMap) -> None:
        """Add a radio map's fingerprints at their (fixed) positions."""
        pos = np.asarray(radio_map.positions, float).reshape(-1, 2)
        base = len(self.fixed_xy)
        self.fixed_xy = np.vstack([self.fixed_xy, pos])
        self.fixed_source += list(radio_map.source)
        self.n_loaded_fixed = len(self.fixed_xy)
        rss = np.asarray(radio_map.rssi_dbm, float)
        scan = WifiScan(0, tuple(radio_map.bssids), np.zeros(len(radio_map.bssids)),
                        np.asarray(radio_map.freq_mhz, float), ssid=tuple(radio_map.ssids))
        cols = self._columns(scan)
        for m in range(len(pos)):
            ok = ~np.isnan(rss[m])
            self._append(cols[ok], rss[m, ok], -1 - (base + m), SURVEY, int(radio_map.stamps_ns[m]))

    def add_scan(self, scan: WifiScan, ref: int, user: int) -> int:
        """A user's scan joins the map at pose ``ref``; returns its row. Beyond ``max_rows`` user rows
        the oldest user row is dropped."""
        cols = self._columns(scan)
        row = self._append(cols, np.asarray(scan.rssi_dbm, float), ref, user, scan.stamp_ns)
        if self._n_user_rows > self.max_rows:
            self._drop_oldest_user_row()
        return row

    def _drop_oldest_user_row(self) -> None:
        users = np.flatnonzero(self.user[:self.n] != SURVEY)
        i = int(users[0])
        keep = np.ones(self.n, bool)
        keep[i] = False
        n = self.n - 1
        self._rss[:n] = self._rss[:self.n][keep]
        for name in ("ref", "user", "stamp"):
            a = getattr(self, name)
            a[:n] = a[:self.n][keep]
        self.n = n
        self.dropped_rows += 1
        self._n_user_rows -= 1
        self._epoch += 1

    def add_point(self, xy: np.ndarray) -> int:
        """A fixed position with no fingerprint (a front-end fix a factor pulls a pose to); returns its
        reference (< 0). Unused ones go with :meth:`collect_fixed`."""
        self.fixed_xy = np.vstack([self.fixed_xy, np.asarray(xy, float).reshape(1, 2)])
        self.fixed_source.append("fix")
        return -len(self.fixed_xy)

    def pin(self, refs: np.ndarray, xy: np.ndarray, source: list[str]) -> np.ndarray:
        """Rows whose position reference is one of the poses ``refs`` (R,) get that pose's final
        position ``xy`` (R, 2) as a fixed (learnt) position; returns the fixed reference (< 0) of
        each pose (used to rewrite hyperedges that named them)."""
        refs = np.asarray(refs, np.int64)
        base = len(self.fixed_xy)
        self.fixed_xy = np.vstack([self.fixed_xy, np.asarray(xy, float).reshape(-1, 2)])
        self.fixed_source += list(source)
        new = -1 - (base + np.arange(len(refs)))
        ref = self.ref[:self.n]
        idx = np.flatnonzero(ref >= 0)
        if len(refs) and len(idx):
            order = np.argsort(refs)
            k = np.minimum(np.searchsorted(refs[order], ref[idx]), len(refs) - 1)
            hit = refs[order][k] == ref[idx]
            ref[idx[hit]] = new[order[k[hit]]]
        return new

    def renumber(self, pose_map: np.ndarray) -> None:
        """Pose references after the graph dropped poses: ``pose_map[old] = new`` (rows must not
        name a dropped pose: :meth:`pin` them first)."""
        ref = self.ref[:self.n]
        ref[ref >= 0] = pose_map[ref[ref >= 0]]

    def collect_fixed(self, in_use: np.ndarray, n_keep: int) -> np.ndarray:
        """Drop learnt fixed positions (index ≥ ``n_keep``: those :meth:`pin` added) that neither a
        row nor ``in_use`` (fixed references < 0 held elsewhere) names; returns the map old
        reference -> new reference for fixed references (index ``-1 - ref``)."""
        ref = self.ref[:self.n]
        used = np.zeros(len(self.fixed_xy), bool)
        used[:n_keep] = True
        used[-1 - ref[ref < 0]] = True
        in_use = np.asarray(in_use, np.int64)
        used[-1 - in_use[in_use < 0]] = True
        new_index = np.cumsum(used) - 1
        self.fixed_xy = self.fixed_xy[used]
        self.fixed_source = [src for src, u in zip(self.fixed_source, used) if u]
        ref[ref < 0] = -1 - new_index[-1 - ref[ref < 0]]
        return new_index

    # ------------------------------------------------------------------------------------------
    def match(self, scan: WifiScan, *, user: int, joint: bool, pose_xy: np.ndarray,
              survey: bool = True) -> Match | None:
        """WKNN of ``scan`` against the survey rows (unless ``survey`` is False) and, when ``joint``,
        other users' rows (never the user's own). None when WKNN declines (fewer candidates than k...).

        The rows are chosen by RSS alone; the fix (the initial position of a pose added at this scan,
        and its covariance) is then taken at the matched rows' current positions: the fixed ones,
        and for users' rows their poses in ``pose_xy (P, 2)``, the graph's current estimates."""
        key = ((user, self._epoch, self._appends - self._own_appends.get(user, 0)) if joint
               else (None, self._epoch)) + (survey,)
        if self._fitted is not None and self._fitted[0] == key:
            rows, wknn = self._fitted[1], self._fitted[2]
        else:
            u = self.user[:self.n]
            rows = np.flatnonzero(((u == SURVEY) & survey) | (((u != user) & (u != SURVEY)) if joint else False))
            if len(rows) == 0:
                return None
            # positions are looked up per match (users' rows move with their poses): not needed here
            rm = RadioMap(positions=np.zeros((len(rows), 2)), bssids=list(self.bssids),
                          rssi_dbm=self._rss[rows, :len(self.bssids)], freq_mhz=np.asarray(self.freq, float),
                          ssids=list(self.ssids), scan_ids=rows.astype(np.int64), stamps_ns=self.stamp[rows].copy(),
                          source=["map"] * len(rows))
            wknn = Wknn(self.wknn_params).fit(rm)
            self._fitted = (key, rows, wknn)
        fix = wknn.locate_rows(scan)
        if not fix.ok:
            return None
        chosen = rows[np.asarray(fix.info["rows"], np.int64)]
        refs = self.ref[chosen].copy()
        w = np.asarray(fix.info["weights"], float)
        xy, cov = neighbour_fix(self.positions(refs, pose_xy), w, self.wknn_params.cov_scale, self._cov_floor)
        fix = replace(fix, xy=xy, cov=cov)
        return Match(fix, refs, w, int(np.sum(self.user[chosen] != SURVEY)))

    def positions(self, refs: np.ndarray, pose_xy: np.ndarray) -> np.ndarray:
        """Current positions ``(N, 2)`` of position references ``refs``: ``fixed_xy[-1 - ref]`` for
        ref < 0, ``pose_xy[ref]`` for ref >= 0."""
        refs = np.asarray(refs, np.int64)
        out = np.empty((len(refs), 2))
        fixed = refs < 0
        out[fixed] = self.fixed_xy[-1 - refs[fixed]]
        out[~fixed] = np.asarray(pose_xy, float)[refs[~fixed]]
        return out

    def radio_map(self, pose_xy: np.ndarray, user_names: list[str]) -> RadioMap:
        """The whole map as a :class:`RadioMap` at the current positions (``pose_xy`` (P, 2) of the
        graph's poses): what ``save_radiomap`` writes. Sources: the survey's labels, else the user."""
        ref = self.ref[:self.n]
        xy = self.positions(ref, pose_xy)
        src = [self.fixed_source[-1 - r] if r < 0 else user_names[u] for r, u in zip(ref, self.user[:self.n])]
        return RadioMap(positions=xy, bssids=list(self.bssids), rssi_dbm=self._rss[:self.n, :len(self.bssids)].copy(),
                        freq_mhz=np.asarray(self.freq, float), ssids=list(self.ssids),
                        scan_ids=np.arange(self.n, dtype=np.int64), stamps_ns=self.stamp[:self.n].copy(), source=src)

    @property
    def n_user_rows(self) -> int:
        return self._n_user_rows


def survey_positions(directory: str | Path) -> np.ndarray:
    """(N, 2) positions of a radio map directory's scans, in file order, without their readings: what
    the back-end draws of a survey it does not match against (``wifi_source: fix``). Of each fingerprint
    row it keeps only the scan's position, once per scan (a fraction of
    :func:`~indoor_loc.wifi.radiomap.load_radiomap`'s time and none of its memory on a large map).
    MapError when the files are missing, foreign or damaged, or hold another number of scans or
    readings than the manifest says."""
    d = Path(directory)
    man = read_manifest(d)
    path = d / (man.get("files") or {}).get("fingerprints", FINGERPRINTS_FILE)
    expected = FP_COLUMNS if man.get("version") == 1 else FP_COLUMNS_V2
    i_id, i_x, i_y = (expected.index(c) for c in ("scan_id", "x", "y"))
    xy: list[tuple[float, float]] = []
    last = None
    n_rows = 0
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = csv.reader(fh)
            header = next(rows, None)
            if tuple(header or ()) != expected:
                raise MapError(f"{d}: fingerprints columns {header}, expected {list(expected)}")
            for r in rows:
                n_rows += 1
                if r[i_id] != last:
                    last = r[i_id]
                    xy.append((float(r[i_x]), float(r[i_y])))
    except OSError as err:
        raise MapError(f"cannot read radio map {d}: {err}") from err
    except (IndexError, ValueError, csv.Error) as err:
        raise MapError(f"{d}: malformed radio map row: {err}") from err
    out = np.array(xy, float).reshape(-1, 2)
    counts = man.get("counts") or {k: man[k] for k in ("scans",) if k in man}
    # a scan without readings is one row with an empty BSSID: rows = readings + such scans
    for key, n, ok in (("scans", len(out), lambda m: m == len(out)),
                       ("readings", n_rows, lambda m: m <= n_rows <= m + len(out))):
        if key in counts and not ok(int(counts[key])):
            raise MapError(f"{d}: manifest says {counts[key]} {key}, files hold {n} (truncated or edited?)")
    if not np.all(np.isfinite(out)):
        raise MapError(f"{d}: a scan position is not finite")
    return out
