"""A simulated run: several walkers in a building, their IMU and WiFi scans, a survey radio map.

:func:`simulate` is pure (numpy + one ``np.random.Generator``): the same seed gives the same run.
:mod:`indoor_loc.sim.write` turns a :class:`SimRun` into bags and files.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from indoor_loc.errors import ConfigError
from indoor_loc.sim.baro import BaroData, BaroSimParams, simulate_pressure
from indoor_loc.sim.building import Building
from indoor_loc.sim.rf import RfParams, RssField, ScannerParams, read_rss
from indoor_loc.sim.walker import ImuData, ImuParams, Motion, Plan, WalkerParams, make_plan, sample_motion, \
    synthesize_imu
from indoor_loc.wifi.types import WifiScan

if TYPE_CHECKING:
    from indoor_loc.sim.robot import RobotParams

#: Bag time of the run start (2026-01-01T00:00:00Z), int ns: fixed so runs are reproducible.
T0_NS = 1_767_225_600_000_000_000
NAMES = ("alice", "bob", "carol", "dave", "erin", "frank", "grace", "heidi")


def _robot_params():
    from indoor_loc.sim.robot import RobotParams
    return RobotParams()


@dataclass(frozen=True)
class SimConfig:
    walkers: int = 3                  # number of walkers (names from NAMES)
    duration_s: float = 90.0          # length of the run, s
    seed: int = 7                     # seeds every random draw of the run
    imu: ImuParams = field(default_factory=ImuParams)
    rf: RfParams = field(default_factory=RfParams)
    scanner: ScannerParams = field(default_factory=ScannerParams)
    step_length_m: tuple[float, float] = (0.72, 0.06)   # mean, std of the walkers' step lengths, m
    cadence_hz: tuple[float, float] = (1.8, 0.12)       # mean, std of the walkers' cadences, Hz
    survey_spacing_m: float = 2.0     # survey points every this many metres along the links, m
    survey_scans: int = 2             # scans per survey point
    start_floor: int | None = 0       # walkers start on this floor (None: anywhere)
    robots: int = 0                   # differential-drive robots (names robot1, ...; indoor_loc/sim/robot.py)
    robot: "RobotParams" = field(default_factory=lambda: _robot_params())
    change_floors: bool = False       # destinations on every floor (True) or on the start floor only
    baro: BaroSimParams | None = None  # a barometer in every phone (None: none)

    def validate(self) -> None:
        if not 0 <= self.robots <= 8:
            raise ConfigError(f"SimConfig.robots: expected 0..8, got {self.robots}")
        if self.robots:
            self.robot.validate()
        if not 1 <= self.walkers <= len(NAMES):
            raise ConfigError(f"SimConfig.walkers: expected 1..{len(NAMES)}, got {self.walkers}")
        if not self.duration_s >= 10.0:
            raise ConfigError(f"SimConfig.duration_s: expected >= 10 s, got {self.duration_s}")
        if not self.survey_spacing_m > 0 or self.survey_scans < 1:
            raise ConfigError("SimConfig: survey_spacing_m must be > 0 and survey_scans >= 1")
        self.imu.validate()
        self.rf.validate()
        self.scanner.validate()


@dataclass
class SimWalker:
    params: WalkerParams
    plan: Plan
    motion: Motion
    imu: ImuData
    scans: list[WifiScan]           # stamps relative to the run start
    scan_xy: np.ndarray             # (S, 2) true device position at each scan stamp, m
    baro: BaroData | None = None    # barometer samples (SimConfig.baro), stamps relative to the run start

    @property
    def name(self) -> str:
        return self.params.name


@dataclass
class SimRun:
    config: SimConfig
    building: Building
    field: RssField
    walkers: list[SimWalker]
    survey_xy: np.ndarray           # (M, 2)
    survey_floor: np.ndarray        # (M,)
    survey_scans: list[WifiScan]
    robots: list = field(default_factory=list)     # SimRobot (indoor_loc/sim/robot.py)


def survey_points(building: Building, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) every ``spacing_m`` along every level link (nodes included, deduplicated) and
    their floors (M,)."""
    pts, floors = [], []
    for (i, j) in building.link_nodes:
        a, b = building.node_xyz[i], building.node_xyz[j]
        if abs(a[2] - b[2]) > 0.5:
            continue                 # no survey on the stairs
        n = max(1, int(np.ceil(np.linalg.norm(b[:2] - a[:2]) / spacing_m)))
        for k in range(n + 1):
            pts.append(a + (b - a) * k / n)
            floors.append(building.node_floor[i])
    pts_a = np.round(np.array(pts), 3)
    _, keep = np.unique(np.column_stack([pts_a, floors]), axis=0, return_index=True)
    keep = np.sort(keep)
    return pts_a[keep], np.array(floors)[keep]


