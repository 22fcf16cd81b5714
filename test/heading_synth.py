"""Synthetic IMU + magnetometer streams with a known orientation, for the heading tests."""
from __future__ import annotations

import numpy as np

from indoor_loc.imu.quaternion import qmul, quat_from_rotvec, quat_to_rotmat

G = 9.81
FIELD_ENU_UT = np.array([0.0, 18.0, -42.0])   # µT, pointing north and down (dip ≈ 67°)


def turning_device(rng, duration_s=30.0, imu_hz=200.0, mag_hz=50.0, yaw_rate=0.3, jitter_s=0.0005,
                   noise=True):
    """A level-ish device turning about up at ``yaw_rate`` rad/s with a small wobble: IMU stamps at
    ``imu_hz`` and magnetometer stamps at ``mag_hz`` on their own jittery clocks. Returns a dict
    with ``t`` (N,) ns, ``gyr`` rad/s, ``acc`` m/s², ``q`` (N, 4) true w x y z device→ENU,
    ``mt`` (M,) ns, ``mag`` µT (M, 3), ``mq`` (M, 4) true orientation at the magnetometer stamps."""
    def stamps(rate, n):
        t = np.arange(n) / rate + rng.uniform(-jitter_s, jitter_s, n)
        return np.round(1e9 + t * 1e9).astype(np.int64)

    def orient(t_ns):
        ts = (t_ns - 1e9) * 1e-9
        yaw = yaw_rate * ts
        roll = 0.15 * np.sin(2 * np.pi * 0.5 * ts)
        return qmul(quat_from_rotvec(np.c_[np.zeros_like(ts), np.zeros_like(ts), yaw]),
                    quat_from_rotvec(np.c_[roll, np.zeros_like(ts), np.zeros_like(ts)]))

    n = int(duration_s * imu_hz)
    t = stamps(imu_hz, n)
    q = orient(t)
    # body rate: yaw rate about world up expressed in the body frame + the roll rate
    ts = (t - 1e9) * 1e-9
    roll = 0.15 * np.sin(2 * np.pi * 0.5 * ts)
    droll = 0.15 * 2 * np.pi * 0.5 * np.cos(2 * np.pi * 0.5 * ts)
    gyr = np.c_[droll, yaw_rate * np.sin(roll), yaw_rate * np.cos(roll)]
    rt = np.transpose(quat_to_rotmat(q), (0, 2, 1))
    acc = rt @ np.array([0.0, 0.0, G])
    m = int(duration_s * mag_hz)
    mt = stamps(mag_hz, m) + 3_000_000               # its own clock phase
    mq = orient(mt)
    mag = np.transpose(quat_to_rotmat(mq), (0, 2, 1)) @ FIELD_ENU_UT
    if noise:
        gyr = gyr + 0.002 * rng.standard_normal(gyr.shape)
        acc = acc + 0.03 * rng.standard_normal(acc.shape)
        mag = mag + 0.2 * rng.standard_normal(mag.shape)
    return {"t": t, "gyr": gyr, "acc": acc, "q": q, "mt": mt, "mag": mag, "mq": mq}


def arrival_order(t, mt, mag_delay_ns, rng=None):
    """The order messages reach a node when each magnetometer message is delivered
    ``mag_delay_ns`` (scalar or (M,)) after its stamp: list of ("imu", i) / ("mag", j)."""
    d = np.broadcast_to(np.asarray(mag_delay_ns, dtype=np.int64), mt.shape)
    arrive = np.maximum.accumulate(mt + d)          # one topic is delivered in order (FIFO)
    ev = [(int(t[i]), 0, "imu", i) for i in range(len(t))] + \
         [(int(arrive[j]), 1, "mag", j) for j in range(len(mt))]
    ev.sort()
    return [(k, i) for _, _, k, i in ev]
