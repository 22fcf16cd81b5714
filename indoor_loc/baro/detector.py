"""Floor changes from a phone's barometer (pure numpy): relative height robust to weather drift and
to door/ventilation spikes, and the transits (stairs, lifts) between floors as events.

Pressure samples (Pa) become heights relative to the first sample (:func:`indoor_loc.baro.height.height_change_m`)
and are smoothed by a running median over ``smooth_s`` (white sensor noise and quantisation; the
median also removes spikes shorter than half the window). A *level* height follows the smoothed
height while it stays within ``band_m`` of it, through a first-order filter of time constant
``drift_tau_s``: the weather moves the pressure by about 1 hPa (8 m) an hour, 0.3 m in two
minutes, which the level absorbs, while a walk up a flight of stairs (0.3-0.6 m/s) or a lift ride
(1-2 m/s) leaves the band within seconds. Leaving the band opens a *transit*:

- it is a **spike** (a door, the ventilation: a pressure step that returns) when the height comes
  back into the band — nothing is reported and the level is unchanged;
- it **ends** when the smoothed height has been still for ``hold_s`` (it moved less than ``still_m``
  over the last ``hold_s`` and over its first half): a height change of at least ``min_change_m``
  (about two thirds of a storey) is a :class:`FloorChange` (start = the last sample inside the
  band, end = the start of the still window, ``dh_m`` = still height − level); a smaller one is a
  new level without a floor change (a split level, a lasting ventilation offset) — unless the next
  transit starts within ``merge_s``: then the two are one transit from the older level (a flight of
  stairs walked with a pause on the mid-landing, or slowly enough for the noise to look still).

So a spike has to hold still for ``hold_s`` at more than ``min_change_m`` to be taken for a floor
change; ``hold_s`` (3.5 s) is longer than a door stays open. A floor change is reported
``hold_s`` plus half the median window after the transit ends (about 4.3 s).

The continuous output is :attr:`BaroState.height_m` (smoothed height since the first sample, which
includes the weather drift) with :meth:`FloorChangeDetector.height_std_m`, and
:attr:`BaroState.level_sum_m`, the sum of the reported changes' ``dh_m`` (drift-free, piecewise constant).

Online (:meth:`FloorChangeDetector.update`, one sample at a time) and batch
(:func:`detect_floor_changes`, whole arrays) run the same code; the state can be saved and restored
(:meth:`FloorChangeDetector.state`).
"""
from __future__ import annotations

import copy
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from indoor_loc import params as P
from indoor_loc.baro.height import height_change_m


class FloorChange(NamedTuple):
    """A transit between floors: ``start_ns`` last stamp on the old level, ``end_ns`` first stamp of
    the new level's still window, ``detect_ns`` when it was reported (int ns), ``dh_m`` the height
    change (m, up positive)."""
    start_ns: int
    end_ns: int
    detect_ns: int
    dh_m: float


@dataclass(frozen=True)
class BaroParams:
    """Barometer height and floor-change detection (units in each field's doc)."""
    smooth_s: float = P.field(1.5, "running median window of the heights (s): sensor noise, quantisation, short spikes")
    band_m: float = P.field(1.0, "the level follows the smoothed height within this band (m); leaving it opens a transit")
    drift_tau_s: float = P.field(120.0, "time constant of the level following the weather drift (s)")
    min_change_m: float = P.field(2.2, "smallest height change reported as a floor change (m; ~2/3 of a storey)")
    still_m: float = P.field(0.8, "a transit ends when the smoothed height moved less than this over hold_s (m)")
    hold_s: float = P.field(3.5, "how long the height must stay still to end a transit (s); longer than a door spike")
    merge_s: float = P.field(15.0, "a transit starting this soon after a small level shift continues it (s)")
    noise_m: float = P.field(0.5, "standard deviation of one height sample (m; 0.06 hPa ~ 0.5 m), for height_std_m")
    drift_m_per_s: float = P.field(8.0 / 3600.0, "weather drift of the height (m/s; 1 hPa/h ~ 8 m/h), for height_std_m")

    def validate(self) -> None:
        n = type(self).__name__
        for name in ("smooth_s", "band_m", "drift_tau_s", "min_change_m", "still_m", "hold_s", "noise_m", "merge_s"):
            P.require(getattr(self, name) > 0, n, name, "> 0", getattr(self, name))
        P.require(self.drift_m_per_s >= 0, n, "drift_m_per_s", ">= 0", self.drift_m_per_s)
        P.require(self.min_change_m > self.band_m, n, "min_change_m", "> band_m", self.min_change_m)


@dataclass
class BaroState:
    """What the detector remembers (copyable: save and restore)."""
    p_ref_pa: float | None = None        # pressure of the first sample: heights are relative to it
    t0_ns: int | None = None
    last_ns: int | None = None
    raw: deque = field(default_factory=deque)       # (t_ns, h) of the median window
    smooth: deque = field(default_factory=deque)    # (t_ns, smoothed h) of the last hold_s
    height_m: float = float("nan")       # smoothed height since the first sample (includes drift), m
    level_m: float | None = None         # height of the current level, m
    in_transit: bool = False
    leave_ns: int = 0                    # last stamp inside the band
    level_sum_m: float = 0.0             # sum of the reported floor changes' dh_m
    shift_from_m: float | None = None    # level before the last small level shift (merged with the next transit)
    shift_start_ns: int = 0              # that shift's start
    shift_ns: int = 0                    # when it ended
    spikes: int = 0                      # transits that came back (doors, ventilation)
    level_shifts: int = 0                # transits too small for a floor change
    changes: int = 0


