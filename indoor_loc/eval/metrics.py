"""Trajectory error metrics (pure numpy): route distance, Nowicki & Skrzypczyński 2019 metric, scan-time error.

Three views of one estimated trajectory against a PUTMC-style ground truth (a route made of
segments, plus true positions at time-stamped WiFi scans):

(a) **Paper metric** (Nowicki & Skrzypczyński 2019, Table 2, exactly as its published numbers were
    computed — see ``datasets/README.md``): for every estimated pose, e = the *squared* distance to
    the nearest ground-truth segment, m²; keep e < 100 (distance < 10 m); "RMSE" = sqrt(mean(e²))
    (= sqrt(mean d⁴)) and "mean" = mean(e) (= mean d²), per walk and pooled over all poses.
(b) The same route distances in true metres over the same kept poses: RMSE, mean, median, p95, max.
(c) **Scan-time error**: the trajectory linearly interpolated at each scan stamp vs that scan's
    true position, m: mean / median / p95 / max / RMSE. This sees along-track error, which the
    route metric hides.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from indoor_loc.errors import EvalError

#: The paper keeps poses whose squared route distance is below this, m² (i.e. d < 10 m).
PAPER_MAX_SQ_ERR_M2 = 100.0


def _xy(name: str, xy: ArrayLike) -> np.ndarray:
    a = np.asarray(xy, dtype=np.float64)
    if a.size == 0:
        a = a.reshape(0, 2)
    if a.ndim != 2 or a.shape[1] != 2:
        raise EvalError(f"{name}: expected shape (N, 2), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise EvalError(f"{name}: non-finite values")
    return a


def _segments(segments: ArrayLike) -> np.ndarray:
    s = np.asarray(segments, dtype=np.float64)
    if s.ndim != 3 or s.shape[1:] != (2, 2) or s.shape[0] == 0:
        raise EvalError(f"segments: expected shape (L >= 1, 2, 2), got {s.shape}")
    if not np.all(np.isfinite(s)):
        raise EvalError("segments: non-finite values")
    return s


def point_segment_distance(xy: ArrayLike, segments: ArrayLike) -> np.ndarray:
    """Distance, m, from each point (N, 2) to the nearest of L segments (L, 2, 2) -> (N,).

    Projection clamped to the segment (a zero-length segment is a point)."""
    p = _xy("xy", xy)
    s = _segments(segments)
    a, b = s[:, 0], s[:, 1]                                   # (L, 2)
    ab = b - a
    len2 = np.einsum("ij,ij->i", ab, ab)                      # (L,)
    ap = p[:, None, :] - a[None, :, :]                        # (N, L, 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.einsum("nlk,lk->nl", ap, ab) / len2
    t = np.where(len2 > 0, np.clip(t, 0.0, 1.0), 0.0)
    closest = a[None] + t[..., None] * ab[None]
    d2 = np.sum((p[:, None, :] - closest) ** 2, axis=2)       # (N, L)
    return np.sqrt(d2.min(axis=1)) if len(p) else np.zeros(0)


@dataclass(frozen=True)
class PaperScore:
    """The paper's convention: ``rmse`` = sqrt(mean(e²)), ``mean`` = mean(e), e = d² in m², over
    ``n`` poses with e < 100 (``n_cut`` poses dropped by that cut)."""
    rmse: float
    mean: float
    n: int
    n_cut: int


@dataclass(frozen=True)
class Stats:
    """Error statistics in metres over ``n`` values (NaN when n = 0)."""
    n: int
    rmse: float
    mean: float
    median: float
    p95: float
    max: float

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def stats(d: ArrayLike) -> Stats:
    """RMSE, mean, median, 95th percentile (linear interpolation) and max of distances d (N,), m."""
    d = np.asarray(d, dtype=np.float64).ravel()
    if d.size == 0:
        nan = float("nan")
        return Stats(0, nan, nan, nan, nan, nan)
    return Stats(int(d.size), float(np.sqrt(np.mean(d * d))), float(np.mean(d)), float(np.median(d)),
                 float(np.percentile(d, 95)), float(np.max(d)))


def paper_score(d: ArrayLike, *, max_sq_err_m2: float = PAPER_MAX_SQ_ERR_M2) -> PaperScore:
    """The Nowicki & Skrzypczyński 2019 metric of route distances d (N,) m: e = d², keep e < max_sq_err_m2,
    "RMSE" = sqrt(mean(e²)), "mean" = mean(e) (both in squared units, as published)."""
    d = np.asarray(d, dtype=np.float64).ravel()
    e = d * d
    keep = e < max_sq_err_m2
    ek = e[keep]
    if ek.size == 0:
        return PaperScore(float("nan"), float("nan"), 0, int(d.size))
    return PaperScore(float(np.sqrt(np.mean(ek * ek))), float(np.mean(ek)), int(ek.size), int(d.size - ek.size))


def interpolate_xy(stamps_ns: ArrayLike, xy: ArrayLike, at_ns: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Trajectory (stamps_ns (N,) int increasing, xy (N, 2)) linearly interpolated at at_ns (K,).

    Returns (xy_at (K, 2), inside (K,) bool). Outside [stamps[0], stamps[-1]] the end pose is held
    (``inside`` False there). Stamps are shifted to the first one before the float conversion so
    int64 ns keep their precision."""
    t = np.asarray(stamps_ns, dtype=np.int64).ravel()
    p = _xy("xy", xy)
    q = np.asarray(at_ns, dtype=np.int64).ravel()
    if len(t) != len(p):
        raise EvalError(f"stamps_ns has {len(t)} entries for {len(p)} positions")
    if len(t) == 0:
        raise EvalError("cannot interpolate an empty trajectory")
    if np.any(np.diff(t) < 0):
        raise EvalError("stamps_ns must be non-decreasing")
    t0 = t[0]
    tf, qf = (t - t0).astype(np.float64), (q - t0).astype(np.float64)
    out = np.stack([np.interp(qf, tf, p[:, 0]), np.interp(qf, tf, p[:, 1])], axis=1)
    inside = (q >= t[0]) & (q <= t[-1])
    return out, inside


