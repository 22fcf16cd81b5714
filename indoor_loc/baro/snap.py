"""The floor during a barometer transit (pure): the barometric height as a continuous state, the floor
snapped to it with a storey hysteresis.

:class:`~indoor_loc.baro.detector.FloorChangeDetector` reports a floor change only once the height
has been still for ``hold_s`` after the transit (about 4 s after the walker arrives: a door spike must
not pass for a floor). The height itself is known all along: during a transit the detector's level
is frozen at the drift-corrected height of the floor left (the weather drift is absorbed only while
the height is level), so ``z_anchor + (height − level)`` is the walker's height in the map, where
``z_anchor`` is the height of the floor the transit started from. The snap keeps its own floor
height (``base_tau_s``, 20 s) rather than the detector's level (120 s, which lags a fast weather
change by most of a metre) and freezes it when the transit opens. :class:`FloorSnap` moves the
floor to a neighbouring storey when that height passes the midpoint between the two by
``hysteresis`` of the storey (0.7 of a storey up or down with the default 0.2), one storey at a
time and back the same way, so on stairs or in a lift the floor changes before the walker arrives,
and two flights walked without a stop are two storeys.

A door or the ventilation moves the pressure as a *step*, a walker or a lift as a *ramp*: the
height cannot climb from the detector's band to the snapping height faster than
``max_vertical_speed_mps`` (office lifts move at 1-2.5 m/s). A transit whose smoothed height got
there faster is a step: it snaps nothing (the detector decides at its end, as without the snap).
And the height must still
be moving when it leaves the start floor (``min_vertical_speed_mps`` over the last second): a
pressure plateau that noise carries across the snapping height is not a walker on the way. When the transit ends (a floor
change reported, a spike that came back, a small level shift) the snap is over and the floor is the
floor HMM's again (:class:`~indoor_loc.baro.floors.FloorFilter`, which takes the reported change).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from indoor_loc import params as P
from indoor_loc.baro.detector import FloorChangeDetector


@dataclass(frozen=True)
class FloorSnapParams:
    """The floor snapped to the barometric height during a transit (see the module docstring)."""
    enabled: bool = P.field(True, "snap the floor to the barometric height during a transit (false: the floor "
                                  "changes only when the detector reports the change, ~4 s after arrival)")
    hysteresis: float = P.field(0.2, "the height must pass the midpoint between two floors by this fraction of "
                                     "the storey to snap to the other floor (and back): 0.7 of a 3.5 m storey = 2.45 m, above most door "
                                     "pressure steps (up to 0.25 hPa ~ 2.1 m)")
    base_tau_s: float = P.field(20.0, "time constant (s) of the floor's height following the weather drift while "
                                      "level (faster than the detector's level: its lag is part of the margin)")
    min_vertical_speed_mps: float = P.field(0.25, "slowest climb (m/s; stairs 0.3-0.6 m/s): leaving the start floor "
                                                  "the height must still be moving this fast (not a plateau)")
    max_vertical_speed_mps: float = P.field(2.5, "fastest plausible climb (m/s; office lifts 1-2.5 m/s): a height "
                                                 "reaching the snapping height faster is a pressure step (a door)")

    def validate(self) -> None:
        n = type(self).__name__
        P.require(0 <= self.hysteresis < 0.5, n, "hysteresis", "in [0, 0.5)", self.hysteresis)
        P.require(self.base_tau_s > 0, n, "base_tau_s", "> 0", self.base_tau_s)
        P.require(self.min_vertical_speed_mps >= 0, n, "min_vertical_speed_mps", ">= 0", self.min_vertical_speed_mps)
        P.require(self.max_vertical_speed_mps > 0, n, "max_vertical_speed_mps", "> 0", self.max_vertical_speed_mps)


class FloorSnap:
    """Call :meth:`update` after every detector update; :attr:`floor` is the snapped floor (an index
    into the floor heights given) during a transit, None otherwise."""

    def __init__(self, params: FloorSnapParams | None = None) -> None:
        self.params = params or FloorSnapParams()
        self.params.validate()
        self.anchor: int | None = None       # floor the transit started from
        self.floor: int | None = None
        self.step = False                    # this transit rose too fast: a pressure step
        self.base: float | None = None       # smoothed height of the floor stood on (m, drift followed)
        self._base_ns: int | None = None
        self._transit_base: float | None = None   # base at the start of this transit
        self._shift_base: float | None = None     # base at the start of the last transit
        self._ramp_ns = 0
        self._changes = 0                    # detector changes seen (a new one: the base is its new level)
        self.snaps = 0                       # floors snapped (diagnostics)
        #: the walker's barometric height in ``map`` during a transit (``z_anchor + h − h_base``, m) once
        #: the floor has been snapped (the transit ramped like a walker or a lift), and when its transit
        #: started (ns); None otherwise (level, before the snap, a door's pressure step or plateau)
        self.height_z: float | None = None
        self.ramp_ns = 0
        self.steps = 0                       # transits taken for pressure steps

    def _reset(self) -> None:
        if self._transit_base is not None:
            self._shift_base = self._transit_base    # a small shift's start height, for a merge
        self.anchor = self.floor = None
        self.step = False
        self._transit_base = None
        self.height_z = None

    def update(self, det: FloorChangeDetector, floor_z: np.ndarray, base_floor: int | None, stamp_ns: int
               ) -> int | None:
        """The detector ``det`` has just taken the sample at ``stamp_ns``; ``floor_z`` (F,) the floor
        heights (ascending), ``base_floor`` the floor now believed (the transit's start floor when a
        transit opens). Returns :attr:`floor`."""
        s, dp = det.s, det.params
        if s.changes != self._changes:
            # a reported floor change: the new floor's height is the detector's new level (following it
            # from the old floor's at base_tau_s left the base metres off for the next transit)
            self._changes = s.changes
            if s.level_m is not None and np.isfinite(s.level_m):
                self.base, self._base_ns = float(s.level_m), stamp_ns
        # a small level shift the next transit may still continue (stairs with a pause: the detector
        # merges them within merge_s): the transit is not over for the snap either
        pending = (not det.in_transit and not self.step and self._transit_base is not None
                   and s.shift_from_m is not None and stamp_ns - s.shift_ns <= int(dp.merge_s * 1e9))
        if not det.in_transit and not pending and s.level_m is not None and np.isfinite(s.height_m):
            # the height of the floor, following the weather faster than the detector's level
            a = 1.0 if self.base is None or self._base_ns is None else \
                min(1.0, (stamp_ns - self._base_ns) * 1e-9 / self.params.base_tau_s)
            self.base = s.height_m if self.base is None else self.base + a * (s.height_m - self.base)
            self._base_ns = stamp_ns
        if (not self.params.enabled or not (det.in_transit or pending) or s.level_m is None or base_floor is None
                or len(floor_z) < 2 or self.base is None):
            self._reset()
            return None
        if self.anchor is None:
            if base_floor >= len(floor_z):
                return None
            self.anchor = self.floor = int(base_floor)
        if self.step:
            self.height_z = None
            return self.floor
        if self._transit_base is None:
            self._transit_base, self._ramp_ns = self.base, s.leave_ns
            if s.shift_from_m is not None and s.leave_ns - s.shift_ns <= int(dp.merge_s * 1e9):
                # the detector merges this transit with the small shift before (stairs with a pause)
                self._transit_base = self._shift_base if self._shift_base is not None else s.shift_from_m
                self._ramp_ns = s.shift_start_ns
        base, ramp_ns = self._transit_base, self._ramp_ns
        z = float(floor_z[self.anchor]) + (s.height_m - base)
        h = self.params.hysteresis
        while self.floor is not None:
            cur = self.floor
            nb = cur + (1 if z > floor_z[cur] else -1)
            if not 0 <= nb < len(floor_z):
                break
            gap = abs(float(floor_z[nb] - floor_z[cur]))
            if abs(z - float(floor_z[cur])) <= (0.5 + h) * gap:
                break
            if nb != self.anchor and cur == self.anchor:
                # leaving the start floor: the height must have ramped, not stepped
                rise = (0.5 + h) * gap - dp.band_m
                if (stamp_ns - ramp_ns) * 1e-9 < rise / self.params.max_vertical_speed_mps:
                    self.step = True
                    self.steps += 1
                    break
                if not self._climbing(det, stamp_ns, nb - cur):
                    break                           # a plateau near the snapping height: not yet
            self.floor = nb
            self.snaps += 1
        # the height is the walker's once the floor has been snapped (a ride: ramped, still moving, past
        # 0.7 storey); before that a door's pressure step or plateau could pass for one
        self.height_z = z if self.floor != self.anchor and not self.step else None
        self.ramp_ns = ramp_ns
        return self.floor

    def _climbing(self, det: FloorChangeDetector, stamp_ns: int, sign: int) -> bool:
        """The smoothed height rose (``sign`` > 0; fell for < 0) by ``min_vertical_speed_mps`` over the
        last second: a walker or a lift still on the way, not a pressure plateau near the threshold."""
        past = [h for t, h in det.s.smooth if t <= stamp_ns - 10**9]
        if not past:
            return False
        return sign * (det.s.height_m - past[-1]) >= self.params.min_vertical_speed_mps
