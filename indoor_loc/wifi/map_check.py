"""Map mismatch: do the scans still fit the radio map they are positioned against?

A radio map of another place, or of the same place before its access points were moved, still gives
fixes: every positioning method returns the best match it finds, however poor. This monitor watches
the stream of scans and says when they stop fitting the map.

**Residual of a scan.** The Sørensen (Bray–Curtis) distance of the scan to its nearest map fingerprint
in the powed representation (Torres-Sospedra et al., "Comprehensive analysis of distance and similarity
measures for Wi-Fi fingerprinting indoor positioning systems", Expert Systems with Applications 42,
2015, §3.1–3.2; the representation :mod:`indoor_loc.wifi.powed_knn` matches with)::

    x_a = (max(r_a − floor_dbm, 0) / −floor_dbm) ** beta
    D(x, y) = 1 − 2 Σ_a min(x_a, y_a) / (Σ_a x_a + Σ_a y_a)      in [0, 1]

Every AP the scan heard counts, those the map does not know too (a strong unknown AP is a reading the
map cannot explain), so D is 0 for a scan identical to a fingerprint and 1 for one sharing no AP with
the map. It does not depend on the positioning method (WKNN, powed k-NN, path loss, coverage areas and
their fallbacks all answer the same scans), and it costs one pass over the map readings of the scan's
APs through an inverted index (:class:`~indoor_loc.wifi.types.ApReadings`), about what a WKNN fix costs.

**The map's own residuals.** At start-up up to ``reference_scans`` map fingerprints (evenly spaced) are
each left out and matched against the rest of the map, without the fingerprints within ``exclude_m`` of
it (the same survey point: a second scan there is no test of the map) and, on a map of several sources
(walks, users), without its own source (a neighbour of the same walk shares its cached readings) — the
leave-walks-out of :mod:`indoor_loc.wifi.powed_knn`'s calibration. Their ``residual_quantile`` quantile
(p99 by default) is what a scan taken where the map was surveyed may reach.

**Verdict.** Over the last ``window`` scans (at least ``min_scans``): *mismatch* when more than
``declined_share`` of them were declined by the positioner, or when their median residual is more than
``residual_margin`` of the way from the map's quantile q to 1 (``q + margin (1 − q)``: the distance is
bounded, and a large map of many weak APs reaches 0.9 on its own); back to *ok* when at most
``clear_declined_share`` were declined and the median is back at or below q. The one-scan :meth:`MapCheck.update`
and the whole-array :func:`verdicts` give the same states.

**The map against itself.** A map whose fingerprints sit at the wrong positions (paired by row order instead
of by scan id, say) fits its scans perfectly and gives confident wrong fixes; the scans cannot tell. The
same leave-one-out says it: on a map whose neighbours in RSS are neighbours in space, a fingerprint's best
match lies a small share of the distance between two of its scans away (:func:`match_ratio`: 0.1–0.3 on the
simulated office, PUTMC and ms_site2's floors), on one with shuffled positions about as far as any other
scan (≈ 1). At ``max_match_ratio`` or more the map is suspect. A map moved as a whole (a wrong origin,
a mirrored axis) keeps its neighbours and is not seen.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from indoor_loc.params import field, require
from indoor_loc.wifi.powed_repr import powed
from indoor_loc.wifi.types import ApIndex, ApReadings, RadioMap, WifiScan

#: fewest left-out fingerprints with a match that say whether the map agrees with itself
MIN_MATCHES = 30
#: states of :class:`MapCheck`
STARTING, OK, MISMATCH = "starting", "ok", "mismatch"


@dataclass(frozen=True)
class MapCheckParams:
    """When the scans stop fitting the radio map (see the module doc)."""
    enabled: bool = field(True, "watch whether the scans fit the radio map (a WARN when they stop)")
    window: int = field(20, "the last this many scans are judged together")
    min_scans: int = field(8, "fewer scans seen: no verdict yet")
    declined_share: float = field(0.7, "mismatch when more than this share of the window's scans was declined (0-1)")
    clear_declined_share: float = field(0.5, "a mismatch ends only when at most this share was declined (0-1)")
    residual_quantile: float = field(0.99, "quantile of the map's own leave-one-out residuals a scan may reach (0-1)")
    residual_margin: float = field(0.5, "mismatch when the window's median residual is more than this share of the "
                                        "way from the map's quantile to 1 (a scan sharing no AP with the map) (0-1)")
    max_match_ratio: float = field(0.5, "the map itself is suspect when its fingerprints' best matches (each left "
                                        "out) lie a median this share of the median distance between two of its "
                                        "scans or farther (0-1; fingerprints paired with random positions: about 1)")
    reference_scans: int = field(300, "at most this many map scans (evenly spaced) are left out in turn to get the "
                                      "map's own residuals (bounds the start-up time on large maps)")
    exclude_m: float = field(1.0, "a left-out map scan is matched against the map scans at least this far from it "
                                  "(m; and, on a map of several sources, of other sources)")
    floor_dbm: float = field(-100.0, "RSS mapped to 0 in the powed representation (dBm)")
    beta: float = field(math.e, "exponent of the powed representation")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.window >= 1, n, "window", ">= 1", self.window)
        require(1 <= self.min_scans <= self.window, n, "min_scans", f"in [1, window = {self.window}]", self.min_scans)
        require(0.0 <= self.declined_share < 1.0, n, "declined_share", "in [0, 1)", self.declined_share)
        require(0.0 <= self.clear_declined_share <= self.declined_share, n, "clear_declined_share",
                f"in [0, declined_share = {self.declined_share}]", self.clear_declined_share)
        require(0.0 < self.residual_quantile <= 1.0, n, "residual_quantile", "in (0, 1]", self.residual_quantile)
        require(0.0 <= self.residual_margin < 1.0, n, "residual_margin", "in [0, 1)", self.residual_margin)
        require(0.0 < self.max_match_ratio <= 1.0, n, "max_match_ratio", "in (0, 1]", self.max_match_ratio)
        require(self.reference_scans >= 1, n, "reference_scans", ">= 1", self.reference_scans)
        require(math.isfinite(self.exclude_m) and self.exclude_m >= 0, n, "exclude_m", ">= 0", self.exclude_m)
        require(-120.0 <= self.floor_dbm < 0.0, n, "floor_dbm", "in [-120, 0) dBm", self.floor_dbm)
        require(math.isfinite(self.beta) and self.beta > 0, n, "beta", "> 0", self.beta)


@dataclass
class MapCheckState:
    """The window, as ring arrays (slot ``count % window`` is the next): ``declined`` (W,) bool, ``residual``
    (W,) Sørensen distance; ``count`` scans seen; ``mismatch`` the verdict; ``mismatches`` the turns to it."""
    declined: np.ndarray
    residual: np.ndarray
    count: int = 0
    mismatch: bool = False
    mismatches: int = 0

    @classmethod
    def empty(cls, window: int) -> "MapCheckState":
        return cls(np.zeros(window, bool), np.full(window, np.nan))

    def copy(self) -> "MapCheckState":
        return MapCheckState(self.declined.copy(), self.residual.copy(), self.count, self.mismatch, self.mismatches)


@dataclass(frozen=True)
class WindowStats:
    """What the window says: ``scans`` in it, the ``declined_share``, the ``residual_p50`` (median)."""
    scans: int
    declined_share: float
    residual_p50: float


class MapIndex:
    """A radio map's fingerprints in the powed representation, indexed by AP for the residual."""

    def __init__(self, radio_map: RadioMap, params: MapCheckParams) -> None:
        self.params = params
        vals = powed(np.asarray(radio_map.rssi_dbm, float), params.floor_dbm, params.beta)   # (M, A), 0 = not heard
        self.n = int(vals.shape[0])
        self.aps = ApIndex(radio_map.bssids)
        self.readings = ApReadings(vals > 0, vals)
        self.sums = vals.sum(axis=1)                                    # (M,)

    def distances(self, cols: np.ndarray, q: np.ndarray, total: float) -> tuple[np.ndarray, np.ndarray]:
        """Sørensen distance of a query (known columns ``cols`` (q,), their values ``q`` (q,); ``total`` the
        sum of all its values, unknown APs included) to the map rows sharing an AP with it: (rows, D)."""
        rows, map_vals, lens = self.readings.gather(cols)
        if len(rows) == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        shared = np.bincount(rows, weights=np.minimum(np.repeat(q, lens), map_vals), minlength=self.n)
        touched = np.flatnonzero(shared > 0)
        d = 1.0 - 2.0 * shared[touched] / np.maximum(total + self.sums[touched], 1e-300)
        return touched, np.clip(d, 0.0, 1.0)

    def residual(self, scan: WifiScan) -> float:
        """The scan's distance to its nearest fingerprint (1 when it shares no AP with the map)."""
        v = powed(np.asarray(scan.rssi_dbm, float), self.params.floor_dbm, self.params.beta)
        total = float(v.sum())
        cols = self.aps.columns(scan.bssid)
        keep = (v > 0) & (cols >= 0)
        if not keep.any():
            return 1.0
        _, d = self.distances(cols[keep], v[keep], total)
        return float(d.min()) if len(d) else 1.0


