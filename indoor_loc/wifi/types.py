"""Core WiFi types shared by ingestion, radio maps and every positioning method (pure numpy); a
method's output, :class:`~indoor_loc.measurements.Fix`, is a measurement shared by every estimator."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

import numpy as np

from indoor_loc.measurements import Fix

__all__ = ["ApIndex", "ApReadings", "Positioner", "RadioMap", "WifiScan"]


@dataclass(frozen=True)
class WifiScan:
    """One scan. ``bssid`` lower-case colon-separated, unique; arrays have one entry per AP.

    rssi_dbm: received signal strength, dBm, shape (n,); freq_mhz: channel centre frequency, MHz,
    shape (n,); age_ms: how old each reading was at ``stamp_ns`` (None when unknown).
    """
    stamp_ns: int
    bssid: tuple[str, ...]
    rssi_dbm: np.ndarray
    freq_mhz: np.ndarray
    ssid: tuple[str, ...] = ()
    age_ms: np.ndarray | None = None
    frame_id: str = ""
    source: str = ""

    def __len__(self) -> int:
        return len(self.bssid)

    def as_dict(self) -> dict[str, float]:
        return {b: float(r) for b, r in zip(self.bssid, self.rssi_dbm)}


@dataclass
class RadioMap:
    """Fingerprints: M scans at known positions over A access points.

    positions: (M, 2) metres, map frame (ENU, x east/right, y north/up).
    bssids: list of A lower-case BSSIDs (column order); ssids: same length.
    rssi_dbm: (M, A) float, NaN where the AP was not heard in that scan.
    freq_mhz: (A,) per-AP frequency (0 if unknown).
    scan_ids: (M,) int identifiers; stamps_ns: (M,) int (0 for a pre-surveyed map);
    source: (M,) str label, e.g. "survey" or the user/walk a fingerprint was learnt from.
    z_m: (M,) float, the floor height of each scan, m (0 on a single-floor map); ``floors`` names
    the heights (``{"B1": -5.0, "F3": 10.0}``, empty on a single-floor map).
    age_ms: (M, A) float, how old each reading was when its scan was taken (a cached result),
    NaN where unknown or not heard; None when no reading has an age.
    """
    positions: np.ndarray
    bssids: list[str]
    rssi_dbm: np.ndarray
    freq_mhz: np.ndarray
    ssids: list[str] = field(default_factory=list)
    scan_ids: np.ndarray = None  # type: ignore[assignment]  # None -> filled in by __post_init__
    stamps_ns: np.ndarray = None  # type: ignore[assignment]  # None -> filled in by __post_init__
    source: list[str] = field(default_factory=list)
    frame_id: str = "map"
    z_m: np.ndarray = None  # type: ignore[assignment]  # None -> filled in by __post_init__
    floors: dict[str, float] = field(default_factory=dict)
    age_ms: np.ndarray | None = None

    def __post_init__(self) -> None:
        m = len(self.positions)
        if self.z_m is None:
            self.z_m = np.zeros(m)
        if self.scan_ids is None:
            self.scan_ids = np.arange(m)
        if self.stamps_ns is None:
            self.stamps_ns = np.zeros(m, dtype=np.int64)
        if not self.source:
            self.source = ["survey"] * m
        if not self.ssids:
            self.ssids = [""] * len(self.bssids)

    @property
    def n_scans(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_aps(self) -> int:
        return len(self.bssids)

    def ap_index(self) -> "ApIndex":
        """BSSID -> column of this map (a new index; it does not follow later edits of the map)."""
        return ApIndex(self.bssids)


class ApIndex:
    """BSSID -> column in a radio map's AP order, shared by the positioning methods; grows when a
    method learns new APs (``add``)."""

    def __init__(self, bssids: Iterable[str] = ()) -> None:
        self.bssids: list[str] = list(bssids)
        self._col = {b: i for i, b in enumerate(self.bssids)}

    def __len__(self) -> int:
        return len(self.bssids)

    def columns(self, bssids: Sequence[str]) -> np.ndarray:
        """Columns (K,) int64 of the given BSSIDs, -1 for APs not in the index."""
        get = self._col.get
        return np.fromiter((get(b, -1) for b in bssids), dtype=np.int64, count=len(bssids))

    def add(self, bssid: str) -> int:
        """The column of ``bssid``, appended as a new column if unknown."""
        j = self._col.get(bssid)
        if j is None:
            j = self._col[bssid] = len(self.bssids)
            self.bssids.append(bssid)
        return j


class ApReadings:
    """Inverted index of a radio map's readings by AP: for each column (AP) the map rows that hold a
    reading and its value, in CSR-by-column layout (``ptr`` (A + 1,), ``row`` (R,), ``val`` (R,)).
    A query touches only the readings of its own APs, so fingerprint methods cost O(M q density)
    per scan instead of O(M A). Row numbers are int32 (half the memory traffic of int64 in every
    gather) and the arrays of a sparse matrix are taken as they are, without copies."""

    #: mean readings per asked column above which :meth:`gather` copies whole runs (slices) instead of
    #: indexing element by element
    RUN_COPY = 48

    def __init__(self, mask: np.ndarray, values: np.ndarray) -> None:
        """``mask`` (M, A) bool: which readings count; ``values`` (M, A): their values."""
        cols, rows = np.nonzero(np.asarray(mask, bool).T)
        self.ptr = np.searchsorted(cols, np.arange(mask.shape[1] + 1)).astype(np.int64)
        self.row = rows.astype(np.int32)
        self.val = np.asarray(values, float)[rows, cols]

    @classmethod
    def from_sparse(cls, matrix: Any) -> "ApReadings":
        """From a scipy sparse (M, A) matrix whose stored non-zero entries are the readings."""
        from scipy import sparse
        csc = sparse.csc_matrix(matrix)
        csc.eliminate_zeros()
        csc.sort_indices()
        out = cls.__new__(cls)
        out.ptr = csc.indptr.astype(np.int64, copy=False)
        out.row = csc.indices.astype(np.int32, copy=False)
        out.val = csc.data.astype(float, copy=False)
        return out

    def gather(self, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The readings of columns ``cols`` (q,): map rows (R',), values (R',) and per-column counts
        (q,) (the readings of ``cols[i]`` are the i-th run of ``lens[i]`` entries)."""
        start, stop = self.ptr[cols], self.ptr[cols + 1]
        lens = stop - start
        total = int(lens.sum())
        if len(cols) and total >= self.RUN_COPY * len(cols):      # long runs: one memcpy per column
            s, e = start.tolist(), stop.tolist()
            return (np.concatenate([self.row[a:b] for a, b in zip(s, e)]),
                    np.concatenate([self.val[a:b] for a, b in zip(s, e)]), lens)
        offs = np.repeat(start - np.cumsum(lens) + lens, lens) + np.arange(total)
        return self.row[offs], self.val[offs], lens


class Positioner:
    """Interface of every WiFi positioning method (WKNN, path loss, coverage area).

    ``fit(radio_map)`` once (and again when the map grows); ``locate(scan)`` per scan returns a
    :class:`Fix` with an honest covariance, or ``ok=False`` with a reason.
    """
    name: str = "positioner"

    def fit(self, radio_map: RadioMap) -> "Positioner":
        raise NotImplementedError

    def locate(self, scan: WifiScan) -> Fix:
        raise NotImplementedError

    def locate_many(self, scans: list[WifiScan]) -> list[Fix]:
        return [self.locate(s) for s in scans]
