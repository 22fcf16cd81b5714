"""Walkers on the building graph and the IMU they carry (pure numpy/scipy).

A walker goes along shortest paths between random destinations, stops there, sometimes turns
round mid-corridor (U-turn), and walks with its own step length and cadence. Its motion is a
plan of knots (time, position, heading, walking or not) sampled on the IMU's time grid and
smoothed (corners take about a second, starts and stops about half a second).

The device (a phone held in front, x forward, z up — REP 103) follows the body plus a gait
displacement: a vertical bob at the step frequency, a forward surge at the step frequency and a
lateral sway at the stride frequency (half the cadence), with matching roll/pitch/yaw wobble —
the periodic vertical acceleration the FFT stepometer looks for (Kim et al., "A step, stride and
heading determination for the pedestrian navigation system", J. Global Positioning Systems, 2004;
Zijlstra & Hof, "Displacement of the pelvis during human walking", Gait & Posture 1997, for the
centimetre amplitudes).

IMU synthesis is exact for the discrete motion: the accelerometer is the second difference of
the device position on the sample grid plus gravity, rotated into the device frame
(``f = Rᵀ (a + g e_z)``); the gyroscope is ``log(R_kᵀ R_(k+1)) / dt`` in the device frame, so a
strapdown integration of the noise-free IMU recovers the path to rounding error. Noise: white
noise per sample, constant biases per device, a gyro bias random walk. The magnetometer samples
an Earth field (ENU, north along +y, dip below the horizon) plus Gaussian-shaped local
disturbances of the building, at its own rate and time grid.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation, Slerp

from indoor_loc.errors import ConfigError
from indoor_loc.sim.building import Building

GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class WalkerParams:
    """One person and their phone."""
    name: str = "alice"
    step_length_m: float = 0.7        # true step length, m
    cadence_hz: float = 1.8           # steps per second
    stop_s: tuple[float, float] = (2.0, 6.0)     # stop duration at a destination, uniform range, s
    start_still_s: tuple[float, float] = (1.0, 2.0)   # standing still before the first step, uniform range, s
    uturn_prob: float = 0.2           # probability per leg of turning round part-way along a link
    stair_speed_factor: float = 0.55  # along-link speed on stairs relative to level walking
    lift_speed_m_s: float = 1.0       # vertical speed of a lift car, m/s
    lift_wait_s: tuple[float, float] = (3.0, 10.0)   # wait for the car (doors included), uniform range, s
    lift_exit_s: tuple[float, float] = (1.0, 2.5)    # doors opening at the arrival, uniform range, s
    hand_height_m: float = 1.1        # device height above the floor, m
    bob_m: float = 0.03               # vertical gait displacement amplitude, m
    surge_m: float = 0.015            # forward gait displacement amplitude, m
    sway_m: float = 0.02              # lateral gait displacement amplitude (stride frequency), m
    wobble_deg: float = 2.0           # roll/pitch/yaw gait wobble amplitude, deg
    device_pitch_deg: float = 0.0     # constant pitch of the device in the hand, deg
    turn_s: float = 1.2               # duration of a turn in place (U-turn), s
    smooth_s: float = 0.25            # std of the Gaussian that rounds corners and speed changes, s

    def validate(self) -> None:
        if not (0.2 <= self.step_length_m <= 1.5):
            raise ConfigError(f"WalkerParams.step_length_m: expected 0.2..1.5 m, got {self.step_length_m}")
        if not (0.5 <= self.cadence_hz <= 3.5):
            raise ConfigError(f"WalkerParams.cadence_hz: expected 0.5..3.5 Hz, got {self.cadence_hz}")
        if not (0 <= self.uturn_prob <= 1):
            raise ConfigError(f"WalkerParams.uturn_prob: expected 0..1, got {self.uturn_prob}")


@dataclass(frozen=True)
class ImuParams:
    """Phone-grade IMU (defaults of a consumer MEMS part)."""
    rate_hz: float = 100.0            # accelerometer + gyroscope rate, Hz
    mag_rate_hz: float = 50.0         # magnetometer rate (own time grid), Hz
    acc_noise: float = 0.04           # accelerometer white noise per sample, m/s²
    gyro_noise: float = 0.004         # gyroscope white noise per sample, rad/s
    mag_noise_t: float = 0.4e-6       # magnetometer white noise per sample, T
    acc_bias_std: float = 0.05        # accelerometer bias per axis (drawn once), m/s²
    gyro_bias_std: float = 0.005      # gyroscope bias per axis (drawn once), rad/s
    gyro_bias_walk: float = 1e-4      # gyroscope bias random walk, rad/s/√s
    mag_bias_std_t: float = 1.0e-6    # residual hard-iron bias per axis after calibration, T
    earth_field_t: float = 49e-6      # Earth field magnitude, T
    inclination_deg: float = 66.0     # dip below the horizon (Central Europe), deg

    def validate(self) -> None:
        if not (20.0 <= self.rate_hz <= 1000.0):
            raise ConfigError(f"ImuParams.rate_hz: expected 20..1000 Hz, got {self.rate_hz}")
        if not (1.0 <= self.mag_rate_hz <= 1000.0):
            raise ConfigError(f"ImuParams.mag_rate_hz: expected 1..1000 Hz, got {self.mag_rate_hz}")

    def earth_field_enu(self) -> np.ndarray:
        inc = np.radians(self.inclination_deg)
        return np.array([0.0, np.cos(inc), -np.sin(inc)]) * self.earth_field_t


@dataclass
class Plan:
    """Piecewise motion: knot times t_s (K,), positions xyz (K, 3), headings (K,) rad (unwrapped),
    per interval k→k+1 whether the walker walks (K-1,) (on stairs at the same cadence but
    ``stair_speed_factor`` slower along the link), and the graph nodes reached in order."""
    t_s: np.ndarray
    xyz: np.ndarray
    heading: np.ndarray
    walking: np.ndarray
    node_seq: list[int]


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def make_plan(building: Building, params: WalkerParams, duration_s: float, rng: np.random.Generator, *,
              start_node: int | None = None, floors: tuple[int, ...] | None = None) -> Plan:
    """Random destinations on the graph until ``duration_s`` (the last leg may run past it)."""
    params.validate()
    kinds = np.array(building.node_kind)
    cand = np.flatnonzero(np.isin(kinds, ("room", "junction", "corridor", "stairs")))
    if floors is not None:
        cand = cand[np.isin(building.node_floor[cand], floors)]
    node = int(rng.choice(cand)) if start_node is None else int(start_node)
    xyz0 = building.node_xyz[node] + np.array([0, 0, params.hand_height_m])
    t = [0.0]
    pos = [xyz0]
    head = [float(rng.uniform(-np.pi, np.pi))]
    walking: list[bool] = []
    seq = [node]
    v = params.step_length_m * params.cadence_hz
    hh = np.array([0, 0, params.hand_height_m])

    def add(dt, p, h, walk):
        t.append(t[-1] + dt)
        pos.append(np.asarray(p, float))
        head.append(h)
        walking.append(walk)

    def stop(dt):
        add(dt, pos[-1], head[-1], False)

    def face(direction):
        # the heading jumps to the new direction within 1 ms (rounded later by the smoothing)
        h = head[-1] + _wrap(direction - head[-1])
        add(1e-3, pos[-1], h, False)

    stop(float(rng.uniform(*params.start_still_s)))
    while t[-1] < duration_s:
        dest = int(rng.choice(cand))
        if dest == node:
            continue
        path = building.shortest_path(node, dest)
        for a, b in zip(path[:-1], path[1:]):
            pa, pb = building.node_xyz[a] + hh, building.node_xyz[b] + hh
            d = pb - pa
            plan_len = float(np.linalg.norm(d[:2]))
            stairs = abs(d[2]) > 0.5
            if stairs and plan_len < 0.5:            # a lift: wait, ride standing, get out
                stop(float(rng.uniform(*params.lift_wait_s)))
                add(abs(float(d[2])) / params.lift_speed_m_s, pb, head[-1], False)
                stop(float(rng.uniform(*params.lift_exit_s)))
                seq.append(b)
                continue
            direction = float(np.arctan2(d[1], d[0])) if plan_len > 1e-6 else head[-1]
            face(direction)
            length = float(np.linalg.norm(d))
            speed = v * (params.stair_speed_factor if stairs else 1.0)
            if not stairs and plan_len > 3.0 and rng.random() < params.uturn_prob:
                frac = float(rng.uniform(0.3, 0.7))
                add(frac * length / speed, pa + frac * d, head[-1], True)
                stop(float(rng.uniform(0.3, 1.0)))
                sign = 1.0 if rng.random() < 0.5 else -1.0
                add(params.turn_s, pos[-1], head[-1] + sign * np.pi, False)
                add(frac * length / speed, pa, head[-1], True)
                stop(float(rng.uniform(0.3, 1.0)))
                face(direction)
            add(length / speed, pb, head[-1], True)
            seq.append(b)
            if t[-1] >= duration_s:
                break
        node = seq[-1]
        stop(float(rng.uniform(*params.stop_s)))
    return Plan(np.array(t), np.array(pos), np.array(head), np.array(walking, bool), seq)


@dataclass
class Motion:
    """The sampled motion of a walker's device on the IMU grid (``t_ns`` (N,) int, relative to the run start)."""
    t_ns: np.ndarray
    xyz: np.ndarray            # (N, 3) device position, m (map frame)
    body_xyz: np.ndarray       # (N, 3) body position on the route (no gait displacement), m
    heading: np.ndarray        # (N,) walking heading, rad (wrapped)
    rot: Rotation              # device -> map
    steps: np.ndarray          # (N,) cumulative true step count
    walk: np.ndarray           # (N,) gait factor 0..1 after smoothing
    floor: np.ndarray          # (N,) int