class Reference(NamedTuple):
    """The map matched against itself: ``residual`` (R,) of the left-out fingerprints, ``match_m`` (R',) the
    distance (m) from each to its best match (those sharing an AP with some other), ``pairs_m`` the median
    distance between two of the left-out fingerprints (m; NaN with fewer than two)."""
    residual: np.ndarray
    match_m: np.ndarray
    pairs_m: float


def map_reference(radio_map: RadioMap, params: MapCheckParams, index: MapIndex | None = None) -> Reference:
    """Up to ``reference_scans`` evenly spaced map fingerprints, each left out and matched against the map
    without the fingerprints closer than ``exclude_m`` to it (3-D, floor heights included) and, when the map
    has several sources, without its own source: their residuals and how far their best matches lie. A
    fingerprint with nothing left to match against gives no value."""
    index = MapIndex(radio_map, params) if index is None else index
    m = index.n
    if m < 2:
        return Reference(np.zeros(0), np.zeros(0), math.nan)
    pick = np.unique(np.linspace(0, m - 1, min(m, params.reference_scans)).round().astype(np.int64))
    xyz = np.column_stack([np.asarray(radio_map.positions, float), np.asarray(radio_map.z_m, float)])
    labels = np.asarray(radio_map.source, dtype=object)
    by_source = len(set(radio_map.source)) > 1
    out, match = [], []
    rss = np.asarray(radio_map.rssi_dbm, float)
    for i in pick:
        v = powed(rss[i], params.floor_dbm, params.beta)
        cols = np.flatnonzero(v > 0)
        q = v[cols]
        if len(cols) == 0:
            continue
        near = np.linalg.norm(xyz - xyz[i], axis=1) < params.exclude_m
        near[i] = True
        banned = near | (labels == labels[i]) if by_source else near
        if banned.all():
            continue
        rows, d = index.distances(cols, q, float(q.sum()))
        allowed = ~banned[rows]
        rows, d = rows[allowed], d[allowed]
        out.append(float(d.min()) if len(d) else 1.0)
        if len(d):
            match.append(float(np.linalg.norm(xyz[rows[np.argmin(d)]] - xyz[i])))
    sep = np.linalg.norm(xyz[pick][:, None] - xyz[pick][None], axis=2)[np.triu_indices(len(pick), 1)]
    return Reference(np.asarray(out, float), np.asarray(match, float), float(np.median(sep)) if len(sep) else math.nan)


