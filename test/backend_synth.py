"""A small synthetic building for back-end tests: a 60 m corridor with access points, a survey map
over part of it, and users walking with a stepometer (hops of 0.32 s) and a scan every 4 s."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from indoor_loc.wifi.types import RadioMap, WifiScan

SEC = 1_000_000_000
HOP_NS = 320_000_000
AP_XY = np.array([[x, y] for x in range(0, 61, 2) for y in (-2.0, 2.0)], float)
BSSIDS = tuple(f"02:00:00:00:00:{i:02x}" for i in range(len(AP_XY)))


def rssi(xy: np.ndarray, rng: np.random.Generator | None = None, sigma_db: float = 2.0) -> np.ndarray:
    """Log-distance RSS of every AP at xy (dBm), NaN where below -90 dBm (not heard: beyond ~6 m, so
    places a few metres apart hear different sets of APs)."""
    d = np.linalg.norm(AP_XY - np.asarray(xy, float), axis=1)
    r = -30.0 - 77.0 * np.log10(np.maximum(d, 1.0))
    if rng is not None:
        r = r + rng.normal(0.0, sigma_db, len(r))
    return np.where(r >= -90.0, r, np.nan)


def scan_at(stamp_ns: int, xy: np.ndarray, rng: np.random.Generator) -> WifiScan:
    r = rssi(xy, rng)
    ok = ~np.isnan(r)
    return WifiScan(stamp_ns=stamp_ns, bssid=tuple(b for b, k in zip(BSSIDS, ok) if k), rssi_dbm=r[ok],
                    freq_mhz=np.full(int(ok.sum()), 2412.0), ssid=("synth",) * int(ok.sum()))


def survey(x_from: float, x_to: float, rng: np.random.Generator, spacing: float = 2.0) -> RadioMap:
    pos = np.array([[x, y] for x in np.arange(x_from, x_to + 1e-9, spacing) for y in (-1.0, 1.0)], float)
    return RadioMap(positions=pos, bssids=list(BSSIDS), rssi_dbm=np.array([rssi(p, rng, 1.0) for p in pos]),
                    freq_mhz=np.full(len(BSSIDS), 2412.0))


@dataclass
class Walk:
    name: str
    events: list          # (stamp, kind 0 hop / 1 scan, payload) in stamp order
    truth_t: np.ndarray   # (T,) ns
    truth_xy: np.ndarray  # (T, 2)

    def true_xy_at(self, stamps_ns) -> np.ndarray:
        t = np.asarray(stamps_ns, float)
        return np.stack([np.interp(t, self.truth_t.astype(float), self.truth_xy[:, k]) for k in (0, 1)], axis=1)


def corridor_walk(name: str, x0: float, x1: float, t0_ns: int, rng: np.random.Generator, *, speed: float = 1.3,
                  step_len: float = 0.7, scan_period_s: float = 4.0, y: float = 0.0) -> Walk:
    """Walk along the corridor from x0 to x1 at ``speed`` m/s with true step length ``step_len``;
    hop step counts carry 3 % noise, the odometry yaw 0.02 rad noise."""
    heading = 0.0 if x1 >= x0 else math.pi
    n_hops = int(abs(x1 - x0) / speed / (HOP_NS / SEC))
    t_end = t0_ns + np.arange(1, n_hops + 1) * HOP_NS
    truth_t = np.concatenate([[t0_ns], t_end])
    dist = np.concatenate([[0.0], np.arange(1, n_hops + 1) * speed * HOP_NS / SEC])
    truth_xy = np.stack([x0 + math.cos(heading) * dist, np.full(len(dist), y)], axis=1)
    steps_true = speed * HOP_NS / SEC / step_len
    ev = []
    for te in t_end:
        steps = steps_true * (1 + 0.03 * rng.normal())
        ev.append((int(te), 0, (int(te - HOP_NS), int(te), float(steps), heading + 0.02 * rng.normal())))
    w = Walk(name, [], truth_t, truth_xy)
    for ts in np.arange(t0_ns + SEC, t_end[-1], int(scan_period_s * SEC)):
        ev.append((int(ts), 1, scan_at(int(ts), w.true_xy_at([ts])[0], rng)))
    ev.sort(key=lambda e: (e[0], e[1]))
    w.events = ev
    return w


def feed(graph, walk: Walk) -> None:
    for _, kind, payload in walk.events:
        if kind == 0:
            graph.add_hop(walk.name, *payload)
        else:
            graph.add_scan(walk.name, payload)


def delay_fixes(stream: list, lag_s: float, *, never=lambda stamp: False) -> list:
    """One user's messages ``[(stamp_ns, topic, msg)]`` as a slow WiFi node delivers them: each
    ``wifi/fix`` once the ``pdr/odom`` is ``lag_s`` past its stamp (the rest at the end); fixes for
    which ``never(stamp)`` holds are not delivered at all."""
    out, held = [], []
    for stamp, topic, msg in stream:
        if topic == "wifi/fix":
            if not never(stamp):
                held.append((stamp, topic, msg))
            continue
        out.append((stamp, topic, msg))
        if topic == "pdr/odom":
            while held and stamp - held[0][0] >= lag_s * SEC:
                out.append(held.pop(0))
    return out + held
