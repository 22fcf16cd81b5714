"""Estimated trajectories and ground truth for evaluation (pure; no ROS).

Trajectory CSV format (one file per user, ``<user>.csv``, e.g. ``walk07.csv``)::

    stamp_ns,x,y,heading
    484328393044,59.5762,13.5310,1.5708
    ...

- ``stamp_ns``: int nanoseconds on the clock of the input data (for PUTMC: device boot clock);
  rows in non-decreasing stamp order.
- ``x``, ``y``: metres in the ENU map frame ("map"; for PUTMC x = x_img, y = PUTMC_Y0 - y_img).
- ``heading``: yaw, rad, CCW from map x; empty or ``nan`` when unknown.

The user name is the file stem; it is matched with the ground truth's walk name (``walkNN``).
Trajectories can also come from an MCAP bag (see ``indoor_loc/commands/eval.py``): on a topic of
``nav_msgs/Path`` the last message is the trajectory; on ``PoseWithCovarianceStamped`` or
``Odometry`` topics every message adds a pose (header stamp, position, yaw). The namespace of
the topic (``/walk07/wifi/fix``) is the user.

Ground truth (:class:`Truth`) per user: the route as segments (L, 2, 2) m, and the time-stamped
true positions of the WiFi scans (stamps (K,), xy (K, 2)).
"""
from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from indoor_loc.errors import DatasetError, EvalError

CSV_HEADER = ("stamp_ns", "x", "y", "heading")


@dataclass(frozen=True)
class Trajectory:
    """stamps_ns (N,) int64 non-decreasing; xy (N, 2) m map frame; heading (N,) rad (NaN unknown)."""
    name: str
    stamps_ns: np.ndarray
    xy: np.ndarray
    heading: np.ndarray

    @staticmethod
    def make(name: str, stamps_ns: ArrayLike, xy: ArrayLike, heading: ArrayLike | None = None, *,
             sort: bool = True) -> "Trajectory":
        """Validated trajectory; rows sorted by stamp (stable) when ``sort``."""
        t = np.asarray(stamps_ns, dtype=np.int64).ravel()
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        h = np.full(len(t), np.nan) if heading is None else np.asarray(heading, dtype=np.float64).ravel()
        if not (len(t) == len(p) == len(h)):
            raise EvalError(f"trajectory {name}: {len(t)} stamps, {len(p)} positions, {len(h)} headings")
        if not np.all(np.isfinite(p)):
            raise EvalError(f"trajectory {name}: non-finite positions")
        if sort and np.any(np.diff(t) < 0):
            o = np.argsort(t, kind="stable")
            t, p, h = t[o], p[o], h[o]
        elif np.any(np.diff(t) < 0):
            raise EvalError(f"trajectory {name}: stamps go backwards")
        return Trajectory(name, t, p, h)

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass(frozen=True)
class Truth:
    """Ground truth of one user: route segments (L, 2, 2) m; scan_ns (K,) int64 and scan_xy (K, 2) m."""
    name: str
    segments: np.ndarray
    scan_ns: np.ndarray
    scan_xy: np.ndarray


def write_csv(path: str | Path, traj: Trajectory) -> None:
    """Write ``traj`` in the CSV format above (floats with repr, so a round trip is exact)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_HEADER)
    for t, (x, y), h in zip(traj.stamps_ns.tolist(), traj.xy.tolist(), traj.heading.tolist()):
        w.writerow([t, repr(x), repr(y), "" if math.isnan(h) else repr(h)])
    Path(path).write_text(buf.getvalue())


def read_csv(path: str | Path, name: str | None = None) -> Trajectory:
    """Read a trajectory CSV (header ``stamp_ns,x,y,heading``; heading may be empty)."""
    path = Path(path)
    try:
        rows = list(csv.reader(io.StringIO(path.read_text())))
    except OSError as err:
        raise DatasetError(f"cannot read {path}: {err}") from err
    if not rows or tuple(c.strip() for c in rows[0]) != CSV_HEADER:
        raise DatasetError(f"{path}: expected header {','.join(CSV_HEADER)}, got {rows[0] if rows else 'nothing'}")
    t, xy, h = [], [], []
    for i, r in enumerate(rows[1:], start=2):
        if not r:
            continue
        if len(r) != 4:
            raise DatasetError(f"{path}: line {i}: expected 4 fields, got {len(r)}")
        try:
            t.append(int(r[0]))
            xy.append((float(r[1]), float(r[2])))
            h.append(float(r[3]) if r[3].strip() else math.nan)
        except ValueError as err:
            raise DatasetError(f"{path}: line {i}: {err}") from err
    return Trajectory.make(name or path.stem, np.array(t, dtype=np.int64), np.array(xy).reshape(-1, 2), h)


def read_csv_dir(directory: str | Path) -> dict[str, Trajectory]:
    """Every ``<user>.csv`` of a directory, by user name."""
    d = Path(directory)
    if not d.is_dir():
        raise DatasetError(f"trajectory directory {d} does not exist")
    return {p.stem: read_csv(p) for p in sorted(d.glob("*.csv"))}


def truth_from_putmc(root: str | Path, walks: list[int] | None = None, *, keep_stale: bool = False
                     ) -> dict[str, Truth]:
    """Ground truth straight from the PUTMC dataset directory, by walk name (``walkNN``)."""
    from indoor_loc.datasets.putmc import Putmc

    ds = Putmc(root)
    out: dict[str, Truth] = {}
    for n in (walks or ds.walk_numbers):
        w = ds.walk(n, keep_stale=keep_stale)
        out[w.name] = Truth(w.name, ds.routes[n].segments, w.scan_t, w.scan_xy)
    return out
