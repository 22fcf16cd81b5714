"""One user's floor from the barometer and the WiFi fixes (pure): the floor-change detector and the
floor HMM together, as ``pdr_kf_node`` and ``backend_node`` use them.

Feed :meth:`FloorTrack.baro` every pressure sample and :meth:`FloorTrack.fix` every fix (in stamp
order per kind; the HMM takes evidence at ``max(stamp, newest)`` so its history stays ordered). The
floor heights come from ``floors_m`` when given, else from the fixes (each new fix height is a
floor). Outputs: :meth:`z` (the filtered floor's height and variance, for a pose published now; during a
barometer transit the floor snapped to the barometric height, :mod:`indoor_loc.baro.snap`) and
:meth:`z_at` (smoothed, for a path; a barometer floor change dated back to the middle of its height
ramp, where the walker is nearer the new floor than the old).
"""
from __future__ import annotations

import numpy as np

from indoor_loc.baro.detector import BaroParams, FloorChange, FloorChangeDetector
from indoor_loc.baro.floors import FloorFilter, FloorFilterParams
from indoor_loc.baro.snap import FloorSnap, FloorSnapParams


class FloorTrack:
    def __init__(self, baro: BaroParams | None = None, floors: FloorFilterParams | None = None,
                 floors_m=(), snap: FloorSnapParams | None = None) -> None:
        self.detector = FloorChangeDetector(baro)
        self.filter = FloorFilter(floors_m, floors)
        self.snap = FloorSnap(snap)
        self._snap_ns = 0                   # when the snapped floor last changed
        self.baro_samples = 0
        self.moved = False                  # the last barometer sample changed floor_now()
        self.events: list[FloorChange] = []

    def _at(self, stamp_ns: int) -> int:
        last = self.filter.last_ns
        return stamp_ns if last is None else max(stamp_ns, last)

    def baro(self, stamp_ns: int, pressure_pa: float) -> list[FloorChange]:
        """A pressure sample (Pa): the detector runs; its floor changes move the floor HMM."""
        self.baro_samples += 1
        was = self.floor_now()
        events = self.detector.update(stamp_ns, pressure_pa)
        self.filter.baro_sample(stamp_ns)
        for ev in events:
            self.filter.baro_event(ev._replace(detect_ns=self._at(ev.detect_ns)))
        self.events += events
        before = self.snap.floor
        self.snap.update(self.detector, self.filter.floor_z, self.filter.floor, stamp_ns)
        if self.snap.floor != before:
            self._snap_ns = stamp_ns
        # the floor now changed on this sample (snapped, or a reported change): an estimator that
        # publishes its pose only on steps and fixes publishes it now too (a walker standing in a lift)
        self.moved = self.floor_now() != was and was is not None
        return events

    def floor_now(self) -> int | None:
        """The floor now (index into ``filter.floor_z``): the snapped floor during a barometer
        transit, else the HMM's reported floor; None before any evidence."""
        snapped = self.snap.floor
        return snapped if snapped is not None and snapped < self.filter.n_floors else self.filter.floor

    def fix(self, stamp_ns: int, z: float, z_var: float) -> bool:
        """A fix's floor: height ``z`` (m) with variance ``z_var`` (m²)."""
        return self.filter.fix(stamp_ns, z, z_var)       # (a fix older than a barometer change goes before it)

    def z(self) -> tuple[float, float]:
        """The floor's height (m) and variance (m²) now (:meth:`floor_now`); (0, 0) before any evidence."""
        k = self.floor_now()
        if k is None or k == self.filter.floor:
            return self.filter.z()
        zf = float(self.filter.floor_z[k])
        return zf, float(self.filter.p @ (self.filter.floor_z - zf) ** 2)

    def z_at(self, stamps_ns) -> np.ndarray:
        """Smoothed floor heights (m) at ``stamps_ns``: each barometer floor change takes effect at the
        middle of its height ramp (between its start and end) rather than when it was reported; during
        a transit, stamps since the floor was snapped are on the snapped floor (as :meth:`z`)."""
        st = np.asarray(stamps_ns, np.int64).reshape(-1)
        z = self.filter.z_at(st)
        if not len(st):
            return z
        for ev in self.events:
            mid = ev.start_ns + (ev.end_ns - ev.start_ns) // 2
            sel = (st >= mid) & (st < ev.detect_ns)
            if sel.any():
                z[sel] = self.filter.z_at([ev.detect_ns])[0]
        k = self.snap.floor
        if k is not None and k != self.filter.floor and k < self.filter.n_floors:
            z[st >= self._snap_ns] = self.filter.floor_z[k]      # a transit in progress: the snapped floor
        return z

    def diagnostics(self) -> dict[str, str]:
        f = self.filter
        d: dict[str, str] = {}
        if f.floor is not None and f.n_floors > 1:
            d["floor_z_m"] = f"{f.floor_z[f.floor]:g}"
            d["floor_changes"] = str(f.changes)
        if self.baro_samples:
            s = self.detector.s
            d.update(baro_floor_changes=str(s.changes), baro_spikes=str(s.spikes),
                     baro_in_transit="true" if s.in_transit else "false", baro_floors_snapped=str(self.snap.snaps))
        return d