def scan_time_errors(stamps_ns: ArrayLike, xy: ArrayLike, scan_ns: ArrayLike,
                     scan_xy: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Distance, m, between the trajectory interpolated at each scan stamp and the scan's true
    position: (d (K,), inside (K,) bool — False where the stamp lies outside the trajectory)."""
    truth = _xy("scan_xy", scan_xy)
    est, inside = interpolate_xy(stamps_ns, xy, scan_ns)
    if len(est) != len(truth):
        raise EvalError(f"scan_ns has {len(est)} entries for {len(truth)} true positions")
    return np.linalg.norm(est - truth, axis=1), inside


@dataclass(frozen=True)
class WalkScore:
    """All metrics of one walk (or pooled): paper convention, route distance in metres (over the
    same kept poses), scan-time error in metres; n_scans_outside = scans outside the trajectory."""
    name: str
    n_poses: int
    paper: PaperScore
    route_m: Stats
    scan_m: Stats
    n_scans_outside: int

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "n_poses": self.n_poses, "paper": asdict(self.paper),
                "route_m": self.route_m.as_dict(), "scan_m": self.scan_m.as_dict(),
                "n_scans_outside": self.n_scans_outside}


@dataclass(frozen=True)
class WalkErrors:
    """Raw per-pose route distances and per-scan errors of one walk (pooled by concatenation)."""
    name: str
    route_d: np.ndarray
    scan_d: np.ndarray
    scan_inside: np.ndarray


def walk_errors(name: str, stamps_ns: ArrayLike, xy: ArrayLike, segments: ArrayLike,
                scan_ns: ArrayLike | None = None, scan_xy: ArrayLike | None = None) -> WalkErrors:
    """Route distance of every pose and, when scans are given, the scan-time errors."""
    route_d = point_segment_distance(xy, segments)
    if scan_ns is None or scan_xy is None or len(np.asarray(scan_ns)) == 0:
        scan_d, inside = np.zeros(0), np.zeros(0, dtype=bool)
    else:
        scan_d, inside = scan_time_errors(stamps_ns, xy, scan_ns, scan_xy)
    return WalkErrors(name, route_d, scan_d, inside)


def score(errs: WalkErrors, *, max_sq_err_m2: float = PAPER_MAX_SQ_ERR_M2) -> WalkScore:
    """Metrics (a), (b), (c) of one walk's errors."""
    paper = paper_score(errs.route_d, max_sq_err_m2=max_sq_err_m2)
    kept = errs.route_d[errs.route_d ** 2 < max_sq_err_m2]
    return WalkScore(errs.name, int(errs.route_d.size), paper, stats(kept), stats(errs.scan_d),
                     int(np.sum(~errs.scan_inside)))


def pool(errs: list[WalkErrors], name: str = "pooled") -> WalkErrors:
    """All walks' poses and scans as one set (the paper pools poses, not per-walk scores)."""
    def cat(xs: list[np.ndarray], dt: type) -> np.ndarray:
        return np.concatenate(xs) if xs else np.zeros(0, dtype=dt)
    return WalkErrors(name, cat([e.route_d for e in errs], float), cat([e.scan_d for e in errs], float),
                      cat([e.scan_inside for e in errs], bool))
