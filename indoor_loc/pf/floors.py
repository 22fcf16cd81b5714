"""Floors for the graph particle filter (pure numpy): where a particle is in height, the floor of a
WiFi fix as a likelihood, and the barometer's floor changes as a gate on vertical transitions.

A particle on link ``l`` at ``pos`` metres from end 0 is at the height interpolated between its
ends' floors (a vertical link climbs along its walking length) and *on* the floor of its nearer end.

**Fix floor.** A fix carries its floor's height ``z`` with the floor detector's variance ``z_var``:
``P(fix floor k | particle floor j) = 1 − w`` for ``j = k``, ``w / (F − 1)`` otherwise, with
``w = clip(z_var / Δz², fix_floor_wrong_min, 1 − 1/F)`` (Δz the smallest storey): a fix on
another floor is evidence against a particle, as strong as the detector is sure.

**Barometer gate.** Every particle carries ``floor_ref``, the floor it should be on if the
barometer is right: its own floor when it is created, shifted by each barometer floor change
(:class:`~indoor_loc.baro.detector.FloorChange`, ``dh_m`` → the floor whose height is nearest
``z(floor_ref) + dh_m``). While the barometer holds still (no transit in progress), at most once a
``baro_check_s`` a particle off its ``floor_ref`` is weighed by ``baro_floor_wrong``: the particles
that took the stairs while the barometer stayed level die out, and those that did not follow a
transit the barometer saw die out. At a floor change the particles that cannot follow it by
walking (a lift: the PDR sees no steps) and are within ``shaft_reach_m`` of a lift or stairwell
(a connected set of vertical links, a *shaft*) are moved to the shaft's stop on their new floor,
leaving on a level link; when almost no weight is left on the right floor the rest are projected
onto that floor's links where they stand (plan position kept).

**Height likelihood during a transit.** Once the barometer's floor track has snapped the floor
during a transit (:class:`~indoor_loc.baro.snap.FloorSnap`), the walker's barometric height in
``map`` is known; a particle's height (its floor's, or along its stair or lift link) is weighed by
a Gaussian around it (:func:`baro_height`, σ from the detector's parameters: :func:`baro_height_sigma`),
never below ``baro_floor_wrong``: particles that walk a flight faster than the walker, or back down
it after the arrival, lose weight before the detector ends the transit and the gate takes over.

**Sensor resetting from the barometer.** A floor change means the walker is at a lift or a
stairwell now: a particle still off the new floor beyond ``shaft_reach_m`` of every shaft is
evidence that the cloud is wrong in the plane, not that the walker stayed. Such particles are
re-drawn at the nearest shaft's stop on the new floor, their weight multiplied by
``exp(−½ ((d − shaft_reach_m) / shaft_reset_sigma_m)²)`` (``d`` the plan distance they jump): the
cloud's mass is on the new floor at once, mostly at the shafts nearest where it was.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from indoor_loc import params as P
from indoor_loc.graph.model import BuildingGraph

if TYPE_CHECKING:
    from indoor_loc.baro.detector import FloorChangeDetector
    from indoor_loc.pf.filter import GraphParticleFilter


class FloorGeometry:
    """The graph's floors as arrays: floor heights ``fz (F,)`` m, the shafts' stops ``shaft_stop
    (C, F)`` (node index, -1 where a shaft has no stop on a floor) and per node a level link to
    leave it by (``exit_link``, ``exit_end``: the link's end at the node; -1 if none)."""

    def __init__(self, g: BuildingGraph) -> None:
        self.g = g
        self.fz = np.array([f.height_m for f in g.floors], float)
        self.n_floors = len(self.fz)
        gaps = np.diff(np.sort(self.fz))
        self.storey_m = float(gaps[gaps > 0].min()) if np.any(gaps > 0) else 3.0
        vert = np.flatnonzero(g.link_vertical)
        m = g.n_nodes
        if len(vert):
            adj = coo_matrix((np.ones(len(vert)), (g.link_nodes[vert, 0], g.link_nodes[vert, 1])), shape=(m, m))
            _, label = connected_components(adj, directed=False)
            on = np.unique(g.link_nodes[vert].reshape(-1))
            comps = np.unique(label[on])
            self.shaft_stop = np.full((len(comps), self.n_floors), -1, np.int64)
            for c, lab in enumerate(comps):
                for node in on[label[on] == lab]:
                    self.shaft_stop[c, g.node_floor[node]] = node
        else:
            self.shaft_stop = np.zeros((0, self.n_floors), np.int64)
        self.exit_link = np.full(m, -1, np.int64)
        self.exit_end = np.zeros(m, np.int8)
        for node in range(m):
            for k in range(g.adj_ptr[node], g.adj_ptr[node + 1]):
                if not g.link_vertical[g.adj_link[k]]:
                    self.exit_link[node], self.exit_end[node] = g.adj_link[k], g.adj_end[k]
                    break

    # -- where particles are ------------------------------------------------------------------
    def floor_of(self, link: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """(N,) floor index of particles: the floor of the nearer end of their link."""
        g = self.g
        far = pos > 0.5 * g.link_len[link]
        return g.node_floor[g.link_nodes[link, far.astype(np.intp)]].astype(np.int64)

    def z_of(self, link: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """(N,) height (m) of particles along their link."""
        g = self.g
        za, zb = g.node_xyz[g.link_nodes[link, 0], 2], g.node_xyz[g.link_nodes[link, 1], 2]
        t = np.divide(pos, g.link_len[link], out=np.zeros_like(pos, dtype=float), where=g.link_len[link] > 0)
        return za + t * (zb - za)

    def floor_at_height(self, z: float | np.ndarray) -> np.ndarray:
        """Index of the floor nearest each height."""
        return np.argmin(np.abs(np.asarray(z, float)[..., None] - self.fz), axis=-1)

    def fix_floor(self, z: float, z_var: float, wrong_min: float) -> tuple[int, float] | None:
        """The floor of a fix (index) and the probability ``w`` it is wrong; None when the fix's
        height is farther than a quarter storey from every floor (a fix that does not know floors)."""
        if self.n_floors < 2 or not (np.isfinite(z) and np.isfinite(z_var)):
            return None
        k = int(self.floor_at_height(z))
        if abs(self.fz[k] - z) > 0.25 * self.storey_m:
            return None
        w = float(np.clip(max(z_var, 0.0) / self.storey_m ** 2, wrong_min, 1.0 - 1.0 / self.n_floors))
        return k, w

    def fix_log_likelihood(self, particle_floor: np.ndarray, floor: int, wrong: float) -> np.ndarray:
        """(N,) log P(fix floor | particle floor) (see the module docstring)."""
        return np.where(particle_floor == floor, np.log1p(-wrong), np.log(wrong / (self.n_floors - 1)))

    def shifted(self, floor_ref: np.ndarray, dh_m: float) -> np.ndarray:
        """The floors ``dh_m`` metres from ``floor_ref`` (nearest floor heights)."""
        return self.floor_at_height(self.fz[floor_ref] + dh_m).astype(floor_ref.dtype)

    def through_shafts(self, xy: np.ndarray, floor: np.ndarray, target: np.ndarray, reach_m: float
                       ) -> tuple[np.ndarray, np.ndarray]:
        """Particles at ``xy`` (N, 2) on ``floor`` that can reach ``target`` through a shaft within
        ``reach_m`` of them: (mask (N,), the target stop node (N,), -1 where none)."""
        g = self.g
        node = np.full(len(xy), -1, np.int64)
        best = np.full(len(xy), np.inf)
        for stops in self.shaft_stop:
            src, dst = stops[floor], stops[target]
            ok = (src >= 0) & (dst >= 0) & (floor != target)
            d = np.where(ok, np.hypot(*(xy - g.node_xyz[np.maximum(src, 0), :2]).T), np.inf)
            better = (d <= reach_m) & (d < best)
            node[better], best[better] = dst[better], d[better]
        return node >= 0, node


# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PfFloorParams:
    """Floors in the particle filter (see the module docstring)."""
    fix_floor: bool = P.field(True, "weigh particles by the WiFi fix's floor (pose z) when the graph has several "
                                    "floors; false when the radio map has none (its fixes all say z = 0)")
    fix_floor_wrong_min: float = P.field(0.1, "smallest probability that a fix's floor is wrong (the powed "
                                              "detector on simulated multi-floor walks: about 1 in 8)")
    baro_floor_wrong: float = P.field(0.05, "weight of a particle off the floor the barometer expects, per check")
    baro_check_s: float = P.field(1.0, "the barometer gate weighs the particles at most this often (s)")
    baro_height: bool = P.field(True, "once the floor is snapped during a barometer transit (stairs, a lift, a pause "
                                      "between flights) weigh "
                                      "the particles' heights against the barometric height (Gaussian, the "
                                      "detector's noise, never below baro_floor_wrong); false: no barometer "
                                      "evidence until the transit ends")
    shaft_reach_m: float = P.field(8.0, "at a barometer floor change, particles this close to a lift or stairwell "
                                        "(plan distance, m) that are not on the new floor move to its stop there")
    shaft_reset_sigma_m: float = P.field(10.0, "at a barometer floor change, particles off the new floor beyond "
                                               "shaft_reach_m of every shaft are re-drawn at the nearest shaft's "
                                               "stop there, weighed by a Gaussian of the distance past "
                                               "shaft_reach_m with this sigma (m); 0: they stay")
    reset_weight: float = P.field(1e-3, "when less weight than this is on the floors the barometer expects, the "
                                        "others are projected onto those floors")
    baro_timeout_s: float = P.field(10.0, "the barometer counts as reporting while samples arrive within this (s): "
                                          "then the particles redrawn around a fix go on the filter's floor, not "
                                          "the fix's (floor changes are the barometer's)")
    floor_reinit_fixes: int = P.field(5, "this many consecutive confident fixes (probability of a wrong floor < "
                                         "0.25) on another floor than the filter's re-initialise it on theirs "
                                         "(the start was on the wrong floor, or a change was missed)")

    def validate(self) -> None:
        n = type(self).__name__
        for name in ("fix_floor_wrong_min", "baro_floor_wrong", "reset_weight"):
            P.require(0 < getattr(self, name) < 1, n, name, "in (0, 1)", getattr(self, name))
        P.require(self.baro_check_s >= 0, n, "baro_check_s", ">= 0", self.baro_check_s)
        P.require(self.shaft_reach_m >= 0, n, "shaft_reach_m", ">= 0", self.shaft_reach_m)
        P.require(self.shaft_reset_sigma_m >= 0, n, "shaft_reset_sigma_m", ">= 0", self.shaft_reset_sigma_m)
        P.require(self.baro_timeout_s > 0, n, "baro_timeout_s", "> 0", self.baro_timeout_s)
        P.require(self.floor_reinit_fixes >= 1, n, "floor_reinit_fixes", ">= 1", self.floor_reinit_fixes)


def baro_floor_change(pf: "GraphParticleFilter", dh_m: float, params: PfFloorParams) -> int:
    """A barometer floor change of ``dh_m``: every particle's ``floor_ref`` moves by it, and the
    particles off their new ``floor_ref`` that a shaft within ``shaft_reach_m`` can take there are
    moved to its stop on that floor, leaving along a level link. Returns how many moved."""
    p, fg = pf.p, pf.floors
    assert p is not None
    own = fg.floor_of(p.link, p.pos)
    ref = np.where(p.floor_ref < 0, own, p.floor_ref).astype(np.int64)
    target = fg.shifted(ref, dh_m)
    p.floor_ref = target.astype(np.int16)
    return _through_shafts(pf, own, target, params)


def baro_floor_to(pf: "GraphParticleFilter", floor: int, params: PfFloorParams) -> int:
    """The barometer's floor track moved to ``floor`` (snapped during a transit or reported at its
    end): every particle's ``floor_ref`` becomes it, and the particles off it that a shaft within
    ``shaft_reach_m`` can take there are moved to its stop on that floor, leaving along a level link.
    Particles still off it are re-drawn at the shafts' stops there (:func:`shaft_reset`).
    Returns how many moved."""
    p, fg = pf.p, pf.floors
    assert p is not None
    own = fg.floor_of(p.link, p.pos)
    target = np.full(len(own), int(floor), np.int64)
    p.floor_ref = target.astype(np.int16)
    moved = _through_shafts(pf, own, target, params)
    return moved + shaft_reset(pf, int(floor), params)


def shaft_reset(pf: "GraphParticleFilter", floor: int, params: PfFloorParams) -> int:
    """Sensor resetting at a barometer floor change to ``floor`` (module docstring): the particles
    off it are re-drawn at the nearest shaft's stop on it, weighed by the plan distance of the jump
    past ``shaft_reach_m``. Returns how many were re-drawn."""
    p, fg = pf.p, pf.floors
    assert p is not None
    if params.shaft_reset_sigma_m <= 0:
        return 0
    off = np.flatnonzero(fg.floor_of(p.link, p.pos) != floor)
    stops = fg.shaft_stop[:, floor] if len(fg.shaft_stop) else np.zeros(0, np.int64)
    stops = stops[(stops >= 0) & (fg.exit_link[np.maximum(stops, 0)] >= 0)]
    if not len(off) or not len(stops):
        return 0
    xy = pf.xy()[off]
    d = np.hypot(xy[:, None, 0] - fg.g.node_xyz[stops, 0][None], xy[:, None, 1] - fg.g.node_xyz[stops, 1][None])
    near = np.argmin(d, axis=1)
    node = stops[near]
    excess = np.maximum(d[np.arange(len(off)), near] - params.shaft_reach_m, 0.0)
    link, end = fg.exit_link[node], fg.exit_end[node]
    p.link[off] = link
    p.pos[off] = np.where(end == 0, 0.0, pf.g.link_len[link])
    p.direction[off] = np.where(end == 0, 1, -1).astype(np.int8)
    log_l = np.zeros(len(p.link))
    log_l[off] = -0.5 * (excess / params.shaft_reset_sigma_m) ** 2
    pf.update_log_likelihood(log_l)
    return int(len(off))


def baro_check(pf: "GraphParticleFilter", params: PfFloorParams) -> float:
    """The barometer holds still: particles off their ``floor_ref`` are weighed by
    ``baro_floor_wrong``; when less than ``reset_weight`` is on the expected floors, the others are
    first projected onto them. Returns the weight that was on the expected floors."""
    p, fg = pf.p, pf.floors
    assert p is not None
    own = fg.floor_of(p.link, p.pos)
    unset = p.floor_ref < 0
    p.floor_ref[unset] = own[unset]
    match = own == p.floor_ref
    w_match = float(p.weights[match].sum())
    if w_match < params.reset_weight:
        xy = pf.xy()
        for f in np.unique(p.floor_ref[~match]):
            idx = np.flatnonzero(~match & (p.floor_ref == f))
            if int(f) in pf.ix_floor:
                p.link[idx], p.pos[idx] = pf.ix_floor[int(f)].project(xy[idx])
        match = fg.floor_of(p.link, p.pos) == p.floor_ref
    pf.update_log_likelihood(np.where(match, 0.0, np.log(params.baro_floor_wrong)))
    return w_match


def _through_shafts(pf: "GraphParticleFilter", own: np.ndarray, target: np.ndarray, params: PfFloorParams) -> int:
    """The particles on floor ``own`` that a shaft within ``shaft_reach_m`` takes to floor ``target``
    moved to its stop there, leaving along a level link; how many moved."""
    p, fg = pf.p, pf.floors
    assert p is not None
    ok, node = fg.through_shafts(pf.xy(), own, target, params.shaft_reach_m)
    move = np.flatnonzero(ok & (fg.exit_link[np.maximum(node, 0)] >= 0))
    if len(move):
        link = fg.exit_link[node[move]]
        end = fg.exit_end[node[move]]
        p.link[move] = link
        p.pos[move] = np.where(end == 0, 0.0, pf.g.link_len[link])
        p.direction[move] = np.where(end == 0, 1, -1).astype(np.int8)
    return int(len(move))


def baro_height_sigma(det: "FloorChangeDetector", since_ns: int) -> float:
    """Standard deviation (m) of the barometric height in ``map`` during a transit, from the
    detector's own parameters: the running median's noise (``1.25 σ / √n`` over the samples in its
    window), the median's lag on a moving height (half the window times the vertical speed over the
    last second) and the weather drift since the transit started at ``since_ns``."""
    s, p = det.s, det.params
    if s.last_ns is None or not np.isfinite(s.height_m):
        return float("inf")
    median = 1.25 * p.noise_m / np.sqrt(max(len(s.raw), 1))
    past = [h for t, h in s.smooth if t <= s.last_ns - 10**9]
    speed = abs(s.height_m - past[-1]) if past else 0.0          # m over the last second
    lag = 0.5 * p.smooth_s * speed
    drift = p.drift_m_per_s * max(s.last_ns - since_ns, 0) * 1e-9
    return float(np.sqrt(median ** 2 + lag ** 2 + drift ** 2))


def baro_height(pf: "GraphParticleFilter", z_m: float, sigma_m: float, params: PfFloorParams) -> np.ndarray:
    """The barometer's height during a transit: each particle's height (its floor's, or along a
    stair or lift link) weighed by ``exp(−½ ((z − z_m) / sigma_m)²)``, never below
    ``baro_floor_wrong`` (the weight of a particle off the barometer's floor while it holds still:
    the same evidence, continuous while the walker climbs). Returns the particles' log-likelihood."""
    p, fg = pf.p, pf.floors
    assert p is not None
    if not (np.isfinite(z_m) and np.isfinite(sigma_m) and sigma_m > 0):
        return np.zeros(len(p.link))
    d = (fg.z_of(p.link, p.pos) - z_m) / sigma_m
    log_l = np.maximum(-0.5 * d * d, np.log(params.baro_floor_wrong))
    pf.update_log_likelihood(log_l)
    return log_l