def match_ratio(ref: Reference) -> float:
    """Median distance of the map's fingerprints to their best matches over the median distance between two of
    them: small on a map whose neighbours in RSS are neighbours in space (0.1–0.3 on the simulated office, PUTMC
    and ms_site2's floors), about 1 when fingerprints and positions are paired at random (NaN with fewer than
    :data:`MIN_MATCHES` matches)."""
    if len(ref.match_m) < MIN_MATCHES or not ref.pairs_m > 0:
        return math.nan
    return float(np.median(ref.match_m)) / ref.pairs_m


def window_stats(state: MapCheckState) -> WindowStats:
    """The statistics of the scans in the window."""
    n = min(state.count, len(state.declined))
    if n == 0:
        return WindowStats(0, math.nan, math.nan)
    return WindowStats(n, float(np.mean(state.declined[:n])), float(np.median(state.residual[:n])))


def residual_limit(map_q: float, params: MapCheckParams) -> float:
    """The window's median residual above which the scans do not fit the map: ``residual_margin`` of the way
    from the map's own quantile to 1 (the distance is bounded, and a map whose own scans reach 0.9 leaves
    less room than one whose scans reach 0.2)."""
    return map_q + params.residual_margin * (1.0 - map_q)


def judge(mismatch: bool, stats: WindowStats, map_q: float, params: MapCheckParams) -> bool:
    """The verdict after a scan: whether the scans do not fit the map (``mismatch`` the one before)."""
    if stats.scans < params.min_scans:
        return mismatch
    has_ref = math.isfinite(map_q)
    if not mismatch:
        return stats.declined_share > params.declined_share or \
            (has_ref and stats.residual_p50 > residual_limit(map_q, params))
    clear = stats.declined_share <= params.clear_declined_share and (not has_ref or stats.residual_p50 <= map_q)
    return not clear


