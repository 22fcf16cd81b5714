"""Differential-drive robots in the simulated building: their true motion, wheel odometry with
realistic errors, a gyro, and a WiFi card (pure numpy; the same seed gives the same robot).

A robot drives along the graph's corridors like a walker (random destinations, shortest paths,
stops; :func:`indoor_loc.sim.walker.make_plan` with robot speeds, no mid-corridor U-turns, corners
rounded over ``smooth_s``) on one floor. Its wheel odometry integrates what the encoders measure of
the true motion ``(ds, dθ)`` per sample (Borenstein & Feng, "Measurement and correction of
systematic odometry errors in mobile robots", IEEE T-RA 1996, for the error sources and sizes):

- each wheel's radius is off by a factor drawn once (``wheel_scale_std``): a distance scale error
  and, through their difference, a heading drift proportional to the distance driven;
- the wheel base is off by a factor drawn once (``wheel_base_err_std``): every turn is over- or
  under-estimated by that fraction;
- slip: each wheel's travel is scaled by ``1 + e`` with ``e`` a first-order Gauss–Markov process
  (``slip_std``, correlation time ``slip_tau_s``) — floor joints, carpet, accelerations;
- slow drift: a heading-rate bias doing a random walk (``drift_walk``, rad/s/√s);
- lateral motion (the smoothed path is not exactly non-holonomic) is not seen by the wheels.

The odometry pose starts at (0, 0, 0) in ``<robot>/odom`` and is published with a pose covariance
grown by the same (random part of the) model, as an odometry EKF would (``odom_covariance: growing``),
or as zeros (``none``, what many drivers publish). The gyro (``imu``, z rate + bias + noise, gravity
on the accelerometer) comes at the odometry rate. A kidnapping (``kidnap_at_s``) carries the robot,
odometry blind, to a random node at least ``kidnap_min_m`` away, where it drives on.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from indoor_loc.errors import ConfigError
from indoor_loc.sim.building import Building
from indoor_loc.sim.walker import Motion, Plan, WalkerParams, make_plan, sample_motion

ROBOT_NAMES = tuple(f"robot{i}" for i in range(1, 9))


@dataclass(frozen=True)
class RobotParams:
    """One differential-drive robot, its wheel odometry, gyro and WiFi card (units in the names)."""
    name: str = "robot1"
    speed_mps: float = 0.8            # cruise speed, m/s
    wheel_base_m: float = 0.40        # distance between the wheels, m
    odom_rate_hz: float = 20.0        # odometry (and gyro) rate, Hz
    wheel_scale_std: float = 0.001    # each wheel's radius error (drawn once), fraction
    wheel_base_err_std: float = 0.01  # wheel-base error (drawn once), fraction
    slip_std: float = 0.005           # wheel slip (Gauss-Markov), fraction of the wheel's travel
    slip_tau_s: float = 0.5           # its correlation time, s
    drift_walk: float = 2e-5          # heading-rate bias random walk, rad/s/√s
    gyro_noise: float = 0.002         # gyro white noise per sample, rad/s
    gyro_bias_std: float = 0.002      # gyro bias (drawn once), rad/s
    card_height_m: float = 0.4        # WiFi card above the floor, m
    stop_s: tuple[float, float] = (2.0, 6.0)   # stop at a destination, uniform range, s
    smooth_s: float = 0.4             # std of the Gaussian rounding corners and speed changes, s
    odom_covariance: str = "growing"  # growing (an odometry EKF's) or none (zeros)
    kidnap_at_s: float | None = None  # teleport the robot at this time, s (None: never)
    kidnap_min_m: float = 15.0        # ... to a node at least this far, m

    def validate(self) -> None:
        if not 0.1 <= self.speed_mps <= 1.5:
            raise ConfigError(f"RobotParams.speed_mps: expected 0.1..1.5 m/s, got {self.speed_mps}")
        if not 5.0 <= self.odom_rate_hz <= 500.0:
            raise ConfigError(f"RobotParams.odom_rate_hz: expected 5..500 Hz, got {self.odom_rate_hz}")
        if self.odom_covariance not in ("growing", "none"):
            raise ConfigError(f"RobotParams.odom_covariance: expected growing or none, got {self.odom_covariance!r}")
        if self.wheel_base_m <= 0 or self.slip_tau_s <= 0:
            raise ConfigError("RobotParams: wheel_base_m and slip_tau_s must be > 0")


@dataclass
class RobotOdometry:
    """The wheel odometry as published: stamps (N,) relative ns, pose (N, 3) x, y, yaw in the odom
    frame, cov (N, 3, 3), twist (N, 2) forward speed m/s and yaw rate rad/s; gyro z (N,) rad/s."""
    t_ns: np.ndarray
    pose: np.ndarray
    cov: np.ndarray
    twist: np.ndarray
    gyro_z: np.ndarray


@dataclass
class SimRobot:
    params: RobotParams
    plan: Plan                      # the first leg's plan (before any kidnapping)
    motion: Motion                  # the WiFi card's true motion (xyz at card height, heading)
    odom: RobotOdometry
    scans: list                     # WifiScan, stamps relative to the run start
    scan_xy: np.ndarray             # (S, 2) true card position at each scan stamp
    kidnap_ns: int | None = None    # relative stamp of the kidnapping

    @property
    def name(self) -> str:
        return self.params.name


def robot_walker_params(p: RobotParams) -> WalkerParams:
    """The plan/motion parameters of a robot: a walker of one 'step' per second, no gait."""
    return WalkerParams(name=p.name, step_length_m=p.speed_mps, cadence_hz=1.0, stop_s=p.stop_s,
                        start_still_s=(1.0, 2.0), uturn_prob=0.0, hand_height_m=p.card_height_m, bob_m=0.0,
                        surge_m=0.0, sway_m=0.0, wobble_deg=0.0, turn_s=2.0, smooth_s=p.smooth_s)


def _concat(a: Motion, b: Motion, shift_ns: int) -> Motion:
    keep = a.t_ns < shift_ns
    return Motion(np.concatenate([a.t_ns[keep], b.t_ns + shift_ns]), np.vstack([a.xyz[keep], b.xyz]),
                  np.vstack([a.body_xyz[keep], b.body_xyz]), np.concatenate([a.heading[keep], b.heading]),
                  Rotation.concatenate([a.rot[np.flatnonzero(keep)], b.rot]),
                  np.concatenate([a.steps[keep], b.steps]), np.concatenate([a.walk[keep], b.walk]),
                  np.concatenate([a.floor[keep], b.floor]))


def robot_motion(building: Building, p: RobotParams, duration_s: float, rng: np.random.Generator, *,
                 floor: int = 0) -> tuple[Plan, Motion, int | None]:
    """The card's true motion on the odometry grid (with a kidnapping when asked) and the plan."""
    wp = robot_walker_params(p)
    plan = make_plan(building, wp, duration_s, rng, floors=(floor,))
    motion = sample_motion(plan, wp, p.odom_rate_hz, duration_s, building.floor_z)
    if p.kidnap_at_s is None or not 0 < p.kidnap_at_s < duration_s:
        return plan, motion, None
    k_ns = int(round(p.kidnap_at_s * p.odom_rate_hz)) * int(round(1e9 / p.odom_rate_hz))
    here = motion.body_xyz[int(np.searchsorted(motion.t_ns, k_ns)) - 1, :2]
    kinds = np.array(building.node_kind)
    cand = np.flatnonzero(np.isin(kinds, ("room", "junction", "corridor")) & (building.node_floor == floor))
    far = cand[np.hypot(*(building.node_xyz[cand, :2] - here).T) >= p.kidnap_min_m]
    start = int(rng.choice(far if len(far) else cand))
    rest = duration_s - k_ns * 1e-9
    plan2 = make_plan(building, wp, rest, rng, start_node=start, floors=(floor,))
    motion2 = sample_motion(plan2, wp, p.odom_rate_hz, rest, building.floor_z)
    return plan, _concat(motion, motion2, k_ns), k_ns