class FloorChangeDetector:
    """Feed :meth:`update` pressure samples in stamp order; it returns the floor changes it reports."""

    def __init__(self, params: BaroParams | None = None, state: BaroState | None = None) -> None:
        self.params = params or BaroParams()
        self.params.validate()
        self.s = state if state is not None else BaroState()

    def state(self) -> BaroState:
        """A copy of the state (restore with ``FloorChangeDetector(params, state)``)."""
        return copy.deepcopy(self.s)

    @property
    def in_transit(self) -> bool:
        return self.s.in_transit

    def height_std_m(self) -> float:
        """Standard deviation (m) of :attr:`BaroState.height_m` as a height change since the first
        sample: the median's noise (``1.25 σ / √n``) and the weather drift since then."""
        s, p = self.s, self.params
        if s.t0_ns is None or s.last_ns is None:
            return float("inf")
        n = max(len(s.raw), 1)
        drift = p.drift_m_per_s * (s.last_ns - s.t0_ns) * 1e-9
        return float(np.hypot(1.25 * p.noise_m / np.sqrt(n), drift))

    def update(self, stamp_ns: int, pressure_pa: float) -> list[FloorChange]:
        """One pressure sample (Pa) at ``stamp_ns`` (int ns, after the previous one)."""
        s, p = self.s, self.params
        if s.p_ref_pa is None:
            s.p_ref_pa = float(pressure_pa)
            s.t0_ns = stamp_ns
        dt = 0.0 if s.last_ns is None else (stamp_ns - s.last_ns) * 1e-9
        s.last_ns = stamp_ns
        h = float(height_change_m(pressure_pa, s.p_ref_pa))
        s.raw.append((stamp_ns, h))
        win = int(p.smooth_s * 1e9)
        while s.raw and s.raw[0][0] <= stamp_ns - win:
            s.raw.popleft()
        hs = float(np.median([v for _, v in s.raw]))
        s.height_m = hs
        s.smooth.append((stamp_ns, hs))
        hold = int(p.hold_s * 1e9)
        while len(s.smooth) > 1 and s.smooth[1][0] <= stamp_ns - hold:
            s.smooth.popleft()
        if s.level_m is None:
            if stamp_ns - (s.t0_ns or stamp_ns) >= win // 2:     # half a window: the median is settled
                s.level_m = hs
                s.leave_ns = stamp_ns
            return []
        dev = hs - s.level_m
        if not s.in_transit:
            if abs(dev) < p.band_m:
                s.level_m += dev * min(1.0, dt / p.drift_tau_s)
                s.leave_ns = stamp_ns
                return []
            s.in_transit = True
            return []
        if abs(dev) < p.band_m:                  # back in the band: a spike
            s.in_transit = False
            s.spikes += 1
            s.leave_ns = stamp_ns
            return []
        t_first, h_first = s.smooth[0]
        if stamp_ns - t_first < hold or t_first < s.leave_ns:
            return []
        h_mid = s.smooth[len(s.smooth) // 2][1]
        if abs(hs - h_first) > p.still_m or abs(h_mid - h_first) > p.still_m:
            return []
        # still for hold_s: the transit is over
        s.in_transit = False
        start, s.leave_ns = s.leave_ns, stamp_ns
        base = s.level_m
        if s.shift_from_m is not None and start - s.shift_ns <= int(p.merge_s * 1e9):
            base, start = s.shift_from_m, s.shift_start_ns          # continues the last small shift
        s.level_m = hs
        dh = hs - base
        if abs(dh) < p.min_change_m:
            s.level_shifts += 1
            s.shift_from_m, s.shift_start_ns, s.shift_ns = base, start, stamp_ns
            return []
        s.shift_from_m = None
        s.changes += 1
        s.level_sum_m += dh
        return [FloorChange(int(start), int(t_first), int(stamp_ns), float(dh))]


def detect_floor_changes(stamps_ns: np.ndarray, pressure_pa: np.ndarray, params: BaroParams | None = None
                         ) -> tuple[list[FloorChange], np.ndarray]:
    """Batch: the floor changes of a whole pressure record (stamps (N,) int ns ascending, pressure
    (N,) Pa) and the smoothed relative height (N,) m — the online detector run over the arrays."""
    det = FloorChangeDetector(params)
    events: list[FloorChange] = []
    h = np.empty(len(stamps_ns))
    for k, (t, pr) in enumerate(zip(np.asarray(stamps_ns, np.int64).tolist(), np.asarray(pressure_pa, float).tolist())):
        events += det.update(int(t), pr)
        h[k] = det.s.height_m
    return events, h