def sample_motion(plan: Plan, params: WalkerParams, rate_hz: float, duration_s: float,
                  floor_z: np.ndarray) -> Motion:
    """Sample and smooth a plan on a uniform grid of ``rate_hz`` over [0, duration_s]."""
    n = int(np.floor(duration_s * rate_hz)) + 1
    dt = 1.0 / rate_hz
    t = np.arange(n) * dt
    t_ns = np.round(t * 1e9).astype(np.int64)
    body = np.column_stack([np.interp(t, plan.t_s, plan.xyz[:, k]) for k in range(3)])
    seg = np.clip(np.searchsorted(plan.t_s, t, side="right") - 1, 0, len(plan.walking) - 1)
    # heading: linear between knots (turns in place), jumps at corners within 1 ms
    heading_raw = np.interp(t, plan.t_s, plan.heading)
    gait_raw = np.where(plan.walking[seg], 1.0, 0.0)
    sig = params.smooth_s * rate_hz
    body = gaussian_filter1d(body, sig, axis=0, mode="nearest")
    heading_u = gaussian_filter1d(heading_raw, sig, mode="nearest")
    walk = gaussian_filter1d(gait_raw, sig, mode="nearest")
    phase = 2 * np.pi * params.cadence_hz * np.cumsum(walk) * dt
    steps = phase / (2 * np.pi)
    # gait displacement in the body frame (forward, left, up) rotated by the heading
    fwd = params.surge_m * walk * np.sin(phase)
    lat = params.sway_m * walk * np.sin(phase / 2)
    up = params.bob_m * walk * np.cos(phase)
    c, s = np.cos(heading_u), np.sin(heading_u)
    xyz = body + np.column_stack([c * fwd - s * lat, s * fwd + c * lat, up])
    wob = np.radians(params.wobble_deg)
    roll = wob * walk * np.sin(phase / 2)
    pitch = np.radians(params.device_pitch_deg) + 0.7 * wob * walk * np.cos(phase)
    yaw = heading_u + 0.5 * wob * walk * np.sin(phase / 2 + 0.5)
    rot = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]))
    floor = np.argmin(np.abs(body[:, 2:3] - params.hand_height_m - np.asarray(floor_z)[None]), axis=1)
    return Motion(t_ns, xyz, body, (heading_u + np.pi) % (2 * np.pi) - np.pi, rot, steps, walk, floor)