class MapCheck:
    """Online map-mismatch monitor of one radio map: :meth:`update` per scan (see the module doc)."""

    def __init__(self, radio_map: RadioMap, params: MapCheckParams | None = None) -> None:
        self.params = params or MapCheckParams()
        self.params.validate()
        self.radio_map = radio_map
        self.index = MapIndex(radio_map, self.params)
        self.reference = map_reference(radio_map, self.params, self.index)
        res = self.reference.residual
        #: the map's own residual quantile (NaN when the map has too few fingerprints to leave one out)
        self.map_q = float(np.quantile(res, self.params.residual_quantile)) if len(res) else math.nan
        #: how far the map's fingerprints match (:func:`match_ratio`); the map is suspect when it is this far
        self.match_ratio = match_ratio(self.reference)
        self.map_suspect = self.match_ratio >= self.params.max_match_ratio
        self.state = MapCheckState.empty(self.params.window)

    def update(self, scan: WifiScan, declined: bool) -> str:
        """Take one scan (``declined``: the positioner gave no fix); returns the text to say when the scans
        have just stopped fitting the map, else ""."""
        return self.update_residual(self.index.residual(scan), declined)

    def update_residual(self, residual: float, declined: bool) -> str:
        """:meth:`update` with the scan's residual already computed."""
        st = self.state
        slot = st.count % len(st.declined)
        st.declined[slot], st.residual[slot] = bool(declined), float(residual)
        st.count += 1
        was = st.mismatch
        stats = window_stats(st)
        st.mismatch = judge(was, stats, self.map_q, self.params)
        if st.mismatch and not was:
            st.mismatches += 1
            return self.describe(stats)
        return ""

    @property
    def status(self) -> str:
        """"starting" (fewer than ``min_scans`` seen), "ok" or "mismatch"."""
        if self.state.mismatch:
            return MISMATCH
        return OK if self.state.count >= self.params.min_scans else STARTING

    def describe(self, stats: WindowStats | None = None) -> str:
        """Why the scans do not fit the map, in words."""
        s = window_stats(self.state) if stats is None else stats
        p = self.params
        why = []
        if s.declined_share > p.clear_declined_share:
            why.append(f"{round(s.declined_share * s.scans)} of the last {s.scans} scans were declined")
        if math.isfinite(self.map_q) and s.residual_p50 > self.map_q:
            why.append(f"their median distance to the nearest fingerprint is {s.residual_p50:.2f}, where the map's "
                       f"own scans reach {self.map_q:.2f} (p{100 * p.residual_quantile:g}, leave-one-out)")
        return ("the scans do not fit the radio map (" + "; ".join(why or ["see map_fit.*"]) +
                "): is it the map of this place, and are its access points where they were?")

    def describe_map(self) -> str:
        """What is wrong with the map itself, in words ("" when nothing is)."""
        if not self.map_suspect:
            return ""
        r = self.reference
        return (f"the radio map disagrees with itself: its fingerprints' best matches (each left out) lie a median "
                f"{np.median(r.match_m):.1f} m away, {self.match_ratio:.2f} of the median distance between two of its "
                f"scans ({r.pairs_m:.1f} m): are its positions paired with the right fingerprints?")

    def summary(self) -> dict[str, str]:
        """Diagnostics values (``map_fit.*``)."""
        s = window_stats(self.state)
        out = {"map_fit.state": self.status, "map_fit.scans": str(s.scans),
               "map_fit.map_p{:g}".format(100 * self.params.residual_quantile): _fmt(self.map_q),
               "map_fit.residual_limit": _fmt(residual_limit(self.map_q, self.params)),
               "map_fit.map_match_ratio": _fmt(self.match_ratio)}
        if s.scans:
            out["map_fit.declined_share"] = f"{s.declined_share:.2f}"
            out["map_fit.residual_p50"] = _fmt(s.residual_p50)
        if self.state.mismatches:
            out["map_fit.mismatches"] = str(self.state.mismatches)
        return out


