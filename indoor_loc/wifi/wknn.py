"""Weighted k-nearest-neighbour WiFi fingerprinting (Nowicki & Skrzypczyński 2019, Sec. 4.2).

A scan X is compared with every map scan Y over the APs both heard at or above
``min_signal_dbm`` (readings below it are removed from both scans first):

    d_p(X, Y) = || r_X - r_Y ||_p over the shared APs    ("l2": Euclidean, eq. 16; "l1": sum |.|;
                                                           "rms": sqrt(mean square), the authors' code;
                                                           "mae": mean |.|)
    s(X, Y)   = 1 / (d_p(X, Y) + epsilon)                 (eq. 16)

A pair counts only when the shared APs make at least ``shared_threshold`` of the networks of *both*
scans (``shared_strict``: more than, as the authors' code does). Among the candidates the k most
similar give ``p = sum_k s_k f_k / sum_k s_k`` (eq. 13); with fewer than ``min_candidates``
candidates the scan is declined (``reason="few_candidates"``; the authors' code needs k).

Covariance (the paper gives none): the similarity-weighted spread of the k neighbour positions
about p, scaled by ``cov_scale``, plus an isotropic floor ``cov_floor_m**2`` — the neighbours'
spread says how ambiguous the match is, the floor covers the error common to all neighbours (a map
scan's own distance from the truth, the map's spacing). Defaults (0.35, 1 m) were calibrated on
PUTMC (paper setting): the 50 % / 95 % ellipses hold 53 % / 91 % of the true scan positions
(``indoor-loc bench wifi``). The raw spread (scale 1, no floor) gives 64 % / 91 %, scale 1 with the
1 m floor 74 % / 99 %; the 95 % figure stays short of nominal because WKNN errors are heavy-tailed
(a few fixes matched to the wrong corridor lie outside any ellipse a good fix should have).

Index. :meth:`Wknn.fit` builds an inverted index AP -> map readings (CSR by AP column: the map
rows that heard the AP above the threshold and their RSS) plus per-scan network counts. A query
gathers the readings of the q APs it heard, and the shared counts and the summed squared / absolute
differences of every map scan are two ``np.bincount`` calls over those readings — no Python loop
over map scans, and the cost is the number of map readings of the query's APs, O(M q / A * APs
heard per scan), at most linear in the map size. A dense (M, A) masked-matrix version was 6x slower
at 10 000 scans (it touches every map scan for every queried AP); 10 000 synthetic map scans with
200 APs: ~2 ms per scan on one core (``indoor-loc bench wifi``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from indoor_loc.params import field, require
from indoor_loc.errors import MapError
from indoor_loc.measurements import Fix
from indoor_loc.wifi.types import ApIndex, ApReadings, Positioner, RadioMap, WifiScan

ERROR_TYPES = ("l2", "l1", "rms", "mae")


def neighbour_fix(positions: np.ndarray, weights: np.ndarray, cov_scale: float,
                  cov_floor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The WKNN estimate from the k neighbours' ``positions (k, 2)`` and normalised ``weights (k,)``:
    their weighted mean, and ``cov_scale`` × their weighted spread about it + ``cov_floor (2, 2)``."""
    xy = weights @ positions
    dev = positions - xy
    return xy, cov_scale * ((weights[:, None] * dev).T @ dev) + cov_floor