def ideal_imu(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free specific force (N, 3) m/s² and angular rate (N, 3) rad/s in the device frame.

    Acceleration = second difference of the position (ends copy their neighbour); rate k =
    rotation from sample k to k+1 (the last copies its neighbour)."""
    dt = float(motion.t_ns[1] - motion.t_ns[0]) * 1e-9
    p = motion.xyz
    a = np.empty_like(p)
    a[1:-1] = (p[2:] - 2 * p[1:-1] + p[:-2]) / dt**2
    a[0], a[-1] = a[1], a[-2]
    f_world = a + np.array([0.0, 0.0, GRAVITY_M_S2])
    acc = motion.rot.inv().apply(f_world)
    rel = motion.rot[:-1].inv() * motion.rot[1:]
    gyro = np.empty_like(p)
    gyro[:-1] = rel.as_rotvec() / dt
    gyro[-1] = gyro[-2]
    return acc, gyro


def magnetic_field_enu(building: Building, xy: np.ndarray, floor: np.ndarray, earth_enu: np.ndarray) -> np.ndarray:
    """Field (N, 3) T in the map frame at plan positions xy (N, 2) on floors (N,): Earth field plus
    the building's disturbances, each ``B_d exp(-r²/(2 radius²))``."""
    out = np.repeat(earth_enu[None], len(xy), axis=0)
    for x, y, f, bx, by, bz, r in building.mag_disturbances:
        w = np.exp(-((xy[:, 0] - x) ** 2 + (xy[:, 1] - y) ** 2) / (2 * r * r)) * (floor == int(f))
        out += w[:, None] * np.array([bx, by, bz])[None]
    return out


@dataclass
class ImuData:
    t_ns: np.ndarray          # (N,) relative to the run start
    acc: np.ndarray           # (N, 3) m/s²
    gyro: np.ndarray          # (N, 3) rad/s
    mag_t_ns: np.ndarray      # (K,)
    mag_t: np.ndarray         # (K, 3) T
    gyro_bias: np.ndarray     # (N, 3) rad/s, the true bias
    acc_bias: np.ndarray      # (3,) m/s²


def synthesize_imu(motion: Motion, building: Building, params: ImuParams, rng: np.random.Generator) -> ImuData:
    """Noisy IMU + magnetometer of a walker (see module doc)."""
    params.validate()
    acc, gyro = ideal_imu(motion)
    n = len(acc)
    dt = float(motion.t_ns[1] - motion.t_ns[0]) * 1e-9
    acc_bias = rng.normal(0.0, params.acc_bias_std, 3)
    g_bias = rng.normal(0.0, params.gyro_bias_std, 3) + np.cumsum(
        rng.normal(0.0, params.gyro_bias_walk * np.sqrt(dt), (n, 3)), axis=0)
    acc = acc + acc_bias + rng.normal(0.0, params.acc_noise, (n, 3))
    gyro = gyro + g_bias + rng.normal(0.0, params.gyro_noise, (n, 3))
    # magnetometer on its own grid, offset from the IMU's
    t_end = motion.t_ns[-1] * 1e-9
    tm = np.arange(float(rng.uniform(0.0, 1.0 / params.mag_rate_hz)), t_end, 1.0 / params.mag_rate_hz)
    t_imu = motion.t_ns * 1e-9
    rot_m = Slerp(t_imu, motion.rot)(tm)
    xy = np.column_stack([np.interp(tm, t_imu, motion.xyz[:, k]) for k in range(2)])
    floor = np.round(np.interp(tm, t_imu, motion.floor)).astype(np.int64)
    field = magnetic_field_enu(building, xy, floor, params.earth_field_enu())
    mag = rot_m.inv().apply(field) + rng.normal(0.0, params.mag_bias_std_t, 3) \
        + rng.normal(0.0, params.mag_noise_t, (len(tm), 3))
    return ImuData(motion.t_ns, acc, gyro, np.round(tm * 1e9).astype(np.int64), mag, g_bias, acc_bias)
