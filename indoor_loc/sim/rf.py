"""The simulated RSS field: log-distance path loss, wall and floor attenuation, correlated shadowing.

Mean RSS of BSSID ``b`` at a receiver ``r`` (dBm)::

    P(b, r) = P1(band) - 10 n(band) log10(max(d, d0) / 1 m) - L_wall(band) N_walls - L_floor N_floors + S_b(r)

the log-distance model with a wall-attenuation term (the multi-wall model of COST 231; Seidel &
Rappaport, "914 MHz path loss prediction models for indoor wireless communications in multifloored
buildings", IEEE Trans. Antennas Propag. 1992, eq. 6 for the floor term) — the same path-loss
family the WiFi positioning methods assume (Koivisto et al. and Nowicki & Skrzypczyński use
``P0 - 10 n log10 d``). ``N_walls`` counts the wall segments crossed by the straight line
AP→receiver on the receiver's floor when both are on it; ``S_b`` is log-normal shadowing as a
spatially correlated Gaussian field (Gudmundson, "Correlation model for shadow fading in mobile
radio systems", Electron. Lett. 1991: exponential-like decorrelation over a few metres), drawn
per radio as random Fourier features so that it is smooth, deterministic for a seed and cheap to
evaluate anywhere. A reading adds independent fast-fading noise and is quantised to 1 dBm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from indoor_loc.errors import ConfigError
from indoor_loc.sim.building import ApCluster, Building


@dataclass(frozen=True)
class RfParams:
    """Radio model parameters (defaults: a typical office, 2.4 / 5 GHz)."""
    p1_24_dbm: float = -38.0          # mean RSS at 1 m, 2.4 GHz, dBm
    p1_5_dbm: float = -45.0           # mean RSS at 1 m, 5 GHz, dBm
    n_24: float = 2.2                 # path-loss exponent, 2.4 GHz
    n_5: float = 2.5                  # path-loss exponent, 5 GHz
    wall_24_db: float = 4.0           # attenuation per wall, 2.4 GHz, dB
    wall_5_db: float = 7.0            # attenuation per wall, 5 GHz, dB
    floor_db: float = 16.0            # attenuation per floor, dB
    shadow_std_db: float = 3.5        # shadowing standard deviation, dB
    shadow_corr_m: float = 3.0        # shadowing correlation length, m
    fading_std_db: float = 2.0        # per-reading fast-fading noise, dB
    bssid_offset_std_db: float = 1.0  # fixed offset between BSSIDs of one radio, dB
    d0_m: float = 0.5                 # the model is clipped below this distance, m
    n_features: int = 48              # random Fourier features per shadowing field

    def validate(self) -> None:
        for name in ("n_24", "n_5", "shadow_corr_m", "d0_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"RfParams.{name}: expected > 0, got {getattr(self, name)}")
        for name in ("wall_24_db", "wall_5_db", "floor_db", "shadow_std_db", "fading_std_db", "bssid_offset_std_db"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"RfParams.{name}: expected >= 0, got {getattr(self, name)}")


def is_5ghz(freq_mhz) -> np.ndarray:
    return np.asarray(freq_mhz, float) >= 4900.0


def count_crossings(a: np.ndarray, b: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """Number of wall segments crossed by each segment a[k]→b[k] (a, b: (K, 2); walls (W, 2, 2))."""
    if len(walls) == 0:
        return np.zeros(len(a), dtype=np.int64)
    p, r = a[:, None, :], (b - a)[:, None, :]                 # (K, 1, 2)
    q, s = walls[None, :, 0, :], (walls[:, 1] - walls[:, 0])[None]   # (1, W, 2)

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    den = cross(r, s)
    qp = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = cross(qp, s) / den
        u = cross(qp, r) / den
    hit = (np.abs(den) > 1e-12) & (t > 0) & (t < 1) & (u >= 0) & (u <= 1)
    return hit.sum(axis=1)


class RssField:
    """Mean RSS of every BSSID of a building anywhere, at any time (AP events applied).

    ``rng`` draws the shadowing fields and per-BSSID offsets once (so the survey and the walkers
    see the same field); readings draw their own noise from the generator passed to :meth:`read`.
    """

    def __init__(self, building: Building, params: RfParams | None = None, *, rng: np.random.Generator) -> None:
        self.b = building
        self.p = params or RfParams()
        self.p.validate()
        self.bssids: list[str] = []
        self.freq_mhz: list[float] = []
        self.ssids: list[str] = []
        self._ap: list[int] = []                  # cluster index per BSSID
        for k, ap in enumerate(building.aps):
            for bssid, ssid, f in zip(ap.bssids, ap.ssids, ap.freq_mhz):
                self.bssids.append(bssid)
                self.ssids.append(ssid)
                self.freq_mhz.append(f)
                self._ap.append(k)
        self._ap_idx = np.array(self._ap, dtype=np.int64)
        f5 = is_5ghz(self.freq_mhz)
        p = self.p
        self._p1 = np.where(f5, p.p1_5_dbm, p.p1_24_dbm)
        self._n = np.where(f5, p.n_5, p.n_24)
        self._wall = np.where(f5, p.wall_5_db, p.wall_24_db)
        nb = len(self.bssids)
        self._offset = rng.normal(0.0, p.bssid_offset_std_db, nb)
        # one shadowing field per radio (cluster, band): random Fourier features of a Gaussian kernel
        radio_key = [(a, bool(f)) for a, f in zip(self._ap, f5)]
        radios = sorted(set(radio_key))
        self._radio = np.array([radios.index(k) for k in radio_key], dtype=np.int64)
        nf = p.n_features
        self._w = rng.normal(0.0, 1.0 / p.shadow_corr_m, (len(radios), nf, 2))
        self._phase = rng.uniform(0.0, 2 * np.pi, (len(radios), nf))

    def shadowing(self, xy: np.ndarray) -> np.ndarray:
        """(N, B) shadowing in dB at plan positions xy (N, 2): zero mean, ``shadow_std_db`` std."""
        xy = np.atleast_2d(np.asarray(xy, float))
        arg = np.einsum("rfk,nk->nrf", self._w, xy) + self._phase[None]
        field = np.sqrt(2.0 / self.p.n_features) * np.cos(arg).sum(axis=2) * self.p.shadow_std_db
        return field[:, self._radio]

    def ap_state(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per BSSID at time ``t_s`` (s since the start): positions (B, 3), floors (B,), on (B,) bool."""
        pos, floors, on = [], [], []
        for k in self._ap:
            ap: ApCluster = self.b.aps[k]
            moved = ap.move_at_s is not None and t_s >= ap.move_at_s
            pos.append(ap.move_to_xyz if moved else ap.xyz)
            floors.append(ap.floor)
            on.append(ap.off_at_s is None or t_s < ap.off_at_s)
        return np.array(pos, float).reshape(-1, 3), np.array(floors, dtype=np.int64), np.array(on, bool)

    def mean_rss(self, xyz: np.ndarray, floor: np.ndarray, t_s: float = 0.0) -> np.ndarray:
        """Mean RSS (N, B) dBm at receivers xyz (N, 3) m on floors (N,), APs as at ``t_s``; -inf for APs off."""
        xyz = np.atleast_2d(np.asarray(xyz, float))
        floor = np.broadcast_to(np.asarray(floor, dtype=np.int64), (len(xyz),))
        ap_pos, ap_floor, on = self.ap_state(t_s)
        d = np.linalg.norm(xyz[:, None, :] - ap_pos[None], axis=2)
        rss = self._p1[None] - 10.0 * self._n[None] * np.log10(np.maximum(d, self.p.d0_m))
        rss = rss - self.p.floor_db * np.abs(floor[:, None] - ap_floor[None])
        # walls between AP and receiver, on the receiver's floor (only for APs on that floor)
        nw = np.zeros(rss.shape)
        for f in np.unique(floor):
            rows = np.flatnonzero(floor == f)
            cols = np.flatnonzero(ap_floor == f)
            if len(cols) == 0:
                continue
            walls = self.b.walls[self.b.wall_floor == f]
            a = np.repeat(xyz[rows, :2], len(cols), axis=0)
            bb = np.tile(ap_pos[cols, :2], (len(rows), 1))
            nw[np.ix_(rows, cols)] = count_crossings(a, bb, walls).reshape(len(rows), len(cols))
        rss = rss - self._wall[None] * nw + self._offset[None] + self.shadowing(xyz[:, :2])
        return np.where(on[None], rss, -np.inf)