@dataclass(frozen=True)
class WknnParams:
    """WKNN parameters; defaults are the paper's best (k=4, 0.6, -100 dBm, L2)."""
    k: int = field(4, "number of most similar map scans averaged")
    shared_threshold: float = field(0.6, "minimum fraction of each scan's networks the pair must share, "
                                         "checked in both directions (0-1)")
    shared_strict: bool = field(False, "require more than (instead of at least) shared_threshold")
    min_signal_dbm: float = field(-100.0, "readings below this RSS are ignored in scans and map (dBm)")
    error_type: str = field("l2", "RSS distance over the shared APs: 'l2', 'l1', 'rms' (sqrt of the mean "
                                    "square, the authors' code) or 'mae' (mean absolute)")
    epsilon: float = field(1e-4, "epsilon in the similarity 1 / (d + epsilon) (dB)")
    min_candidates: int = field(0, "fewer candidate map scans -> no fix; 0 = k (as the authors' code)")
    min_shared_aps: int = field(1, "a pair must share at least this many APs")
    cov_scale: float = field(0.35, "factor on the weighted spread of the k neighbour positions in the fix "
                                   "covariance")
    cov_floor_m: float = field(1.0, "isotropic standard deviation added to the fix covariance (m)")

    def validate(self) -> None:
        n = type(self).__name__
        require(int(self.k) >= 1, n, "k", "an integer >= 1", self.k)
        require(0.0 <= self.shared_threshold <= 1.0, n, "shared_threshold", "in [0, 1]", self.shared_threshold)
        require(-120.0 <= self.min_signal_dbm <= 0.0, n, "min_signal_dbm", "in [-120, 0] dBm",
                  self.min_signal_dbm)
        require(self.error_type in ERROR_TYPES, n, "error_type", f"one of {list(ERROR_TYPES)}", self.error_type)
        require(math.isfinite(self.epsilon) and self.epsilon > 0, n, "epsilon", "> 0", self.epsilon)
        require(int(self.min_candidates) >= 0, n, "min_candidates", "an integer >= 0", self.min_candidates)
        require(int(self.min_shared_aps) >= 1, n, "min_shared_aps", "an integer >= 1", self.min_shared_aps)
        require(math.isfinite(self.cov_scale) and self.cov_scale >= 0, n, "cov_scale", ">= 0", self.cov_scale)
        require(math.isfinite(self.cov_floor_m) and self.cov_floor_m > 0, n, "cov_floor_m",
                  "> 0 (a fix covariance must be invertible)", self.cov_floor_m)