def _scan(fld: RssField, stamp_ns: int, xyz_at, floor_at, t_reading_s: np.ndarray,
          rng: np.random.Generator, sc: ScannerParams, offset_db: float, source: str, frame_id: str) -> WifiScan | None:
    """One scan; readings of BSSID b taken at t_reading_s[b] (s) at position xyz_at(t)."""
    mean = np.full(len(fld.bssids), -np.inf)
    for tr in np.unique(t_reading_s):
        cols = np.flatnonzero(t_reading_s == tr)
        m = fld.mean_rss(xyz_at(tr)[None], np.array([floor_at(tr)]), float(tr))[0]
        mean[cols] = m[cols]
    val = read_rss(mean, rng, fading_std_db=fld.p.fading_std_db, sensitivity_dbm=sc.sensitivity_dbm,
                   slope_db=sc.detection_slope_db, offset_db=offset_db)
    seen = np.flatnonzero(np.isfinite(val))
    if len(seen) == 0:
        return None
    t_scan = stamp_ns * 1e-9
    age = np.round((t_scan - t_reading_s[seen]) * 1e3)
    return WifiScan(stamp_ns=int(stamp_ns), bssid=tuple(fld.bssids[k] for k in seen), rssi_dbm=val[seen],
                    freq_mhz=np.array([fld.freq_mhz[k] for k in seen]), ssid=tuple(fld.ssids[k] for k in seen),
                    age_ms=age, frame_id=frame_id, source=source)


