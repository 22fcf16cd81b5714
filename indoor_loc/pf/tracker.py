"""One user's graph particle filter driven by time-ordered events (PDR intervals, WiFi fixes),
with the history kept for backward-simulation smoothing.

The same object runs inside the ``tll_pf`` stage (live and offline) and in ``indoor-loc bench pf``
on arrays, so online and batch results agree by construction.

Smoother: backward simulation (Godsill, Doucet & West, "Monte Carlo smoothing for nonlinear time
series", JASA 2004; applied to floor-plan graphs in the floor-plan-to-graph slides): draw the last
state from the final weights, then for t = T-1 … 0 reweight the filter's particles at t by
``W_t^j p(x̃_{t+1} | x_t^j)`` and draw x̃_t. The transition density of a PDR interval is taken as
``N(|Δr| | d_t s^j, σ_d²) · vonMises(angle(Δr) | ψ_t + offset^j, κ)`` over the straight-line
displacement (the slides' step-length and turn factors); along-graph moves shorter than the chord
(corners) are covered by ``σ_d``. Every smoothed pose is a particle position, so it lies on a link;
the reported smoothed pose is the constrained mean of ``n_samples`` backward trajectories.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from indoor_loc.graph.model import BuildingGraph
from indoor_loc.graph.tll import Transitions
from indoor_loc.pf.filter import GraphParticleFilter, PfParams, constrained_mean, particle_xy


@dataclass
class Estimate:
    stamp_ns: int
    xy: np.ndarray
    cov: np.ndarray
    yaw: float


@dataclass
class _Step:
    stamp_ns: int
    xy: np.ndarray            # (N, 2) particle positions after the step's update
    log_w: np.ndarray         # (N,)
    scale: np.ndarray
    yaw_offset: np.ndarray
    distance_m: float         # PDR distance that led here from the previous step (0 for fixes)
    heading_rad: float        # PDR heading of that interval (nan if none)
    dt_s: float


@dataclass
class TrackerStats:
    odom: int = 0
    fixes: int = 0
    reinits: int = 0
    resamples: int = 0
    steps: list = field(default_factory=list)


class GraphTracker:
    """Feed :meth:`odom` and :meth:`fix` in stamp order; read :attr:`estimates`; call
    :meth:`smooth` at the end. The filter starts at the first fix (or :meth:`reset_at`)."""

    def __init__(self, graph: BuildingGraph, transitions: Transitions, params: PfParams | None = None, *,
                 rng: np.random.Generator, keep_history: bool = True) -> None:
        self.pf = GraphParticleFilter(graph, transitions, params)
        self.g = graph
        self.rng = rng
        self.keep_history = keep_history
        self.history: list[_Step] = []
        self.segments: list[list[_Step]] = []        # closed smoother segments (before re-initialisations)
        self.estimates: list[Estimate] = []
        self._last_odom: tuple[int, float, float] | None = None
        self._last_stamp: int | None = None

    @property
    def initialised(self) -> bool:
        return self.pf.initialised

    def _close_segment(self) -> None:
        if self.history:
            self.segments.append(self.history)
        self.history = []

    def reset(self) -> None:
        """Forget everything (time jump backwards, global localisation request)."""
        self.pf.p = None
        self.history = []
        self.segments = []
        self.estimates.clear()
        self._last_odom = None
        self._last_stamp = None

    def reset_at(self, stamp_ns: int, xy: np.ndarray, cov: np.ndarray) -> Estimate:
        """(Re)initialise around a position (``initialpose``)."""
        self._close_segment()
        self.pf.init_gaussian(xy, cov, self.rng)
        self._last_stamp = stamp_ns
        return self._record(stamp_ns, 0.0, np.nan, 0.0)

    def global_localization(self, stamp_ns: int) -> Estimate:
        """Particles uniform over the whole graph."""
        self._close_segment()
        self.pf.init_uniform(self.rng)
        self._last_stamp = stamp_ns
        return self._record(stamp_ns, 0.0, np.nan, 0.0)

    # -- events -----------------------------------------------------------------------------
    def odom(self, stamp_ns: int, x: float, y: float) -> Estimate | None:
        """A PDR odometry sample (odom frame). The interval since the previous one is walked."""
        prev, self._last_odom = self._last_odom, (stamp_ns, x, y)
        if prev is None or not self.pf.initialised:
            return None
        dx, dy = x - prev[1], y - prev[2]
        dist = float(np.hypot(dx, dy))
        heading = float(np.arctan2(dy, dx)) if dist > 1e-9 else np.nan
        self.pf.predict_pdr(dist, heading if dist > 1e-9 else 0.0, self.rng)
        dt = (stamp_ns - (self._last_stamp or stamp_ns)) * 1e-9
        self._last_stamp = stamp_ns
        return self._record(stamp_ns, dist, heading, dt)

    def elapse(self, stamp_ns: int) -> None:
        """Without PDR: move the particles by the speed model up to ``stamp_ns``."""
        if self.pf.initialised and self._last_stamp is not None and stamp_ns > self._last_stamp:
            self.pf.predict_speed((stamp_ns - self._last_stamp) * 1e-9, self.rng)
            self._last_stamp = stamp_ns

    def fix(self, stamp_ns: int, xy: np.ndarray, cov: np.ndarray, *, use_speed_model: bool = False) -> Estimate:
        """A WiFi position fix (map frame, covariance m²)."""
        if not self.pf.initialised:
            return self.reset_at(stamp_ns, xy, cov)
        dt = 0.0
        if use_speed_model:
            dt = (stamp_ns - (self._last_stamp or stamp_ns)) * 1e-9
            self.elapse(stamp_ns)
        if self.pf.update_position(xy, cov, self.rng):
            self._close_segment()                   # a re-initialisation starts a new smoother segment
        est = self._record(stamp_ns, 0.0, np.nan, dt, update=True)
        self.pf.maybe_resample(self.rng)
        if self.keep_history and self.history:
            self._snapshot(self.history[-1])        # smoother uses the resampled set's positions too
        return est

    # -- bookkeeping ----------------------------------------------------------------------------
    def _snapshot(self, step: _Step) -> None:
        p = self.pf.p
        assert p is not None
        step.xy = particle_xy(self.g, p)
        step.log_w = p.log_w.copy()
        step.scale = p.scale.copy()
        step.yaw_offset = p.yaw_offset.copy()

    def _record(self, stamp_ns: int, dist: float, heading: float, dt: float, update: bool = False) -> Estimate:
        xy_mean, cov, yaw = self.pf.estimate()
        est = Estimate(stamp_ns, xy_mean, cov, yaw)
        self.estimates.append(est)
        if self.keep_history:
            p = self.pf.p
            assert p is not None
            self.history.append(_Step(stamp_ns, particle_xy(self.g, p), p.log_w.copy(), p.scale.copy(),
                                      p.yaw_offset.copy(), dist, heading, dt))
        return est

    # -- smoothing -------------------------------------------------------------------------------
    def smooth(self, n_samples: int = 50, *, sigma_d_m: float = 0.6, sigma_speed: float = 1.0) -> list[Estimate]:
        """Backward-simulation smoother over every segment (see the module docstring)."""
        out: list[Estimate] = []
        for seg in self.segments + [self.history]:
            out += self._smooth_segment(seg, n_samples, sigma_d_m, sigma_speed)
        return out

    def _smooth_segment(self, h: list[_Step], n_samples: int, sigma_d_m: float, sigma_speed: float) -> list[Estimate]:
        if not h:
            return []
        rng = self.rng
        kappa = self.pf._kappa
        T = len(h)
        picks = np.empty((T, n_samples), np.int64)
        w = np.exp(h[-1].log_w)
        picks[-1] = rng.choice(len(w), size=n_samples, p=w / w.sum())
        for t in range(T - 2, -1, -1):
            nxt, cur = h[t + 1], h[t]
            target = nxt.xy[picks[t + 1]]                                  # (S, 2)
            disp = target[:, None, :] - cur.xy[None, :, :]                # (S, N, 2)
            chord = np.hypot(disp[..., 0], disp[..., 1])
            if nxt.distance_m > 0:
                mu = nxt.distance_m * cur.scale[None, :]
                ld = -0.5 * ((chord - mu) / sigma_d_m) ** 2
                ang = np.arctan2(disp[..., 1], disp[..., 0])
                lh = np.where(chord > 0.05, np.log((1 - self.pf.params.heading_floor)
                                                   * np.exp(kappa * (np.cos(ang - nxt.heading_rad - cur.yaw_offset[None, :]) - 1))
                                                   + self.pf.params.heading_floor), 0.0)
                logk = ld + lh
            elif nxt.dt_s > 0:
                reach = sigma_speed * nxt.dt_s + sigma_d_m
                logk = -0.5 * (chord / reach) ** 2
            else:
                logk = -0.5 * (chord / sigma_d_m) ** 2
            lw = cur.log_w[None, :] + logk
            lw -= lw.max(axis=1, keepdims=True)
            pw = np.exp(lw)
            cdf = np.cumsum(pw, axis=1)
            cdf /= cdf[:, -1:]
            u = rng.random((n_samples, 1))
            picks[t] = np.minimum((u > cdf).sum(axis=1), len(cur.log_w) - 1)
        out = []
        ones = np.full(n_samples, 1.0 / n_samples)
        for t in range(T):
            pts = h[t].xy[picks[t]]
            xy, _, _ = constrained_mean(self.g, pts, ones)
            d = pts - pts.mean(axis=0)
            out.append(Estimate(h[t].stamp_ns, xy, d.T @ d / n_samples + 1e-6 * np.eye(2), np.nan))
        return out
