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

Divergence monitoring (Raitoharju et al., "A linear state model for PDR+WLAN positioning", 2015,
Sec. 5.2): the linear PDR Kalman filter of the same paper runs alongside on the same PDR intervals
and WiFi fixes. After every event the smallest squared Mahalanobis distance of the weighted
particles from the KF position (eq. 64) is compared with the chi-square gate ``kf_gate_prob``
(2 degrees of freedom); when it stays above the gate for ``kf_persist_s`` seconds of stamp time
the particles are re-initialised around the KF estimate (:meth:`GraphParticleFilter.reinit_gaussian`:
part of the old particles are kept, in case the KF is the one that is wrong, and the count follows
the covariance rule when adaptive). The monitor needs PDR (the KF's motion model) and trusts the KF
after ``kf_min_updates`` accepted fixes; the KF restarts at a fix after two consecutive gated-out
fixes, as the ``pdr_kf`` node does.

Floors (:mod:`indoor_loc.pf.floors`): a fix's floor (``z``, ``z_var``) weighs the particles and
decides where redrawn particles go; barometer samples (:meth:`GraphTracker.baro`) run the
floor-change detector (:mod:`indoor_loc.baro.detector`) and gate the particles' vertical
transitions. Every estimate carries the most probable floor and its height; the smoother's
transition kernel measures the chord in three dimensions, so a backward trajectory does not jump
between floors.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from indoor_loc import params as P
from indoor_loc.baro.detector import BaroParams, FloorChange
from indoor_loc.baro.floors import FloorFilterParams
from indoor_loc.baro.snap import FloorSnapParams
from indoor_loc.baro.track import FloorTrack
from indoor_loc.fusion.position_trust import fixes_agree
from indoor_loc.fusion.linear_pdr import LinearPdrKf, LinearPdrParams
from indoor_loc.measurements import Fix, wrap_angle

from indoor_loc.graph.model import BuildingGraph
from indoor_loc.graph.tll import Transitions
from indoor_loc.pf.filter import GraphParticleFilter, PfParams, constrained_mean
from indoor_loc.pf.floors import PfFloorParams, baro_check, baro_floor_to, baro_height, baro_height_sigma
from indoor_loc.pf.wifi_field import EdgeFingerprintField
from indoor_loc.wifi.types import WifiScan


@dataclass
class Estimate:
    stamp_ns: int
    xy: np.ndarray
    cov: np.ndarray
    yaw: float
    z: float = 0.0            # height of the floor (m)
    z_var: float = 0.0        # variance of the particles' floor heights (m²)
    floor: int = 0            # index into the graph's floors


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
    redrawn_log_q: np.ndarray | None = None   # (N,) log draw density of particles redrawn at this fix, else -inf
    z: np.ndarray | None = None               # (N,) particle heights (m); None on a one-floor graph


@dataclass(frozen=True)
class MonitorParams:
    """Divergence monitoring of the particle filter by the linear PDR Kalman filter."""
    enabled: bool = P.field(True, "run the linear PDR KF alongside and re-initialise the particles when they "
                                  "disagree with it (needs pdr/odom)")
    gate_prob: float = P.field(0.999, "chi-square (2 dof) probability of the PF-vs-KF gate on the smallest particle "
                                      "Mahalanobis distance")
    persist_s: float = P.field(5.0, "re-initialise when the disagreement lasts this long (s of stamp time)")
    keep_fraction: float = P.field(0.3, "fraction of the re-initialised set kept from the old particles")
    min_updates: int = P.field(3, "the KF is trusted after this many accepted WiFi fixes since its (re)start")
    step_length_m: float = P.field(0.7, "KF footstep length: steps = PDR distance / this (m)")
    sigma_dtheta_rad: float = P.field(0.2, "KF heading-change noise per footstep (rad)")

    def validate(self) -> None:
        n = type(self).__name__
        P.require(0 < self.gate_prob < 1, n, "gate_prob", "in (0, 1)", self.gate_prob)
        P.require(self.persist_s >= 0, n, "persist_s", ">= 0", self.persist_s)
        P.require(0 <= self.keep_fraction < 1, n, "keep_fraction", "in [0, 1)", self.keep_fraction)
        P.require(self.min_updates >= 0, n, "min_updates", ">= 0", self.min_updates)
        P.require(self.step_length_m > 0, n, "step_length_m", "> 0", self.step_length_m)
        P.require(self.sigma_dtheta_rad >= 0, n, "sigma_dtheta_rad", ">= 0", self.sigma_dtheta_rad)


@dataclass
class MonitorState:
    """What the monitor counts (``/diagnostics``)."""
    reinits: int = 0               # re-initialisations around the KF estimate
    kf_restarts: int = 0           # KF restarted at a fix after consecutive gated-out fixes
    disagree_since_ns: int | None = None
    last_deviance: float = float("nan")
    rejected_run: int = 0
    last_rejected: tuple | None = None   # (stamp ns, xy, cov) of the run's latest gated-out fix


class GraphTracker:
    """Feed :meth:`odom` and :meth:`fix` in stamp order; read :attr:`estimates`; call
    :meth:`smooth` at the end. The filter starts at the first fix (or :meth:`reset_at`)."""

    def __init__(self, graph: BuildingGraph, transitions: Transitions, params: PfParams | None = None, *,
                 rng: np.random.Generator, keep_history: bool = True, monitor: MonitorParams | None = None,
                 floors: PfFloorParams | None = None, baro: BaroParams | None = None,
                 snap: FloorSnapParams | None = None) -> None:
        self.pf = GraphParticleFilter(graph, transitions, params)
        self.floor_params = floors or PfFloorParams()
        self.floor_params.validate()
        # the user's floor from the barometer (snapped during a transit) and the fixes' floors (a slow
        # prior): the floor the particles are expected on while the barometer reports
        fp = self.floor_params
        self.baro_track = FloorTrack(baro, FloorFilterParams(fix_wrong_min=fp.fix_floor_wrong_min),
                                     floors_m=self.pf.floors.fz, snap=snap)
        self.baro_det = self.baro_track.detector
        self._baro_floor: int | None = None
        self._baro_check_ns: int | None = None
        self.baro_events: list[FloorChange] = []
        self.baro_moved = 0
        self._baro_ns: int | None = None
        self._floor_disagree = 0
        self.floor_reinits = 0
        self.monitor_params = monitor or MonitorParams()
        self.monitor_params.validate()
        self.monitor = MonitorState()
        self.kf: LinearPdrKf | None = None
        self._kf_yaw: float | None = None
        self._gate = float(chi2.ppf(self.monitor_params.gate_prob, 2))
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

    def forget_before(self, stamp_ns: int, keep_estimates: int) -> None:
        """Bound memory in long runs: the smoother's particle history before ``stamp_ns`` is dropped
        (the backward simulation then starts its segments there), and :attr:`estimates` keeps its
        newest ``keep_estimates``."""
        def trim(seg: list[_Step]) -> list[_Step]:
            k = 0
            while k < len(seg) and seg[k].stamp_ns < stamp_ns:
                k += 1
            return seg[k:]
        self.segments = [t for t in (trim(seg) for seg in self.segments) if t]
        self.history = trim(self.history)
        if len(self.estimates) > keep_estimates:
            del self.estimates[:len(self.estimates) - keep_estimates]

    def reset(self) -> None:
        """Forget everything (time jump backwards, global localisation request)."""
        self.pf.p = None
        self.history = []
        self.segments = []
        self.estimates.clear()
        self._last_odom = None
        self._last_stamp = None
        self.kf = None
        self._kf_yaw = None
        self.monitor.disagree_since_ns = None

    def reset_at(self, stamp_ns: int, xy: np.ndarray, cov: np.ndarray, *, inflate: bool = True,
                 floor: int | None = None) -> Estimate:
        """(Re)initialise around a position (the first fix; ``initialpose`` with ``inflate`` False: its
        covariance as given; on ``floor`` when given); the monitoring KF restarts at the next fix."""
        self._close_segment()
        self.kf = None
        self._kf_yaw = None
        self.pf.init_gaussian(xy, cov, self.rng, inflate=inflate, floor=floor)
        self._last_stamp = stamp_ns
        return self._record(stamp_ns, 0.0, np.nan, 0.0)

    def global_localization(self, stamp_ns: int) -> Estimate:
        """Particles uniform over the whole graph; the monitoring KF restarts at the next fix."""
        self._close_segment()
        self.kf = None
        self._kf_yaw = None
        self.pf.init_uniform(self.rng)
        self._last_stamp = stamp_ns
        return self._record(stamp_ns, 0.0, np.nan, 0.0)

    # -- events -----------------------------------------------------------------------------
    def odom(self, stamp_ns: int, x: float, y: float, yaw: float | None = None) -> Estimate | None:
        """A PDR odometry sample (odom frame; ``yaw`` its heading, rad, when known: the monitoring
        KF's heading change, else the change of the walked direction). The interval since the
        previous one is walked."""
        prev, self._last_odom = self._last_odom, (stamp_ns, x, y)
        if prev is None or not self.pf.initialised:
            return None
        dx, dy = x - prev[1], y - prev[2]
        dist = float(np.hypot(dx, dy))
        heading = float(np.arctan2(dy, dx)) if dist > 1e-9 else np.nan
        self.pf.predict_pdr(dist, heading if dist > 1e-9 else 0.0, self.rng)
        self._kf_predict(dist, yaw if yaw is not None else (heading if dist > 1e-9 else None), stamp_ns)
        dt = (stamp_ns - (self._last_stamp or stamp_ns)) * 1e-9
        self._last_stamp = stamp_ns
        est = self._record(stamp_ns, dist, heading, dt)
        return self._check(stamp_ns) or est

    def new_odom_frame(self) -> None:
        """The odometry restarted (a new frame): the next sample walks nothing, the ones after it
        walk their intervals as before."""
        self._last_odom = None

    def increment(self, stamp_ns: int, distance_m: float, travel_rad: float, *, var_along: float,
                  var_yaw: float) -> Estimate | None:
        """A robot odometry increment ending at ``stamp_ns`` (:mod:`indoor_loc.odometry.increments`):
        ``distance_m`` along the heading of travel ``travel_rad`` (increment frame; each particle adds
        its own offset), with the increment's own along-track variance (m²) and heading variance (rad²,
        the offsets' random walk)."""
        if not self.pf.initialised:
            return None
        self.pf.predict_pdr(distance_m, travel_rad if distance_m > 1e-9 else 0.0, self.rng,
                            distance_sd_m=float(np.sqrt(max(var_along, 0.0))),
                            yaw_walk_rad=float(np.sqrt(max(var_yaw, 0.0))))
        self._kf_predict(distance_m, travel_rad, stamp_ns)
        dt = (stamp_ns - (self._last_stamp or stamp_ns)) * 1e-9
        self._last_stamp = stamp_ns
        est = self._record(stamp_ns, distance_m, travel_rad if distance_m > 1e-9 else np.nan, dt)
        return self._check(stamp_ns) or est

    def elapse(self, stamp_ns: int) -> None:
        """Without PDR: move the particles by the speed model up to ``stamp_ns``."""
        if self.pf.initialised and self._last_stamp is not None and stamp_ns > self._last_stamp:
            self.pf.predict_speed((stamp_ns - self._last_stamp) * 1e-9, self.rng)
            self._last_stamp = stamp_ns

    def fix_floor(self, z: float | None, z_var: float = 0.0) -> tuple[int, float] | None:
        """The floor of a fix of height ``z`` (m) and variance ``z_var`` (m²) and the probability it
        is wrong; None when floors are not used (one floor, ``fix_floor`` off, a height off every floor)."""
        if z is None or not self.floor_params.fix_floor:
            return None
        return self.pf.floors.fix_floor(z, z_var, self.floor_params.fix_floor_wrong_min)

    def fix(self, stamp_ns: int, xy: np.ndarray, cov: np.ndarray, *, use_speed_model: bool = False,
            z: float | None = None, z_var: float = 0.0) -> Estimate:
        """A WiFi position fix (map frame, covariance m²; ``z`` its floor's height, m, with variance
        ``z_var``, m²)."""
        floor = self.fix_floor(z, z_var)
        if floor is not None:                       # the floor track's slow prior (its HMM)
            self.baro_track.fix(stamp_ns, float(self.pf.floors.fz[floor[0]]), floor[1] * self.pf.floors.storey_m ** 2)
        if not self.pf.initialised:
            est = self.reset_at(stamp_ns, xy, cov, floor=None if floor is None else floor[0])
            self._kf_fix(stamp_ns, xy, cov, use_speed_model)
            return est
        dt = 0.0
        if use_speed_model:
            dt = (stamp_ns - (self._last_stamp or stamp_ns)) * 1e-9
            self.elapse(stamp_ns)
        inject_floor = None
        if floor is not None:
            current = self.pf.estimate_floor()[0]
            baro_live = self._baro_ns is not None and stamp_ns - self._baro_ns <= int(self.floor_params.baro_timeout_s * 1e9)
            inject_floor = current if baro_live else None
            self._floor_disagree = self._floor_disagree + 1 if floor[0] != current and floor[1] < 0.25 else 0
            if self._floor_disagree >= self.floor_params.floor_reinit_fixes:
                self._floor_disagree = 0
                self.floor_reinits += 1
                self._close_segment()
                self.pf.reinit_gaussian(xy, cov, self.monitor_params.keep_fraction, self.rng, floor=floor[0])
                inject_floor = floor[0]
        if self.pf.update_position(xy, cov, self.rng, floor=floor, inject_floor=inject_floor):
            self._close_segment()                   # a re-initialisation starts a new smoother segment
        self._kf_fix(stamp_ns, xy, cov, use_speed_model)
        return self._after_update(stamp_ns, dt)

    def update_log_likelihood(self, stamp_ns: int, log_l: np.ndarray, *, use_speed_model: bool = False) -> Estimate | None:
        """A measurement given as a per-particle log-likelihood (N,) at ``stamp_ns`` (e.g. a WiFi
        scan against the radio map interpolated on the links). Ignored before initialisation."""
        if not self.pf.initialised:
            return None
        dt = 0.0
        if use_speed_model:
            dt = (stamp_ns - (self._last_stamp or stamp_ns)) * 1e-9
            self.elapse(stamp_ns)
        self.pf.update_log_likelihood(log_l)
        return self._after_update(stamp_ns, dt)

    def scan(self, stamp_ns: int, field: EdgeFingerprintField, scan: WifiScan, *,
             use_speed_model: bool = False) -> Estimate | None:
        """A WiFi scan weighed by the radio map interpolated on the links. Before initialisation
        the particles are drawn over the links in proportion to the scan's likelihood. None when
        the map knows none of the scan's APs (nothing learnt)."""
        if field.known_aps(scan) == 0:
            return None
        if not self.pf.initialised:
            self._close_segment()
            link, t = field.sample_points(scan, self.pf.params.n_particles, self.rng)
            self.pf.p = self.pf._new(link, t, self.rng)
            self._last_stamp = stamp_ns
            return self._record(stamp_ns, 0.0, np.nan, 0.0)
        dt = 0.0
        if use_speed_model:
            dt = (stamp_ns - (self._last_stamp or stamp_ns)) * 1e-9
            self.elapse(stamp_ns)
        k = self.pf.inject_count()
        if k:                                       # sensor resetting, as for fixes, from the scan's likelihood
            self.pf.inject(*field.sample_points(scan, k, self.rng), self.rng)
        p = self.pf.p
        assert p is not None
        self.pf.update_log_likelihood(field.log_likelihood(p.link, p.pos, scan))
        return self._after_update(stamp_ns, dt)

    def baro(self, stamp_ns: int, pressure_pa: float) -> list[FloorChange]:
        """A barometer sample (Pa): the user's floor track runs (the floor-change detector, the floor
        snapped to the barometric height during a transit, the floor HMM with the fixes' floors); on a
        multi-floor graph a change of its floor moves the particles' expected floor (and the particles
        a shaft can take there), and while the barometer holds still the particles off that floor are
        weighed down (at most once a ``baro_check_s``). Returns the floor changes it reported."""
        events = self.baro_track.baro(stamp_ns, pressure_pa)
        self._baro_ns = stamp_ns
        self.baro_events += events
        if not self.pf.initialised or self.pf.floors.n_floors < 2:
            return events
        fp = self.floor_params
        k = self.baro_track.floor_now()
        expected = None if k is None else int(self.pf.floors.floor_at_height(self.baro_track.filter.floor_z[k]))
        if expected is not None and expected != self._baro_floor:
            if self._baro_floor is not None:
                self.baro_moved += baro_floor_to(self.pf, expected, fp)
            else:
                self.pf.p.floor_ref[:] = expected
            self._baro_floor = expected
        due = self._baro_check_ns is None or stamp_ns - self._baro_check_ns >= int(fp.baro_check_s * 1e9)
        snap = self.baro_track.snap
        if due and fp.baro_height and snap.height_z is not None:
            # a transit ramping (or a pause between flights): the particles' heights against the barometer's
            self._baro_check_ns = stamp_ns
            baro_height(self.pf, snap.height_z, baro_height_sigma(self.baro_det, snap.ramp_ns), fp)
        elif due and not self.baro_det.in_transit and self.baro_det.s.level_m is not None:
            self._baro_check_ns = stamp_ns
            if self._baro_floor is not None:
                self.pf.p.floor_ref[:] = self._baro_floor      # particles drawn since then included
            baro_check(self.pf, fp)
        return events

    def _after_update(self, stamp_ns: int, dt: float) -> Estimate:
        est = self._record(stamp_ns, 0.0, np.nan, dt, update=True)
        self.pf.maybe_resample(self.rng)
        if self.keep_history and self.history:
            self._snapshot(self.history[-1])        # smoother uses the resampled set's positions too
            self.history[-1].redrawn_log_q = self.pf.redrawn_log_q
        self.pf.redrawn_log_q = None
        return self._check(stamp_ns) or est

    # -- divergence monitoring ----------------------------------------------------------------
    def _kf_predict(self, dist: float, yaw: float | None, stamp_ns: int) -> None:
        if self.kf is None:
            return
        dtheta = 0.0
        if yaw is not None and np.isfinite(yaw):
            if self._kf_yaw is not None:
                dtheta = float(wrap_angle(yaw - self._kf_yaw))
            self._kf_yaw = yaw
        self.kf.predict(dist / self.monitor_params.step_length_m, dtheta, stamp_ns=stamp_ns)

    def _kf_fix(self, stamp_ns: int, xy: np.ndarray, cov: np.ndarray, speed_model: bool) -> None:
        mp = self.monitor_params
        if not mp.enabled or speed_model:
            return
        if self.kf is None:
            self._kf_start(stamp_ns, xy, cov)
            return
        if self.kf.update(Fix(stamp_ns=stamp_ns, xy=np.asarray(xy, float), cov=np.asarray(cov, float))):
            self.monitor.rejected_run = 0
            self.monitor.last_rejected = None
            return
        # the run counts only while its fixes agree with each other (indoor_loc/fusion/position_trust.py)
        prev = self.monitor.last_rejected
        self.monitor.last_rejected = (stamp_ns, np.asarray(xy, float), np.asarray(cov, float))
        agree = prev is None or fixes_agree(prev, self.monitor.last_rejected, self._gate)
        self.monitor.rejected_run = self.monitor.rejected_run + 1 if agree else 1
        if self.monitor.rejected_run >= 2:
            self.monitor.kf_restarts += 1
            self._kf_start(stamp_ns, xy, cov)

    def _kf_start(self, stamp_ns: int, xy: np.ndarray, cov: np.ndarray) -> None:
        mp = self.monitor_params
        self.kf = LinearPdrKf(LinearPdrParams(step_length_m=mp.step_length_m, sigma_dtheta_rad=mp.sigma_dtheta_rad),
                              xy0=np.asarray(xy, float), pos_cov0=np.asarray(cov, float), stamp_ns=stamp_ns)
        self.monitor.rejected_run = 0
        self.monitor.last_rejected = None
        self.monitor.disagree_since_ns = None

    def _check(self, stamp_ns: int) -> Estimate | None:
        """The monitor's test after an event; returns the new estimate when it re-initialised."""
        kf, mon, mp = self.kf, self.monitor, self.monitor_params
        if kf is None or kf.state.n_updates < mp.min_updates or not self.pf.initialised:
            return None
        mon.last_deviance = self.pf.min_deviance(kf.position, kf.position_cov)
        if mon.last_deviance <= self._gate:
            mon.disagree_since_ns = None
            return None
        if mon.disagree_since_ns is None:
            mon.disagree_since_ns = stamp_ns
        if (stamp_ns - mon.disagree_since_ns) * 1e-9 < mp.persist_s:
            return None
        mon.reinits += 1
        mon.disagree_since_ns = None
        self._close_segment()
        floor = self.pf.estimate_floor()[0] if self.pf.floors.n_floors > 1 else None   # the KF is planar
        self.pf.reinit_gaussian(kf.position, kf.position_cov, mp.keep_fraction, self.rng, floor=floor)
        if self.estimates and self.estimates[-1].stamp_ns == stamp_ns:
            self.estimates.pop()                    # one estimate per event: the re-initialised one
        return self._record(stamp_ns, 0.0, np.nan, 0.0)

    # -- bookkeeping ----------------------------------------------------------------------------
    def _snapshot(self, step: _Step) -> None:
        p = self.pf.p
        assert p is not None
        step.xy = self.pf.xy()
        step.log_w = p.log_w.copy()
        step.scale = p.scale.copy()
        step.yaw_offset = p.yaw_offset.copy()
        step.z = self.pf.floors.z_of(p.link, p.pos) if self.pf.floors.n_floors > 1 else None

    def current(self, stamp_ns: int) -> Estimate:
        """The estimate now from the particles as they are, recorded nowhere (a pose published
        between steps: the floor changed by the barometer)."""
        xy = self.pf.xy()
        floor, z, z_var = self.pf.estimate_floor()
        xy_mean, cov, yaw = self.pf.estimate(xy, floor)
        return Estimate(stamp_ns, xy_mean, cov, yaw, z, z_var, floor)

    def _record(self, stamp_ns: int, dist: float, heading: float, dt: float, update: bool = False) -> Estimate:
        xy = self.pf.xy()                   # once for the estimate and the history (the same particles)
        floor, z, z_var = self.pf.estimate_floor()
        xy_mean, cov, yaw = self.pf.estimate(xy, floor)
        est = Estimate(stamp_ns, xy_mean, cov, yaw, z, z_var, floor)
        self.estimates.append(est)
        if self.keep_history:
            p = self.pf.p
            assert p is not None
            self.history.append(_Step(stamp_ns, xy, p.log_w.copy(), p.scale.copy(),
                                      p.yaw_offset.copy(), dist, heading, dt,
                                      z=self.pf.floors.z_of(p.link, p.pos) if self.pf.floors.n_floors > 1 else None))
        return est

    # -- smoothing -------------------------------------------------------------------------------
    def smooth(self, n_samples: int = 50, *, sigma_d_m: float = 0.6, sigma_speed: float = 1.0,
               redrawn: str = "chain") -> list[Estimate]:
        """Backward-simulation smoother over every segment (see the module docstring). ``redrawn``:
        how a particle redrawn around a fix (sensor resetting) finds its predecessor: ``chain`` =
        the motion kernel alone (its nearest particles), ``mixture`` = the filter's own transition
        at the fix, (1 − inject_mass)·motion + inject_mass·q(x̃)."""
        if redrawn not in ("chain", "mixture"):
            raise ValueError(f"redrawn must be chain or mixture, not {redrawn!r}")
        out: list[Estimate] = []
        for seg in self.segments + [self.history]:
            out += self._smooth_segment(seg, n_samples, sigma_d_m, sigma_speed, redrawn == "mixture")
        return out

    def _smooth_segment(self, h: list[_Step], n_samples: int, sigma_d_m: float, sigma_speed: float,
                        mixture: bool) -> list[Estimate]:
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
            if nxt.z is not None and cur.z is not None:                   # floors: the chord in 3-D
                chord = np.hypot(chord, nxt.z[picks[t + 1]][:, None] - cur.z[None, :])
            if nxt.distance_m > 0:
                mu = nxt.distance_m * cur.scale[None, :]
                ld = -0.5 * ((chord - mu) / sigma_d_m) ** 2
                ang = np.arctan2(disp[..., 1], disp[..., 0])
                lh = np.where(chord > 0.05, np.log((1 - self.pf.params.heading_floor)
                                                   * np.exp(kappa * (np.cos(ang - nxt.heading_rad - cur.yaw_offset[None, :]) - 1))
                                                   + self.pf.params.heading_floor), 0.0)
                logk = ld + lh
            else:
                # no PDR distance (a fix): the speed model's reach over dt_s, or no motion at all
                sig = sigma_speed * nxt.dt_s + sigma_d_m if nxt.dt_s > 0 else sigma_d_m
                logk = -0.5 * (chord / sig) ** 2
                if mixture and nxt.redrawn_log_q is not None:
                    # sensor resetting made the filter's transition at a fix the mixture
                    # (1 − m)·motion(x̃ | x) + m·q(x̃) (m = inject_mass, q the density the redrawn
                    # particles were drawn from). A redrawn x̃ near the filter's particles at t (the
                    # filter lagging the walker) is chained to them; one far from all of them (a
                    # jump to a wrong fix) takes its predecessor from the filter's weights at t
                    # alone, so it does not drag the smoothed past after it.
                    m = self.pf.params.inject_mass
                    lq = nxt.redrawn_log_q[picks[t + 1]][:, None]
                    logk = np.where(np.isfinite(lq), np.logaddexp(np.log1p(-m) + logk - np.log(2 * np.pi * sig ** 2),
                                                                  np.log(m) + lq), logk)
            lw = cur.log_w[None, :] + logk
            lw -= lw.max(axis=1, keepdims=True)
            pw = np.exp(lw)
            cdf = np.cumsum(pw, axis=1)
            cdf /= cdf[:, -1:]
            u = rng.random((n_samples, 1))
            picks[t] = np.minimum((u > cdf).sum(axis=1), len(cur.log_w) - 1)
        out = []
        ones = np.full(n_samples, 1.0 / n_samples)
        fg = self.pf.floors
        for t in range(T):
            pts = h[t].xy[picks[t]]
            d = pts - pts.mean(axis=0)
            zs = h[t].z
            if zs is None:
                xy, _, _ = constrained_mean(self.g, pts, ones)
                out.append(Estimate(h[t].stamp_ns, xy, d.T @ d / n_samples + 1e-6 * np.eye(2), np.nan))
                continue
            fl = fg.floor_at_height(zs[picks[t]])
            k = int(np.argmax(np.bincount(fl, minlength=fg.n_floors)))
            link, tt, _ = self.g.project(pts[fl == k].mean(axis=0)[None, :], floor=k)
            zk = float(fg.fz[k])
            out.append(Estimate(h[t].stamp_ns, self.g.point_at(link, tt)[0], d.T @ d / n_samples + 1e-6 * np.eye(2),
                                np.nan, zk, float(np.mean((fg.fz[fl] - zk) ** 2)), k))
        return out