def simulate(building: Building, config: SimConfig | None = None) -> SimRun:
    """Simulate ``config.walkers`` walkers for ``config.duration_s`` in ``building`` (see module doc)."""
    cfg = config or SimConfig()
    cfg.validate()
    root = np.random.default_rng(cfg.seed)
    rngs = root.spawn(cfg.walkers + 2)
    fld = RssField(building, cfg.rf, rng=rngs[0])
    sc = cfg.scanner
    # survey: stationary scans at every survey point, APs as at the start
    pts, pfl = survey_points(building, cfg.survey_spacing_m)
    srng = rngs[1]
    mean = fld.mean_rss(pts, pfl, 0.0)
    survey_scans, survey_xy, survey_floor = [], [], []
    for _ in range(cfg.survey_scans):
        val = read_rss(mean, srng, fading_std_db=cfg.rf.fading_std_db, sensitivity_dbm=sc.sensitivity_dbm,
                       slope_db=sc.detection_slope_db)
        for i in range(len(pts)):
            seen = np.flatnonzero(np.isfinite(val[i]))
            if len(seen) == 0:
                continue
            survey_scans.append(WifiScan(0, tuple(fld.bssids[j] for j in seen), val[i, seen],
                                         np.array([fld.freq_mhz[j] for j in seen]),
                                         tuple(fld.ssids[j] for j in seen), source="survey"))
            survey_xy.append(pts[i, :2])
            survey_floor.append(pfl[i])
    # channel sweep order: 2.4 GHz channels first, then 5 GHz, each at a fixed fraction of the sweep
    freqs = np.array(fld.freq_mhz)
    order = np.unique(freqs)
    sweep_frac = {f: (k + 0.5) / len(order) for k, f in enumerate(order)}
    frac = np.array([sweep_frac[f] for f in freqs])
    walkers = []
    for w in range(cfg.walkers):
        rng = rngs[2 + w]
        wp = WalkerParams(name=NAMES[w],
                          step_length_m=float(np.clip(rng.normal(*cfg.step_length_m), 0.5, 0.95)),
                          cadence_hz=float(np.clip(rng.normal(*cfg.cadence_hz), 1.45, 2.15)),
                          device_pitch_deg=float(rng.normal(0.0, 5.0)))
        floors = None if cfg.start_floor is None else (cfg.start_floor,)
        if cfg.change_floors:
            kinds = np.array(building.node_kind)
            cand = np.flatnonzero(np.isin(kinds, ("room", "junction", "corridor")))
            if floors is not None:
                cand = cand[np.isin(building.node_floor[cand], floors)]
            plan = make_plan(building, wp, cfg.duration_s, rng, start_node=int(rng.choice(cand)))
        else:
            plan = make_plan(building, wp, cfg.duration_s, rng, floors=floors)
        motion = sample_motion(plan, wp, cfg.imu.rate_hz, cfg.duration_s, building.floor_z)
        imu = synthesize_imu(motion, building, cfg.imu, rng)
        scans, scan_xy = scans_along(fld, motion, rng, sc, cfg.duration_s, frac, wp.name)
        baro = None if cfg.baro is None else simulate_pressure(motion.t_ns * 1e-9, motion.xyz[:, 2], cfg.duration_s,
                                                               cfg.baro, rng)
        walkers.append(SimWalker(wp, plan, motion, imu, scans, scan_xy, baro))
    robots = []
    if cfg.robots:          # their own random streams: adding robots changes nothing of the walkers
        from indoor_loc.sim.robot import ROBOT_NAMES, simulate_robot, with_name
        rrngs = np.random.default_rng([cfg.seed, 24]).spawn(cfg.robots)
        for r in range(cfg.robots):
            rp = with_name(cfg.robot, ROBOT_NAMES[r])
            robots.append(simulate_robot(
                building, rp, cfg.duration_s, rrngs[r],
                lambda m, g, name=rp.name: scans_along(fld, m, g, sc, cfg.duration_s, frac, name),
                floor=cfg.start_floor or 0))
    return SimRun(cfg, building, fld, walkers, np.array(survey_xy).reshape(-1, 2), np.array(survey_floor),
                  survey_scans, robots)


def scans_along(fld: RssField, motion: Motion, rng: np.random.Generator, sc: ScannerParams, duration_s: float,
                frac: np.ndarray, name: str) -> tuple[list[WifiScan], np.ndarray]:
    """The scans of a device following ``motion`` (its own RSS offset, a scan every ``sc.period_s``
    with jitter, channel sweep fractions ``frac``) and the true positions (S, 2) at their stamps."""
    t_s = motion.t_ns * 1e-9

    def xyz_at(t, m=motion, ts=t_s):
        return np.array([np.interp(t, ts, m.xyz[:, k]) for k in range(3)])

    def floor_at(t, m=motion, ts=t_s):
        return int(m.floor[min(int(np.searchsorted(ts, t)), len(ts) - 1)])

    offset = float(rng.normal(0.0, sc.device_offset_std_db))
    scans, scan_xy = [], []
    t_next = float(rng.uniform(sc.sweep_s, sc.sweep_s + sc.period_s))
    while t_next <= duration_s:
        stamp_ns = int(round(t_next * 1e9))
        t_read = t_next - sc.sweep_s * (1.0 - frac)
        s = _scan(fld, stamp_ns, xyz_at, floor_at, t_read, rng, sc, offset, "sim", f"{name}/wifi_link")
        if s is not None:
            scans.append(s)
            scan_xy.append(xyz_at(t_next)[:2])
        t_next += sc.period_s + float(rng.uniform(-sc.period_jitter_s, sc.period_jitter_s))
    return scans, np.array(scan_xy).reshape(-1, 2)
