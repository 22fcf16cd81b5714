"""The map's bounds for the stages that know a map: a map-frame position (``wifi/fix``,
``initialpose``) farther than ``OFF_MAP_MARGIN_M`` outside it is refused as ``off_map`` before any
state is touched (the ``off_map`` row of :data:`indoor_loc.contract.BOUNDS`).

``tll_pf`` bounds by its graph's nodes, ``backend_node`` by its radio map's scan positions; the
linear PDR KF has no map and relies on the adapters' ``map_position`` bound.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from indoor_loc.contract import BOUNDS
from indoor_loc.errors import InvalidInputError


@dataclass(frozen=True)
class MapBox:
    """Axis-aligned box of a map's points, m: ``lo`` (2,) and ``hi`` (2,), with the margin ``margin_m``."""
    lo: tuple[float, float]
    hi: tuple[float, float]
    margin_m: float

    @classmethod
    def around(cls, xy: np.ndarray, margin_m: float | None = None) -> MapBox | None:
        """The box of the finite points ``xy`` (N, 2) m; None when there are none (nothing to bound by)."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if not len(pts):
            return None
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        margin = BOUNDS["off_map"].hi if margin_m is None else float(margin_m)
        return cls((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])), margin)

    def outside_m(self, x: float, y: float) -> float:
        """Distance (m) of (x, y) outside the box (0 inside)."""
        dx = max(self.lo[0] - x, 0.0, x - self.hi[0])
        dy = max(self.lo[1] - y, 0.0, y - self.hi[1])
        return math.hypot(dx, dy)

    def check(self, what: str, xy) -> None:
        """Raise ``off_map`` when ``xy`` (2,) m lies more than the margin outside the box."""
        x, y = float(xy[0]), float(xy[1])
        d = self.outside_m(x, y)
        if d > self.margin_m:
            b = BOUNDS["off_map"]
            raise InvalidInputError(b.reason, f"{what} at ({x:.6g}, {y:.6g}) m is {d:.6g} m outside the map's box "
                                              f"[{self.lo[0]:g}, {self.hi[0]:g}] x [{self.lo[1]:g}, {self.hi[1]:g}] m, "
                                              f"more than {self.margin_m:g} m ({b.why})")
