"""The floor as a discrete state (pure numpy): a hidden Markov model over the building's floors,
fed by the WiFi fixes' floors and the barometer's floor changes, filtered online and smoothed.

States: the floors, by height ``z_f`` (m). Evidence:

- a **fix** on floor ``k`` (``Fix.z`` = its height, ``Fix.z_var`` = the floor detector's variance):
  ``P(fix says k | floor j) = 1 − w`` for ``j = k`` and ``w / (F − 1)`` otherwise, with the
  floor-detection confidence ``w = clip(z_var / Δz², fix_wrong_min, 1 − 1/F)`` (Δz the smallest
  storey: a detector sure of its floor has ``z_var = 0``, one split between two floors ``Δz²/4``);
- a **barometer floor change** (:class:`~indoor_loc.baro.detector.FloorChange`, ``dh_m``): the
  transition ``P(j → k) ∝ exp(−(dh − (z_k − z_j))² / 2σ²)`` over every floor ``k`` (``k = j``, no
  change, included), mixed with ``event_miss`` of staying
  — the discrete form of the Δz barometer factor between consecutive poses of seed 003's smoother;
- between them, time: the floor changes by an adjacent storey at ``change_rate_per_s`` (no
  barometer; a continuous-time chain, ``T = expm(Q Δt)``), or at ``baro_quiet_rate_per_s`` while a
  barometer is reporting and says nothing (it sees every transit, so a change it did not report is
  nearly impossible).

The **reported floor** changes only on evidence: when another floor's probability exceeds
``switch_prob`` (three consistent fixes from a confident WiFi floor detector), or at a barometer
change when another floor is the more probable (a floor known from a single fix is not sure enough
for ``switch_prob`` after the change, but the change is decisive). :meth:`FloorFilter.smoothed`
runs the forward-backward recursion over the history (the paths of ``pdr_kf`` and ``backend_node``).

Floors are learnt from the evidence when not given (when given, from a map, only fixes add floors):
a fix at a height no floor has (farther than ``new_floor_m``) adds a floor; so does a barometer
floor change leading from the reported floor to a height no floor has (at the reported floor's
height + ``dh``, replaced by the first fix's height near it). Heights are metres in the map frame.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from indoor_loc import params as P
from indoor_loc.baro.detector import FloorChange


#: a fix stamped this much (s) before the newest barometer change is no longer put back before it
LATE_FIX_S = 60.0


@dataclass(frozen=True)
class FloorFilterParams:
    """Floor estimation from WiFi fixes and barometer floor changes."""
    fix_wrong_min: float = P.field(0.1, "smallest probability that a fix's floor is wrong (a sure detector is "
                                        "still wrong sometimes: the powed detector on simulated multi-floor walks, "
                                        "transits included, about 1 in 8)")
    switch_prob: float = P.field(0.9, "the reported floor changes when another floor is more probable than this")
    change_rate_per_s: float = P.field(0.01, "without a barometer: rate of moving to an adjacent floor (1/s)")
    baro_quiet_rate_per_s: float = P.field(1e-4, "with a barometer reporting and no floor change: rate of a floor "
                                                 "change it missed (1/s)")
    baro_timeout_s: float = P.field(10.0, "the barometer counts as reporting while samples arrive within this (s)")
    event_sigma_m: float = P.field(1.2, "standard deviation of a barometer floor change's dh against the storeys "
                                        "(m): sensor noise, drift during the transit, storeys of unequal height")
    event_miss: float = P.field(0.02, "probability that a barometer floor change is not one (the floor stays)")
    new_floor_m: float = P.field(1.0, "a fix this far (m) from every known floor height adds a floor")
    min_storey_m: float = P.field(2.5, "a barometer floor change adds a floor only this far (m) from every known "
                                       "floor (a partly seen transit must not invent a floor between two)")
    history_max: int = P.field(20000, "entries kept for smoothing (the newest)")
    heights_m: list[float] = P.field([], "the building's floor heights (m in map: the radio map manifest's or the "
                                         "graph file's floors); empty: learnt from the fixes' heights. Known floors "
                                         "let the barometer snap the floor during a transit to a floor no fix has "
                                         "named yet")

    def validate(self) -> None:
        n = type(self).__name__
        P.require(0 < self.fix_wrong_min < 0.5, n, "fix_wrong_min", "in (0, 0.5)", self.fix_wrong_min)
        P.require(0.5 <= self.switch_prob < 1, n, "switch_prob", "in [0.5, 1)", self.switch_prob)
        for name in ("change_rate_per_s", "baro_quiet_rate_per_s"):
            P.require(0 <= getattr(self, name) < 1, n, name, "in [0, 1)", getattr(self, name))
        P.require(self.baro_timeout_s > 0, n, "baro_timeout_s", "> 0", self.baro_timeout_s)
        P.require(self.event_sigma_m > 0, n, "event_sigma_m", "> 0", self.event_sigma_m)
        P.require(0 <= self.event_miss < 1, n, "event_miss", "in [0, 1)", self.event_miss)
        P.require(self.new_floor_m > 0, n, "new_floor_m", "> 0", self.new_floor_m)
        P.require(self.min_storey_m > 0, n, "min_storey_m", "> 0", self.min_storey_m)
        P.require(self.history_max >= 1, n, "history_max", ">= 1", self.history_max)
        h = np.asarray(self.heights_m, float).reshape(-1)
        P.require(bool(np.all(np.isfinite(h))) and len(np.unique(h)) == len(h), n, "heights_m",
                  "distinct finite heights", self.heights_m)


class FloorFilter:
    """Online floor HMM (see the module docstring). Feed :meth:`fix`, :meth:`baro_sample` and
    :meth:`baro_event` in stamp order; read :attr:`floor` (index into :attr:`floor_z`), :meth:`z`."""

    def __init__(self, floor_z=(), params: FloorFilterParams | None = None) -> None:
        self.params = params or FloorFilterParams()
        self.params.validate()
        self.floor_z = np.sort(np.asarray(floor_z, float).reshape(-1))
        if not len(self.floor_z):
            self.floor_z = np.sort(np.asarray(self.params.heights_m, float).reshape(-1))
        self.map_floors = len(self.floor_z) > 0              # floors from a map: the barometer adds none
        self.learnt = np.zeros(len(self.floor_z), bool)      # floors placed by the barometer, not a fix or the map
        self.p = np.full(len(self.floor_z), 1.0 / max(len(self.floor_z), 1))
        self.floor: int | None = None
        self.last_ns: int | None = None
        self.baro_ns: int | None = None
        self.changes = 0
        #: (stamp_ns, transition (F, F) from the previous entry, filtered p (F,))
        self.history: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._appended = 0                  # history entries ever appended
        # a fix stamped before the newest barometer change but arriving after it (a node that takes
        # fixes through a reorder window, pressure at once): the filter as it was just before that
        # change, and the evidence taken since (the change included), to take them again in stamp order
        self._pre_event: tuple | None = None
        self._since: list[tuple] = []
        self.late_fixes = 0                 # fixes put back before a barometer change they came after

    # -- floors --------------------------------------------------------------------------------
    @property
    def n_floors(self) -> int:
        return len(self.floor_z)

    def _storey(self) -> float:
        return float(np.min(np.diff(self.floor_z))) if self.n_floors > 1 else 3.0

    def nearest(self, z: float) -> int | None:
        """Index of the floor at height ``z`` (None when none is within ``new_floor_m``)."""
        if not self.n_floors:
            return None
        k = int(np.argmin(np.abs(self.floor_z - z)))
        return k if abs(self.floor_z[k] - z) <= self.params.new_floor_m else None

    def add_floor(self, z: float) -> int:
        """A new floor at height ``z`` (m), with a small prior; returns its index."""
        k = int(np.searchsorted(self.floor_z, z))
        self.floor_z = np.insert(self.floor_z, k, float(z))
        self.learnt = np.insert(self.learnt, k, False)
        prior = 1e-3 if len(self.p) else 1.0
        self.p = np.insert(self.p * (1.0 - prior if len(self.p) else 1.0), k, prior)
        self.p /= self.p.sum()
        if self.floor is not None and self.floor >= k:
            self.floor += 1
        self.history = [(t, np.insert(np.insert(T, k, 0.0, axis=0), k, 0.0, axis=1) if T.size else T,
                         np.insert(a, k, 0.0)) for t, T, a in self.history]
        for _t, T, _ in self.history:
            if T.size:
                T[k, k] = 1.0
        return k

    # -- time ----------------------------------------------------------------------------------
    def baro_live(self, stamp_ns: int) -> bool:
        return self.baro_ns is not None and stamp_ns - self.baro_ns <= int(self.params.baro_timeout_s * 1e9)

    def _diffusion(self, stamp_ns: int) -> np.ndarray:
        f = self.n_floors
        dt = 0.0 if self.last_ns is None else max(stamp_ns - self.last_ns, 0) * 1e-9
        rate = self.params.baro_quiet_rate_per_s if self.baro_live(stamp_ns) else self.params.change_rate_per_s
        Q = rate * (np.eye(f, k=1) + np.eye(f, k=-1))      # generator: to each adjacent floor at ``rate``
        Q[np.diag_indices(f)] = -Q.sum(axis=1)
        T = expm(Q * dt)                                    # over a long gap, two storeys are possible too
        return np.clip(T, 0.0, None) / np.clip(T, 0.0, None).sum(axis=1, keepdims=True)

    def _step(self, stamp_ns: int, T: np.ndarray, lik: np.ndarray | None) -> None:
        T = self._diffusion(stamp_ns) @ T
        p = self.p @ T
        if lik is not None:
            p = p * lik
        s = p.sum()
        self.p = p / s if s > 0 else np.full(self.n_floors, 1.0 / self.n_floors)
        self.last_ns = stamp_ns if self.last_ns is None else max(self.last_ns, stamp_ns)
        self.history.append((stamp_ns, T, self.p.copy()))
        self._appended += 1
        if len(self.history) > self.params.history_max:
            del self.history[:len(self.history) - self.params.history_max]
        self._decide()

    def _decide(self, switch_prob: float | None = None) -> None:
        k = int(np.argmax(self.p))
        if self.floor is None:
            if self.p[k] >= 0.5:
                self.floor = k
        elif k != self.floor and self.p[k] > (self.params.switch_prob if switch_prob is None else switch_prob):
            self.floor = k
            self.changes += 1

    # -- evidence ------------------------------------------------------------------------------
    def fix(self, stamp_ns: int, z: float, z_var: float = 0.0) -> bool:
        """A WiFi fix's floor (height ``z`` m, variance ``z_var`` m²). Returns False when the fix
        carries no usable floor (non-finite). A fix stamped before the newest barometer change
        (within ``LATE_FIX_S`` of it) is taken before it: the filter goes back to just before the
        change and takes the evidence since in stamp order; an older one counts at the newest stamp."""
        if not (np.isfinite(z) and np.isfinite(z_var)):
            return False
        pre = self._pre_event
        if pre is not None and self.last_ns is not None and self.last_ns - pre[0] > LATE_FIX_S * 1e9:
            pre = self._pre_event = None
            self._since = []
        if pre is not None and stamp_ns < pre[0] and pre[7] == self.n_floors and \
                self._appended - pre[6] <= len(self.history):
            self.late_fixes += 1
            evidence = sorted(self._since + [(stamp_ns, 0, "fix", (z, z_var))], key=lambda e: (e[0], e[1]))
            _, p, self.floor, self.last_ns, _, self.changes, appended, _ = pre
            self.p = p.copy()
            if self._appended > appended:
                del self.history[len(self.history) - (self._appended - appended):]
            self._appended = appended
            for st, _, kind, args in evidence:
                if kind == "fix":
                    self._fix(st if self.last_ns is None else max(st, self.last_ns), *args)
                else:
                    self._event(args)
            self._since = evidence
            return True
        if pre is not None:
            self._since.append((stamp_ns, 0, "fix", (z, z_var)))
        return self._fix(stamp_ns if self.last_ns is None else max(stamp_ns, self.last_ns), z, z_var)

    def _fix(self, stamp_ns: int, z: float, z_var: float) -> bool:
        k = self.nearest(z)
        if k is None:
            k = self.add_floor(z)
        elif self.learnt[k]:                      # a floor the barometer placed: the map's height now
            self.floor_z[k], self.learnt[k] = float(z), False
        f = self.n_floors
        if f == 1:
            self._step(stamp_ns, np.eye(1), None)
            return True
        w = float(np.clip(max(z_var, 0.0) / self._storey() ** 2, self.params.fix_wrong_min, 1.0 - 1.0 / f))
        lik = np.full(f, w / (f - 1))
        lik[k] = 1.0 - w
        self._step(stamp_ns, np.eye(f), lik)
        return True

    def baro_sample(self, stamp_ns: int) -> None:
        """A barometer sample arrived (the barometer is reporting)."""
        self.baro_ns = stamp_ns

    def event_transition(self, dh_m: float) -> np.ndarray:
        """(F, F) transition of a barometer floor change of ``dh_m`` (see the module docstring)."""
        pp = self.params
        dz = self.floor_z[None, :] - self.floor_z[:, None]
        # every floor, the floor it starts from included (dz = 0), by how well it explains dh: a
        # change of 1.7 storeys is two storeys or one, not "no change" (before, a change far from
        # every storey was mixed with staying as a whole: a two-storey ride measured 6.1 m left a
        # quarter of the mass on the start floor)
        g = np.exp(-0.5 * ((dh_m - dz) / pp.event_sigma_m) ** 2)
        s = g.sum(axis=1, keepdims=True)
        T = np.where(s > 1e-12, g / np.maximum(s, 1e-300), 0.0)
        stay = np.where(s[:, 0] > 1e-12, pp.event_miss, 1.0)       # nowhere near: stay
        T = T * (1.0 - stay)[:, None]
        T[np.diag_indices_from(T)] += stay
        return T

    def baro_event(self, ev: FloorChange) -> None:
        """A barometer floor change, applied at its detection stamp."""
        self._pre_event = (ev.detect_ns, self.p.copy(), self.floor, self.last_ns, self.baro_ns, self.changes,
                           self._appended, self.n_floors)
        self._since = [(ev.detect_ns, 1, "event", ev)]
        self._event(ev)

    def _event(self, ev: FloorChange) -> None:
        self.baro_ns = ev.detect_ns if self.baro_ns is None else max(self.baro_ns, ev.detect_ns)
        target = self.floor_z[self.floor] + ev.dh_m if self.floor is not None else None
        if (target is not None and not self.map_floors
                and np.min(np.abs(self.floor_z - target)) >= self.params.min_storey_m):
            k = self.add_floor(float(self.floor_z[self.floor] + ev.dh_m))
            self.learnt[k] = True
        if self.n_floors < 2:
            return
        self._step(ev.detect_ns, self.event_transition(ev.dh_m), None)
        self._decide(switch_prob=0.5)             # a barometer change is decisive: the more probable floor

    # -- outputs -------------------------------------------------------------------------------
    def z(self) -> tuple[float, float]:
        """Height (m) of the reported floor and its variance (m², from the floor probabilities);
        (0, 0) before any evidence."""
        if self.floor is None:
            return 0.0, 0.0
        zf = float(self.floor_z[self.floor])
        return zf, float(self.p @ (self.floor_z - zf) ** 2)

    def smoothed(self) -> tuple[np.ndarray, np.ndarray]:
        """Forward-backward over the history: stamps (T,) int ns and smoothed probabilities (T, F)."""
        h = self.history
        if not h:
            return np.zeros(0, np.int64), np.zeros((0, self.n_floors))
        g = np.empty((len(h), self.n_floors))
        g[-1] = h[-1][2]
        for t in range(len(h) - 2, -1, -1):
            a, T = h[t][2], h[t + 1][1]
            pred = a @ T
            ratio = np.divide(g[t + 1], pred, out=np.zeros_like(pred), where=pred > 1e-300)
            v = a * (T @ ratio)
            g[t] = v / v.sum() if v.sum() > 0 else a
        return np.array([e[0] for e in h], np.int64), g

    def z_at(self, stamps_ns, *, smooth: bool = True) -> np.ndarray:
        """Height (m) of the most probable floor at each stamp (the newest history entry at or before
        it; the first entry's before the history), smoothed or filtered; 0 without evidence."""
        st = np.asarray(stamps_ns, np.int64).reshape(-1)
        if not self.history or self.floor is None:
            return np.zeros(len(st))
        if smooth:
            t, g = self.smoothed()
        else:
            t = np.array([e[0] for e in self.history], np.int64)
            g = np.array([e[2] for e in self.history])
        idx = np.clip(np.searchsorted(t, st, side="right") - 1, 0, len(t) - 1)
        return self.floor_z[np.argmax(g[idx], axis=1)]

    def forget_before(self, stamp_ns: int) -> None:
        """Drop history entries older than ``stamp_ns`` (keeping the one in force at it)."""
        k = bisect.bisect_right([e[0] for e in self.history], stamp_ns) - 1
        if k > 0:
            del self.history[:k]