@dataclass(frozen=True)
class ScannerParams:
    """A phone's WiFi scanner."""
    period_s: float = 4.0             # time between scans, s
    period_jitter_s: float = 0.5      # uniform jitter of the period, ± s
    sweep_s: float = 2.0              # a scan sweeps the channels over this long; readings are older by up to it, s
    sensitivity_dbm: float = -90.0    # 50 % detection level, dBm
    detection_slope_db: float = 2.0   # width of the logistic detection curve, dB
    device_offset_std_db: float = 1.5  # per-device RSS offset (antenna/gain), dB

    def validate(self) -> None:
        if not self.period_s > self.sweep_s >= 0:
            raise ConfigError(f"ScannerParams: expected period_s > sweep_s >= 0, got {self.period_s}, {self.sweep_s}")
        if not self.detection_slope_db > 0:
            raise ConfigError(f"ScannerParams.detection_slope_db: expected > 0, got {self.detection_slope_db}")


def read_rss(mean_dbm: np.ndarray, rng: np.random.Generator, *, fading_std_db: float, sensitivity_dbm: float,
             slope_db: float, offset_db: float = 0.0) -> np.ndarray:
    """Noisy, quantised readings of mean RSS values (any shape); NaN = not detected (weak APs are
    missed with a logistic probability around ``sensitivity_dbm``)."""
    mean = np.asarray(mean_dbm, float) + offset_db
    val = np.round(mean + rng.normal(0.0, fading_std_db, mean.shape))
    with np.errstate(over="ignore", invalid="ignore"):
        p_det = 1.0 / (1.0 + np.exp(-(mean - sensitivity_dbm) / slope_db))
    seen = np.isfinite(mean) & (rng.random(mean.shape) < p_det) & (val <= -1.0) & (val >= -119.0)
    return np.where(seen, val, np.nan)