def wheel_odometry(motion: Motion, p: RobotParams, rng: np.random.Generator, kidnap_ns: int | None = None) -> RobotOdometry:
    """Integrate the encoders' view of the true motion (see the module doc)."""
    n = len(motion.t_ns)
    dt = 1.0 / p.odom_rate_hz
    x, y = motion.body_xyz[:, 0], motion.body_xyz[:, 1]
    th = np.unwrap(motion.heading)
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    ds_true = c * np.diff(x) + s * np.diff(y)            # forward motion per sample (lateral unseen)
    dth_true = np.diff(th)
    if kidnap_ns is not None:                            # carried: the wheels do not turn
        jump = np.flatnonzero((motion.t_ns[:-1] < kidnap_ns) & (motion.t_ns[1:] >= kidnap_ns))
        ds_true[jump] = 0.0
        dth_true[jump] = 0.0
    b = p.wheel_base_m
    e_r, e_l = rng.normal(0.0, p.wheel_scale_std, 2)
    e_b = rng.normal(0.0, p.wheel_base_err_std)
    a = np.exp(-dt / p.slip_tau_s)
    white = rng.normal(0.0, p.slip_std * np.sqrt(1 - a * a), (n - 1, 2))
    slip = np.empty((n - 1, 2))
    prev = rng.normal(0.0, p.slip_std, 2)
    for k in range(n - 1):                               # Gauss-Markov slip per wheel
        prev = a * prev + white[k]
        slip[k] = prev
    drift = rng.normal(0.0, p.drift_walk * np.sqrt(dt), n - 1).cumsum()
    s_r = (ds_true + 0.5 * b * dth_true) * (1 + e_r) * (1 + slip[:, 0])
    s_l = (ds_true - 0.5 * b * dth_true) * (1 + e_l) * (1 + slip[:, 1])
    ds = 0.5 * (s_r + s_l)
    dth = (s_r - s_l) / (b * (1 + e_b)) + drift * dt
    pose = np.zeros((n, 3))
    mid = np.concatenate([[0.0], np.cumsum(dth)])
    heading_mid = mid[:-1] + 0.5 * dth
    pose[1:, 0] = np.cumsum(ds * np.cos(heading_mid))
    pose[1:, 1] = np.cumsum(ds * np.sin(heading_mid))
    pose[:, 2] = (mid + np.pi) % (2 * np.pi) - np.pi
    cov = np.zeros((n, 3, 3))
    if p.odom_covariance == "growing":
        # an odometry EKF's covariance: the slip's variance per sample (white-noise approximation of
        # the Gauss-Markov process over its correlation time) propagated along the path
        q_wheel = (p.slip_std ** 2) * 2 * p.slip_tau_s / dt
        var_r = q_wheel * (np.abs(s_r) ** 2) + 1e-10
        var_l = q_wheel * (np.abs(s_l) ** 2) + 1e-10
        P = np.zeros((3, 3))
        for k in range(n - 1):
            ch, sh = np.cos(heading_mid[k]), np.sin(heading_mid[k])
            J = np.array([[1.0, 0.0, -ds[k] * sh], [0.0, 1.0, ds[k] * ch], [0.0, 0.0, 1.0]])
            G = np.array([[0.5 * ch, 0.5 * ch], [0.5 * sh, 0.5 * sh], [1.0 / b, -1.0 / b]])
            P = J @ P @ J.T + G @ np.diag([var_r[k], var_l[k]]) @ G.T
            P[2, 2] += (p.drift_walk * dt) ** 2 * (k + 1)
            cov[k + 1] = P
    twist = np.column_stack([np.concatenate([[0.0], ds / dt]), np.concatenate([[0.0], dth / dt])])
    gyro_z = (np.concatenate([dth_true / dt, [0.0]]) + rng.normal(0.0, p.gyro_bias_std)
              + rng.normal(0.0, p.gyro_noise, n))
    return RobotOdometry(motion.t_ns.copy(), pose, cov, twist, gyro_z)