def _fmt(x: float) -> str:
    return f"{x:.3f}" if math.isfinite(x) else "n/a"


def verdicts(residuals: np.ndarray, declined: np.ndarray, map_q: float, params: MapCheckParams,
             state: MapCheckState | None = None) -> np.ndarray:
    """The verdict (N,) bool after each of N scans, from their residuals (N,) and declined flags (N,),
    continuing ``state`` (default: none seen); the batch form of :meth:`MapCheck.update`."""
    st = (state or MapCheckState.empty(params.window)).copy()
    residuals = np.asarray(residuals, float)
    declined = np.asarray(declined, bool)
    w = params.window
    hist_d = np.concatenate([_ordered(st.declined, st.count), declined]).astype(float)
    hist_r = np.concatenate([_ordered(st.residual, st.count), residuals])
    k0 = min(st.count, w)
    out = np.zeros(len(residuals), bool)
    mismatch = st.mismatch
    for j in range(len(residuals)):
        end = k0 + j + 1
        lo = max(0, end - w)
        n = end - lo
        stats = WindowStats(min(st.count + j + 1, w), float(hist_d[lo:end].mean()),
                            float(np.median(hist_r[lo:end]))) if n else WindowStats(0, math.nan, math.nan)
        mismatch = judge(mismatch, stats, map_q, params)
        out[j] = mismatch
    return out


def _ordered(ring: np.ndarray, count: int) -> np.ndarray:
    """A ring's filled slots, oldest first."""
    w = len(ring)
    if count <= w:
        return ring[:count]
    s = count % w
    return np.concatenate([ring[s:], ring[:s]])


__all__ = ["MapCheck", "MapCheckParams", "MapCheckState", "MapIndex", "Reference", "WindowStats", "judge",
           "map_reference", "match_ratio", "residual_limit", "verdicts", "window_stats", "STARTING", "OK", "MISMATCH"]