class Wknn(Positioner):
    """WKNN positioning against a radio map (see module docstring)."""
    name = "wknn"
    def __init__(self, params: WknnParams | None = None) -> None:
        self.params = params or WknnParams()
        self.params.validate()
        self.radio_map: RadioMap | None = None
        self.aps = ApIndex()
        self._n_map = np.zeros(0)                    # (M,) usable networks per map scan
        self._n_map_floor = np.zeros(0)              # (M,) the same, at least 1 (the shared-fraction divisor)
        self._cov_floor = (self.params.cov_floor_m ** 2) * np.eye(2)
        self._pos = np.zeros((0, 2))                 # (M, 2) map positions, m
        self._readings = ApReadings(np.zeros((0, 0), bool), np.zeros((0, 0)))   # usable RSS (dBm) by AP

    # ------------------------------------------------------------------------------------------
    def fit(self, radio_map: RadioMap) -> "Wknn":
        """Index ``radio_map``: the inverted AP -> readings index (see module docstring)."""
        rss = np.asarray(radio_map.rssi_dbm, float)
        pos = np.asarray(radio_map.positions, float)
        if pos.ndim != 2 or pos.shape[1] != 2 or rss.shape != (len(pos), len(radio_map.bssids)):
            raise MapError(f"wknn: radio map expected positions (M, 2) and rssi (M, A), got {pos.shape}, {rss.shape}")
        if len(pos) == 0:
            raise MapError("wknn: the radio map has no scans")
        usable = rss >= self.params.min_signal_dbm           # NaN (not heard) compares False
        self.radio_map = radio_map
        self.aps = ApIndex(radio_map.bssids)
        self._n_map = usable.sum(axis=1).astype(float)
        self._n_map_floor = np.maximum(self._n_map, 1.0)
        self._pos = pos
        self._readings = ApReadings(usable, rss)
        return self

    @property
    def k_eff(self) -> int:
        return int(self.params.k)

    # ------------------------------------------------------------------------------------------
    def _nearest(self, scan: WifiScan) -> tuple[np.ndarray | None, np.ndarray | str, int]:
        """The k most similar candidate map rows of a scan, most similar first, and their
        similarities: (best (k,), s (k,), candidates), or (None, reason, candidates) when declined.

        Only map rows sharing at least one AP with the scan can be candidates, so the distances,
        shared fractions and the candidate test are evaluated on those rows alone (element by
        element the same arithmetic as over every map row)."""
        p = self.params
        r = np.asarray(scan.rssi_dbm, float)
        ok = np.isfinite(r) & (r >= p.min_signal_dbm)
        n_x = int(np.count_nonzero(ok))
        if n_x == 0:
            return None, "no_usable_aps", 0
        cols = self.aps.columns(scan.bssid)
        keep = ok & (cols >= 0)
        rows, map_vals, lens = self._readings.gather(cols[keep])
        if len(rows) == 0:
            return None, "no_candidates", 0
        m = self._pos.shape[0]
        diff = np.repeat(r[keep], lens) - map_vals
        count = np.bincount(rows, minlength=m)
        et = p.error_type
        acc_all = np.bincount(rows, weights=diff * diff if et in ("l2", "rms") else np.abs(diff), minlength=m)
        idx = np.flatnonzero(count)                       # the rows sharing an AP with the scan
        shared = count[idx].astype(float)
        acc = acc_all[idx]
        if et == "l2":
            d = np.sqrt(acc)
        elif et == "rms":
            d = np.sqrt(acc / np.maximum(shared, 1.0))
        elif et == "mae":
            d = acc / np.maximum(shared, 1.0)
        else:
            d = acc
        frac_x = shared / n_x
        frac_y = shared / self._n_map_floor[idx]
        if p.shared_strict:
            cand = (frac_x > p.shared_threshold) & (frac_y > p.shared_threshold)
        else:
            thr = p.shared_threshold - 1e-12
            cand = (frac_x >= thr) & (frac_y >= thr)
        cand &= (shared >= p.min_shared_aps) & np.isfinite(d)
        sub = d[cand]
        n_cand = len(sub)
        if n_cand == 0:
            return None, "no_candidates", 0
        if n_cand < (p.min_candidates or p.k):
            return None, "few_candidates", n_cand
        idx = idx[cand]
        k = min(p.k, n_cand)
        part = np.argpartition(sub, k - 1)[:k] if k < n_cand else np.arange(n_cand)
        part = part[np.argsort(sub[part], kind="stable")]
        return idx[part], 1.0 / (sub[part] + p.epsilon), n_cand

    def _fix(self, stamp_ns: int, scan: WifiScan, full_info: bool) -> Fix:
        best, s, n_cand = self._nearest(scan)
        if best is None:
            assert isinstance(s, str)
            return Fix(stamp_ns, np.full(2, np.nan), np.full((2, 2), np.nan), ok=False, reason=s,
                       info={"candidates": n_cand})
        assert isinstance(s, np.ndarray)
        p = self.params
        w = s / s.sum()
        f = self._pos[best]
        xy, cov = neighbour_fix(f, w, p.cov_scale, self._cov_floor)
        if not full_info:
            return Fix(stamp_ns, xy, cov, ok=True, info={"rows": best, "weights": w, "similarity": s,
                                                          "candidates": n_cand})
        rm = self.radio_map
        assert rm is not None
        return Fix(stamp_ns, xy, cov, ok=True, info={
            "rows": best, "scan_ids": np.asarray(rm.scan_ids)[best], "weights": w, "similarity": s,
            "positions": f, "sources": [rm.source[i] for i in best], "candidates": n_cand})

    # ------------------------------------------------------------------------------------------
    def locate(self, scan: WifiScan) -> Fix:
        """Position one scan: a Fix with the k neighbours in ``info`` (rows, scan_ids, weights,
        similarity, positions, sources, candidates), or ok=False with a reason."""
        return self.locate_many([scan])[0]

    def locate_many(self, scans: list[WifiScan]) -> list[Fix]:
        """Position a batch of scans (each through the inverted index; same results as ``locate``)."""
        if self.radio_map is None:
            raise MapError("wknn: fit() a radio map before locating")
        return [self._fix(scan.stamp_ns, scan, True) for scan in scans]

    def locate_rows(self, scan: WifiScan) -> Fix:
        """:meth:`locate` with a lighter ``info`` (rows, weights, similarity, candidates): for callers
        that look the matched rows up themselves (the back-end's evolving map, once per scan)."""
        if self.radio_map is None:
            raise MapError("wknn: fit() a radio map before locating")
        return self._fix(scan.stamp_ns, scan, False)