def simulate_robot(building: Building, p: RobotParams, duration_s: float, rng: np.random.Generator, scan_fn, *,
                   floor: int = 0) -> SimRobot:
    """One robot: motion, odometry and the scans ``scan_fn(motion, rng) -> (scans, scan_xy)`` of its card."""
    p.validate()
    plan, motion, k_ns = robot_motion(building, p, duration_s, rng, floor=floor)
    odom = wheel_odometry(motion, p, rng, k_ns)
    scans, scan_xy = scan_fn(motion, rng)
    return SimRobot(p, plan, motion, odom, scans, scan_xy, k_ns)


def pedestrian_twin_plan(robot: SimRobot, walker: WalkerParams) -> Plan:
    """The robot's first-leg plan walked by a pedestrian at their own speed (time scaled, the
    device at hand height): the reference 'PDR on the same path'."""
    pl = robot.plan
    f = robot.params.speed_mps / (walker.step_length_m * walker.cadence_hz)
    xyz = pl.xyz.copy()
    xyz[:, 2] += walker.hand_height_m - robot.params.card_height_m
    return Plan(pl.t_s * f, xyz, pl.heading.copy(), pl.walking.copy(), list(pl.node_seq))


def with_name(p: RobotParams, name: str) -> RobotParams:
    return replace(p, name=name)
