"""The multi-user factor graph: insertion policy, evolving WiFi map, bounded optimisation.

Method: Nowicki & Skrzypczyński, "A Multi-user Personal Indoor Localization System Employing
Graph-based Optimization", Sensors 19(16) 2019, §5. Per user: poses (x, y, θ) in the map frame and
one step length; PDR edges between consecutive poses, WKNN hyperedges to the survey map (fixed) and
— in the joint configuration — to other users' earlier scans (their poses, optimised), a prior on
each step length. Factor models: :mod:`indoor_loc.backend.factors`.

Insertion policy (events of one user arrive in stamp order; :class:`MultiUserGraph` refuses older
ones):

- a user's graph starts at its first *localised* scan (a pose at the WKNN position, heading = the
  PDR heading): before it nothing ties the track to the map (as in the reference implementation,
  whose trajectories span first to last scan);
- PDR hops (stepometer intervals: steps, heading change) accumulate; a pose is added every
  ``pose_period_s`` of stamp time (1.28 s ≈ the paper's 256-sample stepometer window), initialised
  by PDR from the previous pose (a fixed grid in time, not restarted by scan poses);
- at a localised scan: if the PDR distance since the last pose is below ``min_scan_move_m`` the scan
  attaches to the last pose, else a pose is added at the scan stamp, initialised at the WKNN
  position (the paper's policy). The stepometer reports a hop only at its end, so the motion from
  the last hop to the scan is extrapolated at the last hop's step rate and taken off the next hop;
- a scan WKNN cannot localise (fewer than k candidates) gets no hyperedge but still a pose by the
  same rule (from PDR) once the user has started, and joins the map there (joint configuration): a
  user walking beyond the survey leaves fingerprints that later users can match;
- a user whose stamps jumped back (a replay loop, a clock reset) is restarted
  (:meth:`MultiUserGraph.restart_user`): its track so far is kept as a finished user's and its next
  event begins a new track (its own step length), so a user is a sequence of tracks, the last one
  current (``users``; every track by index in ``tracks``).

Solver: ``scipy.optimize.least_squares`` on the whitened residuals of all factors touching the
chosen variables, with the analytic Jacobian assembled in a few vectorised numpy calls: MINPACK's
Levenberg–Marquardt on the dense Jacobian for small live windows (≤ 120 variables, ~10 ms), the
trust-region reflective method with LSMR on the sparse Jacobian for the whole graph. GTSAM's LM with
Python ``CustomFactor`` spends its time in one Python callback per factor (4.5 s for 15 iterations at
this size); the vectorised residual makes a whole-graph solve a few hundred ms and a local window a
few ms.

Bounding (long-running deployments), so memory, matching and solve time stay flat however long
the node runs and however many users come and go:

- freeze: at most ``max_active_poses`` poses are optimised; beyond that the oldest-inserted poses
  are frozen (kept as constants: finished users' first, then the oldest history of active users),
  and a user's poses beyond its newest ``max_user_poses`` are frozen too (per-user history cap);
- drop: beyond ``max_frozen_poses`` frozen poses, frozen poses leave memory with their PDR edges,
  hyperedges and priors — except a frozen pose a PDR edge links to an optimised one (the constant
  that edge needs). Their scans stay in the WiFi map as fixed fingerprints at the poses' final
  positions (later users still match them), and hyperedges of kept poses that named a dropped pose
  name that fixed position instead (the same constant it already was). A user's path then holds
  its poses still in memory; the path published when a user finishes holds its whole trajectory
  unless the caps were reached before;
- learnt map rows are capped (``max_map_rows``, oldest dropped) so matching stays bounded.
 Live updates optimise a window of the
user's last ``window_poses`` poses (everything else constant); the whole active graph is optimised
by :meth:`MultiUserGraph.optimize` (end of a user, end of input, or periodically).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.sparse.linalg import splu

from indoor_loc.params import field as pfield, group, params_from_dict, require
from indoor_loc.backend import factors as F
from indoor_loc.backend.wifi_map import EvolvingMap, Match
from indoor_loc.errors import ConfigError
from indoor_loc.wifi.types import RadioMap, WifiScan
from indoor_loc.wifi.wknn import WknnParams


@dataclass(frozen=True)
class BackendWknnParams(WknnParams):
    """WKNN of the back-end; defaults are the authors' code's comparison (RMS of RSS differences over
    the shared APs, more than 50 % of both scans' APs shared), which the published Table 2 used."""
    error_type: str = pfield("rms", "RSS distance over the shared APs: 'l2', 'l1', 'rms' (the authors' code) or 'mae'")
    shared_threshold: float = pfield(0.5, "minimum fraction of each scan's networks the pair must share, both ways")
    shared_strict: bool = pfield(True, "require more than (instead of at least) shared_threshold (authors' code)")


#: How the survey map enters the graph (``GraphParams.wifi_source``).
WIFI_SOURCES = ("scan", "fix")

#: The graph on a front end's fixes (what ``indoor-loc import ms-indoor`` writes for ``backend_node``):
#: each ``wifi/fix`` a position factor weighted by its own (calibrated) covariance, a Huber kernel at
#: the usual 1.345 σ for the wrong ones, the paper's PDR information; users separate. On a mall
#: (ms_site2) the paper's WKNN hyperedges are worse than the front end they would replace (plain WKNN
#: errs 1.24× (B1) to 1.70× (F7) as much as its fixes on the scans it locates there). Users are
#: separate: on B1 the joint configuration gave 16.67 m mean error at the scan times against
#: 3.96 m — WKNN against other users' scans alone takes the k most similar of a few walks' scans
#: however dissimilar, often across the floor — and 4.37 m (p95 14.58 against 9.60 m) when the
#: survey competes and only matches naming another user's scan are kept. Chosen on ms_site2's B1.
FIX_GRAPH_PARAMS: dict = {"wifi_source": "fix", "joint": False, "wifi_info": 1.0, "robust_kernel": "huber",
                          "robust_threshold_m": 1.345}


#: Added to a robot odometry edge's variances (m², rad²) before inverting them: no edge is certain.
ODOM_VAR_FLOOR = 1e-4


@dataclass(frozen=True)
class GraphParams:
    """Parameters of the multi-user graph (defaults: the paper's joint + step-length configuration)."""
    joint: bool = pfield(True, "match other users' scans too (multi-user coupling); False = each user against "
                               "the survey map only ('separate')")
    estimate_step_length: bool = pfield(True, "optimise a per-user step length (with its prior); False = fixed "
                                              "at step_prior_m")
    step_prior_m: float = pfield(F.STEP_PRIOR_M, "step-length prior mean, m (paper 0.65)")
    step_prior_info: float = pfield(F.STEP_PRIOR_INFO, "step-length prior information, 1/m² (paper 200)")
    pdr_info: list = pfield(list(F.PDR_INFO), "PDR edge information diag (x, y, θ) (paper 1, 1, 15)")
    wifi_info: float = pfield(F.WIFI_INFO, "WKNN hyperedge information, 1/m² (paper 10); with wifi_info_from_fix "
                                           "a factor on the inverse fix covariance")
    wifi_info_from_fix: bool = pfield(False, "weight each hyperedge by the inverse of its WKNN fix covariance "
                                             "(neighbour spread + floor, see Wknn) times wifi_info, instead of "
                                             "the paper's constant wifi_info I")
    wifi_source: str = pfield("scan", "how the survey map enters: 'scan' (the paper) = WKNN hyperedges of each "
                                      "wifi/scan to the survey's fingerprints; 'fix' = each wifi/fix of the front "
                                      "end as a position factor with its covariance (all WiFi factors then weighted "
                                      "by inverse covariance, as wifi_info_from_fix), scans matching only other "
                                      "users' scans (joint)")
    robust_kernel: str = pfield("none", "kernel on WKNN hyperedges and fixes: 'none' (paper), 'huber', 'cauchy' or "
                                        "'maxmix' (max-mixture with a component 10x wider, see factors)")
    robust_threshold_m: float = pfield(2.0, "robust kernel threshold, m of WKNN error")
    pose_period_s: float = pfield(1.28, "a pose every this much stamp time, s (paper: 256 samples at 200 Hz)")
    min_scan_move_m: float = pfield(0.3, "a scan closer than this (PDR distance) to the last pose attaches to it, m")
    gauge_std_m: float = pfield(100.0, "weak prior on each user's first pose position, m (fixes the gauge only)")
    gauge_std_rad: float = pfield(3.0, "weak prior on each user's first heading, rad")
    walkable_std_m: float = pfield(0.0, "floor plan factor (needs the plans, backend_node.floor_plans): a pose "
                                        "outside the walkable area costs (distance to it / this)²; 0 = none")
    fix_bias_std_m: float = pfield(0.0, "wifi_source 'fix': the fixes' error shared along a track (radio-map error "
                                        "is spatially correlated: whole walks' fixes sit metres off together) as one "
                                        "2-D bias per track, added to the pose in every fix factor, with a zero-mean "
                                        "prior of this std, m; the plan (walkable_std_m) can then move a whole track "
                                        "at the cost of the bias prior, not of every fix; 0 = none (independent fixes)")
    walkable_live: bool = pfield(False, "the walkable factor in the live window optimisations too (backend/<u>/pose); "
                                        "False = only in the whole-graph ones (the paths)")
    max_iterations: int = pfield(15, "solver iterations per whole-graph optimisation (paper: 15 LM iterations)")
    window_poses: int = pfield(30, "live: at each localised scan optimise the user's last this many poses "
                                   "(0 = never; batch use then calls optimize())")
    window_iterations: int = pfield(5, "solver iterations of a window optimisation")
    max_active_poses: int = pfield(20000, "at most this many poses are optimised; older ones are frozen")
    max_user_poses: int = pfield(20000, "per-user history: a user's poses beyond its newest this many are frozen")
    max_frozen_poses: int = pfield(2000, "frozen poses kept in memory; beyond this they are dropped (their scans "
                                         "stay in the WiFi map as fixed fingerprints at their final positions)")
    max_map_rows: int = pfield(20000, "at most this many users' scans in the WiFi map (oldest dropped)")
    wknn: BackendWknnParams = group(BackendWknnParams, "WKNN against the survey and users' scans (wknn.k, ...)")

    def __post_init__(self) -> None:
        if isinstance(self.wknn, dict):        # GraphParams(wknn={"k": 3}) in code and tests
            object.__setattr__(self, "wknn", params_from_dict(BackendWknnParams, self.wknn))

    def validate(self) -> None:
        n = type(self).__name__
        require(self.step_prior_m > 0, n, "step_prior_m", "> 0", self.step_prior_m)
        require(self.step_prior_info > 0, n, "step_prior_info", "> 0", self.step_prior_info)
        require(len(self.pdr_info) == 3 and all(float(v) > 0 for v in self.pdr_info), n, "pdr_info",
                  "three positive numbers", self.pdr_info)
        require(self.wifi_info > 0, n, "wifi_info", "> 0", self.wifi_info)
        require(self.robust_kernel in F.ROBUST_KERNELS, n, "robust_kernel", f"one of {F.ROBUST_KERNELS}",
                  self.robust_kernel)
        require(self.robust_threshold_m > 0, n, "robust_threshold_m", "> 0", self.robust_threshold_m)
        require(self.wifi_source in WIFI_SOURCES, n, "wifi_source", f"one of {WIFI_SOURCES}", self.wifi_source)
        require(self.pose_period_s > 0, n, "pose_period_s", "> 0", self.pose_period_s)
        require(self.min_scan_move_m >= 0, n, "min_scan_move_m", ">= 0", self.min_scan_move_m)
        require(self.gauge_std_m > 0 and self.gauge_std_rad > 0, n, "gauge_std_m/gauge_std_rad", "> 0",
                  (self.gauge_std_m, self.gauge_std_rad))
        require(self.walkable_std_m >= 0, n, "walkable_std_m", ">= 0", self.walkable_std_m)
        require(self.fix_bias_std_m >= 0, n, "fix_bias_std_m", ">= 0", self.fix_bias_std_m)
        require(self.max_iterations >= 1, n, "max_iterations", ">= 1", self.max_iterations)
        require(self.window_poses >= 0, n, "window_poses", ">= 0", self.window_poses)
        require(self.window_iterations >= 1, n, "window_iterations", ">= 1", self.window_iterations)
        require(self.max_active_poses >= 10, n, "max_active_poses", ">= 10", self.max_active_poses)
        require(self.max_user_poses >= 2, n, "max_user_poses", ">= 2", self.max_user_poses)
        require(self.max_frozen_poses >= 0, n, "max_frozen_poses", ">= 0", self.max_frozen_poses)
        require(self.max_map_rows >= 0, n, "max_map_rows", ">= 0", self.max_map_rows)
        self.wknn_params()

    @property
    def info_from_fix(self) -> bool:
        """WiFi factors weighted by inverse fix covariances (robust threshold in standard deviations)."""
        return self.wifi_info_from_fix or self.wifi_source == "fix"

    def wknn_params(self) -> WknnParams:
        try:
            self.wknn.validate()
        except ConfigError as err:
            raise ConfigError(f"{type(self).__name__}.wknn: {err}") from err
        return self.wknn


@dataclass
class UserTrack:
    """Per-user insertion state."""
    index: int
    name: str
    poses: list = field(default_factory=list)         # global pose indices, in stamp order
    started: bool = False
    last_event_ns: int | None = None                  # newest hop end or scan stamp taken
    last_hop_end_ns: int | None = None
    last_grid_ns: int = 0                             # stamp of the last periodic pose (or the first pose)
    last_yaw: float = 0.0                             # odometry yaw at the last hop end
    step_rate: float = 0.0                            # steps/s of the last hop
    carry_steps: float = 0.0                          # steps already given to a scan pose
    acc_steps: float = 0.0                            # since the last pose
    acc_dtheta: float = 0.0
    acc_var: list | None = None                       # robot odometry: (x-y, θ) variances since the last pose
    finished: bool = False
    scans_localised: int = 0                          # scans WKNN localised (wifi_source fix: fixes taken)
    scans_unlocalised: int = 0                        # scans not localised (wifi_source fix: before any fix)
    scans_from_users: int = 0                         # hyperedges with >= 1 other user's scan
    floor_z: float = math.nan                         # height of the user's floor (its newest fix's), m


@dataclass(frozen=True)
class SolveReport:
    n_poses: int
    n_factors: int
    iterations: int
    cost0: float
    cost: float
    wall_s: float
    #: False when the time budget ran out first (the estimates are the best the solver had reached)
    completed: bool = True


@dataclass
class _Best:
    """The lowest-cost point a solver evaluated so far."""
    z: np.ndarray
    cost: float
    nfev: int = 0


def _with_deadline(fun, jac, z0: np.ndarray, r0: np.ndarray, deadline: float):
    """``fun`` and ``jac`` raising TimeoutError (caught by the caller, :meth:`MultiUserGraph._solve`) once
    ``time.monotonic()`` is past ``deadline``,
    ``fun`` keeping the lowest-cost point it evaluated (a trust-region solver's accepted iterate is
    its lowest-cost evaluation so far, so that is where the solver was when it was stopped)."""
    best = _Best(z0.copy(), 0.5 * float(r0 @ r0))

    def timed_fun(z):
        if time.monotonic() > deadline:
            raise TimeoutError("the solver's time budget ran out")
        r = fun(z)
        best.nfev += 1
        cost = 0.5 * float(r @ r)
        if cost < best.cost:
            best.z, best.cost = z.copy(), cost
        return r

    def timed_jac(z):
        if time.monotonic() > deadline:
            raise TimeoutError("the solver's time budget ran out")
        return jac(z)

    return timed_fun, timed_jac, best


@dataclass(frozen=True)
class _Factored:
    """A solve's Jacobian and the LU factors of its information matrix JᵀJ (+ 1e-9 I, so a variable
    no factor constrains does not make it singular); ``lu`` None if that failed."""
    jac: Any
    lu: Any

    @classmethod
    def of(cls, J: Any) -> "_Factored":
        J = sp.csr_matrix(J)
        H = (J.T @ J).tocsc()
        try:
            # H is symmetric: a minimum-degree ordering of its own pattern, diagonal pivots (about half
            # the fill of the default column ordering of a general matrix)
            lu = splu(H + sp.identity(H.shape[0], format="csc") * 1e-9, permc_spec="MMD_AT_PLUS_A",
                      options={"SymmetricMode": True})
        except RuntimeError:
            lu = None
        return cls(J, lu)

    def cov(self, c: int) -> np.ndarray | None:
        """(3, 3) block of (JᵀJ)⁻¹ at columns ``c..c+3``."""
        if self.lu is None:
            return None
        E = np.zeros((self.lu.shape[0], 3))
        E[c:c + 3] = np.eye(3)
        return self.lu.solve(E)[c:c + 3]


class _Growing:
    """Columns of a growable table (amortised O(1) append)."""

    def __init__(self, **cols: tuple[tuple, Any]) -> None:
        self._spec = cols
        self.n = 0
        self._cap = 16
        for name, (shape, dtype) in cols.items():
            setattr(self, name, np.zeros((16,) + shape, dtype))

    def append(self, **vals: Any) -> int:
        n = self.n
        if n == self._cap:
            self._cap *= 2
            for name in self._spec:
                a = getattr(self, name)
                b = np.zeros((self._cap,) + a.shape[1:], a.dtype)
                b[:n] = a[:n]
                setattr(self, name, b)
        d = self.__dict__
        for name, v in vals.items():
            d[name][n] = v
        self.n = n + 1
        return n

    def view(self, name: str) -> np.ndarray:
        return getattr(self, name)[:self.n]

    def keep(self, mask: np.ndarray) -> None:
        """Keep the rows where ``mask`` (n,) is True, in order."""
        for name in self._spec:
            a = getattr(self, name)
            kept = a[:self.n][mask]
            a[:len(kept)] = kept
        self.n = int(np.count_nonzero(mask))


class MultiUserGraph:
    """Poses of many users, their PDR and WKNN factors, the evolving WiFi map (see module docstring)."""

    def __init__(self, params: GraphParams, survey: RadioMap | None = None, walkable: Any = None) -> None:
        params.validate()
        self.params = params
        #: the floor plans' distance field (:class:`indoor_loc.backend.walkable_term.WalkableField`); with
        #: ``walkable_std_m`` > 0 every optimised pose on a floor with a plan gets the walkable factor
        self.walkable = walkable if params.walkable_std_m > 0 else None
        self.k = int(params.wknn_params().k)
        self.map = EvolvingMap(params.wknn_params(), max_rows=params.max_map_rows)
        if survey is not None and survey.n_scans:
            self.map.add_fixed(survey)
        self.users: dict[str, UserTrack] = {}         # each user's current track
        self.tracks: list[UserTrack] = []              # every track by index (a restarted user's earlier ones too)
        self.user_names: list[str] = []                # the user of each track
        self.step_len = np.zeros(0)
        #: per track: the common error of its fixes (fix_bias_std_m > 0), m
        self.fix_bias = np.zeros((0, 2))
        self.poses = _Growing(x=((3,), float), user=((), np.int64), stamp=((), np.int64), frozen=((), bool),
                              z=((), float))
        self.pdr = _Growing(prev=((), np.int64), cur=((), np.int64), steps=((), float), dtheta=((), float),
                            sqrt_info=((3,), float))
        self.wifi = _Growing(pose=((), np.int64), refs=((self.k,), np.int64), w=((self.k,), float),
                             sqrt_info=((2, 2), float))
        self.gauge = _Growing(pose=((), np.int64), x=((3,), float))
        self.n_frozen = 0
        self.n_dropped = 0
        self._last_J: tuple | None = None        # (jac, z, var, col) of the last solve
        #: window optimisations at localised scans stop at this ``time.monotonic()`` (None: never): the
        #: end of input takes in everything buffered on a time budget, a whole-graph optimisation next
        self.windows_until: float | None = None
        self.last_solve: SolveReport | None = None
        self._sqrt_pdr = np.sqrt(np.asarray(params.pdr_info, float))
        self._sqrt_wifi = math.sqrt(params.wifi_info)
        self._sqrt_wifi_eye = self._sqrt_wifi * np.eye(2)      # copied into the hyperedge table
        self._sqrt_step = math.sqrt(params.step_prior_info)

    # -- users and events ------------------------------------------------------------------------
    def user(self, name: str) -> UserTrack:
        tr = self.users.get(name)
        if tr is None:
            tr = self.users[name] = UserTrack(len(self.user_names), name)
            self.tracks.append(tr)
            self.user_names.append(name)
            self.step_len = np.append(self.step_len, self.params.step_prior_m)
            self.fix_bias = np.vstack([self.fix_bias, np.zeros((1, 2))])
        return tr

    def _check_order(self, tr: UserTrack, stamp_ns: int, what: str) -> None:
        if tr.last_event_ns is not None and stamp_ns < tr.last_event_ns:
            raise ValueError(f"{tr.name}: {what} stamp {stamp_ns} older than the last event {tr.last_event_ns}")

    def add_hop(self, name: str, t_start_ns: int, t_end_ns: int, steps: float, yaw: float, *,
                var: tuple[float, float] | None = None) -> int | None:
        """One stepometer hop of user ``name``: ``steps`` over [t_start, t_end], odometry yaw (rad) at
        its end. Returns the index of a pose it added, else None. ``var``: a robot odometry increment's
        own (position m², heading rad²) variances; the edge to the next pose then takes the inverse of
        their sums as its information instead of ``pdr_info``."""
        tr = self.users.get(name) or self.user(name)
        t_end_ns = int(t_end_ns)
        self._check_order(tr, t_end_ns, "hop")
        last_end = tr.last_hop_end_ns
        if last_end is not None and t_end_ns <= last_end:
            raise ValueError(f"{name}: hop end {t_end_ns} not after the previous hop end {last_end}")
        steps = float(steps)
        dtheta = F.wrap_scalar(yaw - tr.last_yaw) if last_end is not None else 0.0
        dur = max((t_end_ns - t_start_ns) * 1e-9, 1e-3)
        tr.step_rate = max(steps, 0.0) / dur
        tr.last_hop_end_ns = tr.last_event_ns = t_end_ns
        tr.last_yaw = float(yaw)
        if not tr.started:
            return None
        carry = tr.carry_steps
        tr.carry_steps = max(carry - steps, 0.0)
        tr.acc_steps += max(steps - carry, 0.0)
        tr.acc_dtheta += dtheta
        if var is not None:
            tr.acc_var = [a + float(v) for a, v in zip(tr.acc_var or [0.0, 0.0], var)]
        if (t_end_ns - tr.last_grid_ns) * 1e-9 >= self.params.pose_period_s - 1e-3:
            tr.last_grid_ns = t_end_ns
            self._new_pose(tr, t_end_ns, None)
            self._bound(tr)
            return tr.poses[-1]
        return None

    def add_scan(self, name: str, scan: WifiScan) -> tuple[int | None, Match | None]:
        """A WiFi scan of user ``name``. Returns (pose it is attached to or None (user not started yet),
        the WKNN match or None). With ``wifi_source: fix`` a scan matches only other users' scans
        (joint; the survey enters through :meth:`add_fix`) and never starts a user."""
        tr = self.users.get(name) or self.user(name)
        self._check_order(tr, scan.stamp_ns, "scan")
        tr.last_event_ns = int(scan.stamp_ns)
        by_fix = self.params.wifi_source == "fix"
        match = None
        if not by_fix or (self.params.joint and tr.started):
            match = self.map.match(scan, user=tr.index, joint=self.params.joint,
                                   pose_xy=self.poses.x[:self.poses.n, :2], survey=not by_fix)
        if match is None:
            if not by_fix or not tr.started:      # with fixes: a scan before the user's first fix
                tr.scans_unlocalised += 1
            if not tr.started or (by_fix and not self.params.joint):
                return None, None
        else:
            tr.scans_localised += int(not by_fix)
            tr.scans_from_users += int(match.n_from_users > 0)
        i = self._scan_pose(tr, scan.stamp_ns, match.fix.xy if match is not None else None)
        if match is not None:
            self.wifi.append(pose=i, refs=match.refs, w=match.weights, sqrt_info=self._wifi_sqrt_info(match.fix.cov))
        if self.params.joint:
            self.map.add_scan(scan, i, tr.index)     # localised or not, it is a fingerprint at pose i
        return self._after_wifi(tr, name, i, match is not None), match

    def add_fix(self, name: str, stamp_ns: int, xy: np.ndarray, cov: np.ndarray) -> int:
        """A position fix of user ``name`` from the WiFi front end (``wifi_source: fix``): a factor
        pulling the pose at ``stamp_ns`` to ``xy`` (2,) with information ``wifi_info`` × ``cov`` (2, 2)⁻¹,
        as a hyperedge to one fixed position. It starts the user; it attaches to the last pose or adds
        one by the same rule as a scan. Returns the pose index. A non-finite ``xy`` or a ``cov`` that is
        not a finite symmetric positive-definite 2×2 matrix is a ValueError, raised before anything
        changes (it would poison every later solve)."""
        xy = np.asarray(xy, float).reshape(2)
        cov = np.asarray(cov, float).reshape(2, 2)
        if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(cov)) and cov[0, 1] == cov[1, 0]
                and cov[0, 0] > 0 and np.linalg.det(cov) > 0):
            raise ValueError(f"{name}: fix at {stamp_ns}: position {xy.tolist()} or covariance {cov.tolist()} "
                             "not finite / positive definite")
        tr = self.users.get(name) or self.user(name)
        self._check_order(tr, stamp_ns, "fix")
        tr.last_event_ns = int(stamp_ns)
        i = self._scan_pose(tr, stamp_ns, xy)
        tr.scans_localised += 1
        refs = np.full(self.k, self.map.add_point(xy), np.int64)
        w = np.zeros(self.k)
        w[0] = 1.0
        self.wifi.append(pose=i, refs=refs, w=w, sqrt_info=self._wifi_sqrt_info(cov))
        return self._after_wifi(tr, name, i, True)

    def _scan_pose(self, tr: UserTrack, stamp_ns: int, xy: np.ndarray | None) -> int:
        """The pose a localised (``xy``: its fix) or unlocalised scan / fix at ``stamp_ns`` attaches to:
        the user's first pose (at ``xy``) if it has not started, the last pose if PDR moved less than
        ``min_scan_move_m`` since, else a new pose (at ``xy`` when given, else from PDR)."""
        if not tr.started:
            assert xy is not None
            tr.started = True
            tr.last_grid_ns = int(stamp_ns)
            i = self._add_pose(tr, stamp_ns, np.array([xy[0], xy[1], tr.last_yaw]))
            self.gauge.append(pose=i, x=self.poses.x[i].copy())
            return i
        extra = 0.0
        if tr.last_hop_end_ns is not None and stamp_ns > tr.last_hop_end_ns:
            extra = tr.step_rate * (stamp_ns - tr.last_hop_end_ns) * 1e-9
        move = self.step_len[tr.index] * (tr.acc_steps + extra)
        if move < self.params.min_scan_move_m:
            return tr.poses[-1]
        tr.carry_steps += extra
        tr.acc_steps += extra
        return self._new_pose(tr, stamp_ns, xy)

    def _after_wifi(self, tr: UserTrack, name: str, i: int, localised: bool) -> int:
        """Bound the graph after a scan or fix at pose ``i`` (returned renumbered) and optimise the
        user's window when it was localised."""
        pose_map = self._bound(tr)
        if pose_map is not None:
            i = int(pose_map[i])
        if self.params.window_poses and localised and (self.windows_until is None
                                                        or time.monotonic() < self.windows_until):
            self.optimize_window(name)
        return i

    def _wifi_sqrt_info(self, cov: np.ndarray) -> np.ndarray:
        """Square root L (Lᵀ L = Ω) of a hyperedge's information (``cov``: its fix's covariance)."""
        if not self.params.info_from_fix:
            return self._sqrt_wifi_eye
        info = self.params.wifi_info * np.linalg.inv(np.asarray(cov, float))
        return np.linalg.cholesky(info).T

    def set_floor(self, name: str, z: float) -> None:
        """User ``name`` is on the floor at height ``z`` (m) from now on: its next poses take that floor's
        plan in the walkable factor."""
        (self.users.get(name) or self.user(name)).floor_z = float(z)

    def _add_pose(self, tr: UserTrack, stamp_ns: int, x: np.ndarray) -> int:
        i = self.poses.append(x=x, user=tr.index, stamp=stamp_ns, frozen=False, z=tr.floor_z)
        tr.poses.append(i)
        return i

    def _new_pose(self, tr: UserTrack, stamp_ns: int, xy: np.ndarray | None) -> int:
        """A pose after the last one, from the accumulated PDR (position from ``xy`` when given)."""
        last = tr.poses[-1]
        px, py, pth = self.poses.x[last].tolist()
        d = float(self.step_len[tr.index]) * tr.acc_steps
        mean = pth + 0.5 * tr.acc_dtheta
        x = np.array([px + d * math.cos(mean), py + d * math.sin(mean), F.wrap_scalar(pth + tr.acc_dtheta)])
        if xy is not None:
            x[:2] = xy
        i = self._add_pose(tr, stamp_ns, x)
        sqrt_info = self._sqrt_pdr
        if tr.acc_var is not None:           # a robot's odometry: the edge's own information
            vxy, vth = tr.acc_var
            sqrt_info = 1.0 / np.sqrt(np.array([vxy, vxy, vth]) + ODOM_VAR_FLOOR)
            tr.acc_var = [0.0, 0.0]
        self.pdr.append(prev=last, cur=i, steps=tr.acc_steps, dtheta=tr.acc_dtheta, sqrt_info=sqrt_info)
        tr.acc_steps = tr.acc_dtheta = 0.0
        return i

    def finish_user(self, name: str) -> None:
        """The user's input has ended (nothing else changes: its poses stay optimisable until the
        bound freezes them; its scans stay in the map)."""
        if name in self.users:
            self.users[name].finished = True

    def restart_user(self, name: str) -> None:
        """Start user ``name`` afresh (its stamps went back: a replay loop, a clock reset): its
        current track is finished and detached — kept as a finished user's track is (optimised
        until the bound freezes it, its scans in the map, which the new track may match as another
        user's in the joint configuration) — and its next event begins a new track, with a new
        step length at its prior."""
        tr = self.users.pop(name, None)
        if tr is not None:
            tr.finished = True

    def _bound(self, tr: UserTrack) -> np.ndarray | None:
        """Freeze the oldest poses of ``tr`` beyond ``max_user_poses`` and the oldest-inserted poses
        beyond ``max_active_poses`` (finished users first); drop frozen poses beyond
        ``max_frozen_poses``. Returns the old -> new pose index map when poses were dropped."""
        p = self.params
        if (len(tr.poses) <= p.max_user_poses and self.poses.n - self.n_frozen <= p.max_active_poses
                and self.n_frozen <= p.max_frozen_poses):
            return None                  # within every bound: nothing to freeze or drop
        frozen = self.poses.view("frozen")
        old = np.asarray(tr.poses[:-self.params.max_user_poses], np.int64)
        if len(old):
            old = old[~frozen[old]]
            frozen[old] = True
            self.n_frozen += len(old)
        excess = self.poses.n - self.n_frozen - self.params.max_active_poses
        if excess > 0:
            finished = np.array([t.finished for t in self.tracks])
            cand = np.flatnonzero(~frozen)
            order = np.argsort(~finished[self.poses.user[cand]], kind="stable")   # finished users' poses first
            pick = cand[order[:excess]]
            frozen[pick] = True
            self.n_frozen += len(pick)
        if self.n_frozen > self.params.max_frozen_poses:
            return self._drop_frozen()
        return None

    def _drop_frozen(self) -> np.ndarray | None:
        """Remove frozen poses from memory (see module docstring): a frozen pose one of whose PDR
        edges leads to an optimised pose stays (a constant the edge needs); the rest go, with
        their PDR edges, hyperedges and gauge priors. Their scans stay in the map, pinned at the
        poses' final positions, and hyperedges of kept poses that named them name the pinned
        positions instead. Returns the old -> new pose index map (-1 = dropped)."""
        n = self.poses.n
        frozen = self.poses.view("frozen")
        pprev, pcur = self.pdr.view("prev"), self.pdr.view("cur")
        needed = np.zeros(n, bool)
        mixed = frozen[pprev] != frozen[pcur]
        needed[np.where(frozen[pprev], pprev, pcur)[mixed]] = True
        drop = frozen & ~needed
        if not drop.any():
            return None
        gone = np.flatnonzero(drop)
        names = [self.user_names[u] for u in self.poses.user[gone]]
        fixed_ref = self.map.pin(gone, self.poses.x[gone, :2], names)
        # hyperedges: drop those of dropped poses, rewrite references to dropped poses
        wkeep = ~drop[self.wifi.view("pose")]
        self.wifi.keep(wkeep)
        refs = self.wifi.view("refs")
        lut = np.zeros(n, np.int64)
        lut[gone] = fixed_ref
        hit = refs >= 0
        hit[hit] = drop[refs[hit]]
        refs[hit] = lut[refs[hit]]
        self.pdr.keep(~(drop[self.pdr.view("prev")] | drop[self.pdr.view("cur")]))
        self.gauge.keep(~drop[self.gauge.view("pose")])
        # renumber poses
        pose_map = np.cumsum(~drop) - 1
        pose_map[drop] = -1
        self.poses.keep(~drop)
        for name in ("prev", "cur"):
            a = self.pdr.view(name)
            a[:] = pose_map[a]
        a = self.wifi.view("pose")
        a[:] = pose_map[a]
        refs = self.wifi.view("refs")
        refs[refs >= 0] = pose_map[refs[refs >= 0]]
        a = self.gauge.view("pose")
        a[:] = pose_map[a]
        self.map.renumber(pose_map)
        fix_map = self.map.collect_fixed(refs.ravel(), self.map.n_loaded_fixed)
        refs[refs < 0] = -1 - fix_map[-1 - refs[refs < 0]]
        for t in self.tracks:
            if t.poses:
                idx = pose_map[np.asarray(t.poses, np.int64)]
                t.poses = [int(v) for v in idx[idx >= 0]]
        self.n_frozen = int(np.count_nonzero(self.poses.view("frozen")))
        self.n_dropped += len(gone)
        self._last_J = None
        return pose_map

    # -- optimisation ---------------------------------------------------------------------------
    def optimize(self, *, max_iterations: int | None = None, deadline: float | None = None) -> SolveReport | None:
        """Optimise every active (not frozen) pose and the step lengths of their users.

        ``deadline`` (``time.monotonic()`` seconds; None = none): the solver stops at the first
        residual or Jacobian evaluation after it and the estimates are those of the lowest cost it
        evaluated (never worse than the start); the report says ``completed=False``. The solver is
        checked between evaluations, so it may overrun the deadline by one of its steps."""
        var = np.flatnonzero(~self.poses.view("frozen"))
        return self._solve(var, max_iterations or self.params.max_iterations, deadline)

    def solved_users(self) -> list[str]:
        """Names of the users (current tracks) with a pose among the last solve's variables."""
        last = self._last_J
        if last is None:
            return []
        var = last[2]
        idx = set(np.unique(self.poses.user[var[var < self.poses.n]]).tolist())
        return [u for u, tr in self.users.items() if tr.index in idx]

    def optimize_window(self, name: str) -> SolveReport | None:
        """Optimise the user's last ``window_poses`` poses (and its step length); the rest constant."""
        tr = self.users[name]
        var = np.asarray(tr.poses[-self.params.window_poses:], np.int64)
        var = var[~self.poses.frozen[var]]
        return self._solve(var, self.params.window_iterations, walkable=self.params.walkable_live)

    def _solve(self, var: np.ndarray, max_iter: int, deadline: float | None = None, *,
               walkable: bool = True) -> SolveReport | None:
        if self.params.robust_kernel == "maxmix":
            # the max-mixture cost is not convex: a solve from poses that a stretch of wrong fixes placed
            # stays with them. Huber's convex cost first, then the mixture from its optimum
            self._solve_with(var, max_iter, deadline, walkable=walkable, kernel="huber")
        return self._solve_with(var, max_iter, deadline, walkable=walkable, kernel=self.params.robust_kernel)

    def _solve_with(self, var: np.ndarray, max_iter: int, deadline: float | None = None, *,
                    walkable: bool = True, kernel: str) -> SolveReport | None:
        t0 = time.perf_counter()
        prob = self.problem(var, walkable=walkable, kernel=kernel)
        if prob is None:
            return None
        fun, jac, z0, unpack, n_factors = prob
        r0 = fun(z0)
        if deadline is not None:
            fun, jac, best = _with_deadline(fun, jac, z0, r0, deadline)
        completed = True
        try:
            if len(z0) <= 120 and len(r0) >= len(z0):
                # small windows: MINPACK's Levenberg-Marquardt on the dense Jacobian (a few ms)
                sol = least_squares(fun, z0, jac=lambda z: jac(z).toarray(), method="lm", max_nfev=max_iter)
            else:
                # the whole graph: trust-region reflective with LSMR on the sparse Jacobian; columns scaled
                # by their Jacobian norms (the weak gauge priors make the raw problem ill-conditioned, and
                # LSMR then needs hundreds of products per step) and inexact steps (LSMR tolerance 1e-4,
                # inexact Newton): the same final cost to 0.1 % at a fifth of the time
                sol = least_squares(fun, z0, jac=jac, method="trf", max_nfev=max_iter, x_scale="jac",
                                    tr_solver="lsmr", tr_options={"atol": 1e-4, "btol": 1e-4})
            z_end, cost, nfev = sol.x, float(sol.cost), int(sol.nfev)
        except TimeoutError:
            completed = False
            z_end, cost, nfev = best.z, best.cost, best.nfev
        Xc, L, B = unpack(z_end)
        Xc[var, 2] = F.wrap(Xc[var, 2])
        self.poses.x[:self.poses.n] = Xc
        self.step_len = L
        self.fix_bias = B
        col = np.full(self.poses.n, -1, np.int64)
        col[var] = 3 * np.arange(len(var))
        self._last_J = (prob[1], z_end.copy(), var, col)     # J at the optimum: evaluated by marginal_cov
        rep = SolveReport(len(var), n_factors, nfev, 0.5 * float(r0 @ r0), cost, time.perf_counter() - t0, completed)
        self.last_solve = rep
        return rep

    def problem(self, var: np.ndarray, *, walkable: bool = True, kernel: str | None = None):
        """The least-squares problem over poses ``var`` (and their users' step lengths): (fun(z) ->
        whitened residuals, jac(z) -> sparse CSR Jacobian, z0, unpack(z) -> (poses, step lengths, fix biases),
        number of factors), or None when no factor touches the variables. ``kernel``: the robust kernel
        instead of ``robust_kernel``."""
        var = np.asarray(var, np.int64)
        if len(var) == 0:
            return None
        p = self.params
        kernel = p.robust_kernel if kernel is None else kernel
        n_pose = self.poses.n
        X = self.poses.view("x")
        col = np.full(n_pose, -1, np.int64)
        col[var] = 3 * np.arange(len(var))
        var_users = np.unique(self.poses.user[var]) if p.estimate_step_length else np.zeros(0, np.int64)
        ucol = np.full(len(self.user_names), -1, np.int64)
        ucol[var_users] = 3 * len(var) + np.arange(len(var_users))
        # fix-bias variables: the users of the variable poses (their fix factors share the bias)
        bias_users = (np.unique(self.poses.user[var]) if p.fix_bias_std_m > 0 and p.wifi_source == "fix"
                      else np.zeros(0, np.int64))
        bcol = np.full(len(self.user_names), -1, np.int64)
        bcol[bias_users] = 3 * len(var) + len(var_users) + 2 * np.arange(len(bias_users))
        n_b = len(bias_users)
        n_x = 3 * len(var) + len(var_users) + 2 * n_b
        isvar = col >= 0

        # factors touching a variable
        pprev, pcur = self.pdr.view("prev"), self.pdr.view("cur")
        sel_p = np.flatnonzero(isvar[pprev] | isvar[pcur])
        pprev, pcur = pprev[sel_p], pcur[sel_p]
        psteps, pdth = self.pdr.view("steps")[sel_p], self.pdr.view("dtheta")[sel_p]
        psqrt = self.pdr.view("sqrt_info")[sel_p]
        puser = self.poses.user[pcur]
        wpose, wrefs, ww = self.wifi.view("pose"), self.wifi.view("refs"), self.wifi.view("w")
        wL = self.wifi.view("sqrt_info")
        refvar = np.where(wrefs >= 0, isvar[np.maximum(wrefs, 0)], False)
        sel_w = np.flatnonzero(isvar[wpose] | refvar.any(axis=1))
        wpose, wrefs, ww, refvar, wL = wpose[sel_w], wrefs[sel_w], ww[sel_w], refvar[sel_w], wL[sel_w]
        # the fix factors (every reference a fixed point) of users with a bias variable
        wbcol = np.where((wrefs < 0).all(axis=1), bcol[self.poses.user[wpose]], -1)
        has_b = wbcol >= 0
        gpose, gx = self.gauge.view("pose"), self.gauge.view("x")
        sel_g = np.flatnonzero(isvar[gpose])
        gpose, gx = gpose[sel_g], gx[sel_g]
        n_p, n_w, n_g, n_u = len(pprev), len(wpose), len(gpose), len(var_users)
        if n_p + n_w + n_g == 0:
            return None
        # walkable factors: the variable poses on a floor with a plan
        wk_pose = np.zeros(0, np.int64)
        if self.walkable is not None and walkable:
            zv = self.poses.z[var]
            wk_pose = var[np.array([self.walkable.floor_at(float(z)) is not None for z in zv], bool)] \
                if len(var) else wk_pose
        n_k = len(wk_pose)
        wk_z = self.poses.z[wk_pose]
        inv_wk = 1.0 / p.walkable_std_m if n_k else 0.0
        r_p, r_w, r_g = 0, 3 * n_p, 3 * n_p + 2 * n_w
        r_u = r_g + 3 * n_g
        r_k = r_u + n_u
        r_b = r_k + n_k
        n_r = r_b + 2 * n_b
        fixed_xy = self.map.fixed_xy
        sqrt_g = np.array([1 / p.gauge_std_m, 1 / p.gauge_std_m, 1 / p.gauge_std_rad])
        # threshold in whitened units: robust_threshold_m at the paper's information, else in sigmas
        c_rob = (1.0 if p.info_from_fix else self._sqrt_wifi) * p.robust_threshold_m

        # Jacobian sparsity: (rows, cols, keep) in the order jac() produces its values. Entries the
        # factor models make zero whatever the estimates are left out (``nz``): the PDR blocks'
        # x-y couplings and the heading row of d e / d l, the gauge priors' off-diagonals and, without
        # a robust kernel, the hyperedges' off-diagonals (lower left only with a fix's information) —
        # nearly half of all entries, which every LSMR product would otherwise multiply by zero
        def blk(row0, nrow, cols0, ncol, ok, nz=None):
            """Entries of (N, nrow, ncol) blocks: rows row0[n] + a, cols cols0[n] + b."""
            r = row0[:, None, None] + np.arange(nrow)[None, :, None] + np.zeros((1, 1, ncol), np.int64)
            c = cols0[:, None, None] + np.zeros((1, nrow, 1), np.int64) + np.arange(ncol)[None, None, :]
            k = ok[:, None, None] if nz is None else ok[:, None, None] & nz[None]
            k = np.broadcast_to(k, r.shape)
            return r.ravel(), c.ravel(), k.ravel()

        nz_pdr = np.array([[1, 0, 1], [0, 1, 1], [0, 0, 1]], bool)      # F.pdr_error's J_prev, J_cur
        nz_len = np.array([[1], [1], [0]], bool)                          # its J_len
        # whitened hyperedge blocks are L (and -w_j L): diagonal for a scalar information, upper
        # triangular for a fix's (Cholesky) one; a robust kernel's correction fills them
        nz_wifi = (None if kernel != "none" else
                   np.triu(np.ones((2, 2), bool)) if p.info_from_fix else np.eye(2, dtype=bool))
        rp = r_p + 3 * np.arange(n_p)
        rw = r_w + 2 * np.arange(n_w)
        parts = [blk(rp, 3, col[pprev], 3, isvar[pprev], nz_pdr), blk(rp, 3, col[pcur], 3, isvar[pcur], nz_pdr),
                 blk(rp, 3, ucol[puser], 1, ucol[puser] >= 0, nz_len),
                 blk(rw, 2, col[wpose], 2, isvar[wpose], nz_wifi)]
        for j in range(self.k):
            rj = np.maximum(wrefs[:, j], 0)
            parts.append(blk(rw, 2, col[rj], 2, refvar[:, j], nz_wifi))
        parts.append(blk(r_g + 3 * np.arange(n_g), 3, col[gpose], 3, np.ones(n_g, bool), np.eye(3, dtype=bool)))
        parts.append(blk(r_u + np.arange(n_u), 1, ucol[var_users], 1, np.ones(n_u, bool)))
        parts.append(blk(r_k + np.arange(n_k), 1, col[wk_pose], 2, np.ones(n_k, bool)))
        parts.append(blk(rw, 2, wbcol, 2, has_b, nz_wifi))
        parts.append(blk(r_b + 2 * np.arange(n_b), 2, bcol[bias_users], 2, np.ones(n_b, bool), np.eye(2, dtype=bool)))
        rows = np.concatenate([q[0] for q in parts])
        cols = np.concatenate([q[1] for q in parts])
        keep = np.concatenate([q[2] for q in parts])
        rows, cols = rows[keep], cols[keep]
        # CSR structure built once: entries sorted row-major, duplicates (two neighbours of one
        # hyperedge on the same pose) summed; each Jacobian evaluation only fills in the values
        lin, slot = np.unique(rows * n_x + cols, return_inverse=True)
        csr_indices = lin % n_x
        csr_indptr = np.searchsorted(lin // n_x, np.arange(n_r + 1))
        slot = slot.ravel()

        base_x = X.copy()
        base_l = self.step_len.copy()
        base_b = self.fix_bias.copy()
        inv_b = 1.0 / p.fix_bias_std_m if n_b else 0.0
        wuser = self.poses.user[wpose]
        # the closures below hold no reference to the graph (the last solve's jac outlives the
        # solve in _last_J; a graph -> jac -> graph cycle would only be freed by the cyclic GC)
        sqrt_pdr, sqrt_step, n_nbr, walkable = psqrt, self._sqrt_step, self.k, self.walkable

        def unpack(z):
            Xc = base_x.copy()
            Xc[var] = z[:3 * len(var)].reshape(-1, 3)
            L = base_l.copy()
            if n_u:
                L[var_users] = z[3 * len(var):3 * len(var) + n_u]
            B = base_b.copy()
            if n_b:
                B[bias_users] = z[3 * len(var) + n_u:].reshape(-1, 2)
            return Xc, L, B

        # neighbour positions (n_w, k, 2): the fixed ones once, the poses' at each evaluation
        nbr_fixed = np.empty(wrefs.shape + (2,))
        at_fixed = wrefs < 0
        nbr_fixed[at_fixed] = fixed_xy[-1 - wrefs[at_fixed]]
        at_pose = ~at_fixed
        pose_refs = wrefs[at_pose]

        def nbr_xy(Xc):
            out = nbr_fixed.copy()
            out[at_pose] = Xc[pose_refs, :2]
            return out

        def evaluate(z, want_jac):
            Xc, L, B = unpack(z)
            res = np.empty(n_r)
            ep = F.pdr_error(Xc[pprev], Xc[pcur], L[puser], psteps, pdth, jacobians=want_jac)
            # a fix factor sees the pose plus its track's common fix error (d e / d bias = d e / d pose)
            pw = Xc[wpose, :2] + B[wuser] * has_b[:, None] if n_b else Xc[wpose, :2]
            ew = F.wifi_error(pw, nbr_xy(Xc), ww, jacobians=want_jac)
            if want_jac:
                ep, (jp, jc, jl) = ep
                ew, (jwp, jwn) = ew
            res[r_p:r_w] = (ep * sqrt_pdr).ravel()
            # whitening by the (n, 2, 2) square roots, as two products and a sum (numpy's einsum
            # costs ~50 us a call at this size)
            ewh = wL[:, :, 0] * ew[:, None, 0] + wL[:, :, 1] * ew[:, None, 1]
            if want_jac:
                jwp = wL[:, :, 0, None] * jwp[:, None, 0, :] + wL[:, :, 1, None] * jwp[:, None, 1, :]
                jwn = (wL[:, None, :, 0, None] * jwn[:, :, None, 0, :]
                       + wL[:, None, :, 1, None] * jwn[:, :, None, 1, :])
                ewh, (jwp, jwn), _ = F.robustify(ewh, [jwp, jwn.transpose(0, 2, 1, 3)], kernel, c_rob)
                jwn = jwn.transpose(0, 2, 1, 3)
            else:
                ewh, _, _ = F.robustify(ewh, None, kernel, c_rob)
            res[r_w:r_g] = ewh.ravel()
            eg = Xc[gpose] - gx
            eg[:, 2] = F.wrap(eg[:, 2])
            res[r_g:r_u] = (eg * sqrt_g).ravel()
            res[r_u:r_k] = (L[var_users] - p.step_prior_m) * sqrt_step
            if n_k:
                dk, gk = walkable.eval(Xc[wk_pose, :2], wk_z)
                res[r_k:r_b] = dk * inv_wk
            res[r_b:] = (B[bias_users] * inv_b).ravel()
            if not want_jac:
                return res
            s = sqrt_pdr[:, :, None]
            vals = [(jp * s).ravel(), (jc * s).ravel(), (jl[:, :, None] * s).ravel(), jwp.ravel()]
            for j in range(n_nbr):
                vals.append(jwn[:, j].ravel())
            vals.append(np.broadcast_to(np.diag(sqrt_g), (n_g, 3, 3)).ravel())
            vals.append(np.full(n_u, sqrt_step))
            if n_k:
                vals.append((gk * inv_wk).ravel())
            vals.append(jwp.ravel())
            vals.append(np.broadcast_to(inv_b * np.eye(2), (n_b, 2, 2)).ravel())
            v = np.concatenate(vals)[keep]
            return res, v

        def fun(z):
            return evaluate(z, False)

        def jac(z):
            _, v = evaluate(z, True)
            data = np.bincount(slot, weights=v, minlength=len(lin))
            return sp.csr_matrix((data, csr_indices, csr_indptr), shape=(n_r, n_x))

        z0 = np.concatenate([X[var].ravel(), self.step_len[var_users], self.fix_bias[bias_users].ravel()])
        return fun, jac, z0, unpack, n_p + n_w + n_g + n_u + n_k + n_b

    def marginal_cov(self, pose: int) -> np.ndarray | None:
        """(3, 3) covariance of a pose from the last solve's information matrix JᵀJ (None if that
        pose was not a variable then).

        The information matrix is factorised once per solve, at the first call (the end of input
        asks every user's newest pose: one factorisation of the whole graph per user made the
        finish quadratic in the number of users); each call is then one solve with three right-hand
        sides. :meth:`marginal_cov_plain` is the same without the cache (the oracle of the tests)."""
        last = self._last_J
        if last is None:
            return None
        J, z, var, col = last
        c = int(col[pose]) if pose < len(col) else -1
        if c < 0:
            return None
        if not isinstance(J, _Factored):     # the first call since the solve factorises JᵀJ, once
            J = _Factored.of(J(z) if callable(J) else J)
            self._last_J = (J, z, var, col)
        return J.cov(c)

    def marginal_cov_plain(self, pose: int) -> np.ndarray | None:
        """:meth:`marginal_cov` without the cached factorisation: JᵀJ built and factorised anew."""
        last = self._last_J
        if last is None:
            return None
        J, z, var, col = last
        c = int(col[pose]) if pose < len(col) else -1
        if c < 0:
            return None
        if isinstance(J, _Factored):
            J = J.jac
        elif callable(J):
            J = J(z)
        return _Factored.of(J).cov(c)

    # -- outputs ---------------------------------------------------------------------------------
    def trajectory(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns (T,), poses (T, 3)) of a user, in stamp order."""
        tr = self.users.get(name)
        if tr is None or not tr.poses:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        idx = np.asarray(tr.poses, np.int64)
        return self.poses.stamp[idx].copy(), self.poses.x[idx].copy()

    def wifi_radio_map(self) -> RadioMap:
        """The evolving map at the current estimates (save with ``save_radiomap``)."""
        return self.map.radio_map(self.poses.view("x")[:, :2], self.user_names)

    def counts(self) -> dict[str, int]:
        return {"poses": self.poses.n, "frozen_poses": self.n_frozen, "dropped_poses": self.n_dropped,
                "pdr_edges": self.pdr.n,
                "wifi_edges": self.wifi.n, "map_rows": self.map.n, "map_user_rows": self.map.n_user_rows,
                "users": len(self.users), "tracks": len(self.tracks)}
