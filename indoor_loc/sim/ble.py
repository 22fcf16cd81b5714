"""Simulated BLE beacons (pure numpy): fixed beacons with known positions that do not rotate their
address (iBeacon-style ids), heard by the survey phone and by every walker's phone.

Beacons are placed on the level links of chosen floors' *zone* (a plan box), at least ``spacing_m``
apart (greedy along the survey points, deterministic), ``height_m`` above the floor. Their signal
follows the simulator's radio model (:class:`~indoor_loc.sim.rf.RssField`: log-distance path loss,
walls, floors, correlated shadowing) with BLE's numbers: −59 dBm at 1 m (an iBeacon's measured
power at 0 dBm), 2.4 GHz path loss, 4 dB fast fading (one advertisement to the next scatters more
than a WiFi scan's average), −95 dBm sensitivity. A phone hears each beacon at ``rate_hz``
(advertisements it catches), each heard advertisement a :class:`~indoor_loc.wifi.ble.BleScan`
row; the survey hears them at each survey point.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from indoor_loc.sim.building import ApCluster, Building
from indoor_loc.sim.rf import RfParams, RssField, read_rss
from indoor_loc.wifi.ble import BleScan

BLE_FREQ_MHZ = 2426.0          # an advertising channel (38)


@dataclass(frozen=True)
class BleSimParams:
    spacing_m: float = 8.0            # beacons at least this far apart, m
    height_m: float = 2.5             # above the floor, m
    rate_hz: float = 1.0              # readings per beacon per second a phone reports
    p1_dbm: float = -59.0             # mean RSS at 1 m, dBm
    fading_std_db: float = 4.0        # per-reading noise, dB
    sensitivity_dbm: float = -95.0    # 50 % detection, dBm
    detection_slope_db: float = 2.0
    device_offset_std_db: float = 1.5


def place_beacons(b: Building, floors: tuple[int, ...], zone: tuple[float, float, float, float],
                  params: BleSimParams | None = None) -> tuple[ApCluster, ...]:
    """Beacons on ``floors`` inside the plan box ``zone`` = (x0, y0, x1, y1), on level links, at least
    ``spacing_m`` apart; ids ``sim-beacon-<floor>-<k>`` (fixed: they do not rotate)."""
    from indoor_loc.sim.scenario import survey_points
    p = params or BleSimParams()
    pts, pfl = survey_points(b, 1.0)
    x0, y0, x1, y1 = zone
    out: list[ApCluster] = []
    for f in floors:
        chosen: list[np.ndarray] = []
        sel = (pfl == f) & (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
        for q in pts[sel]:
            if all(np.hypot(*(q[:2] - c[:2])) >= p.spacing_m for c in chosen):
                chosen.append(q)
        for k, q in enumerate(chosen):
            bid = f"sim-beacon-{f}-{k}"
            out.append(ApCluster(bid, (float(q[0]), float(q[1]), float(b.floor_z[f] + p.height_m)), int(f),
                                 (bid,), ("",), (BLE_FREQ_MHZ,)))
    return tuple(out)


class BeaconField:
    """The beacons' mean RSS anywhere (the simulator's radio model with BLE's numbers)."""

    def __init__(self, b: Building, beacons: tuple[ApCluster, ...], rf: RfParams, params: BleSimParams,
                 rng: np.random.Generator) -> None:
        self.p = params
        self.ids = [a.bssids[0] for a in beacons]
        self.field = RssField(replace(b, aps=beacons), replace(rf, p1_24_dbm=params.p1_dbm,
                                                               fading_std_db=params.fading_std_db), rng=rng)

    def read(self, stamp_ns: int, xyz: np.ndarray, floor: int, rng: np.random.Generator, offset_db: float = 0.0,
             source: str = "", frame_id: str = "") -> BleScan | None:
        """The beacons heard at one instant at ``xyz`` on ``floor`` (None: none)."""
        mean = self.field.mean_rss(np.asarray(xyz, float)[None], np.array([floor]))[0]
        val = read_rss(mean, rng, fading_std_db=self.p.fading_std_db, sensitivity_dbm=self.p.sensitivity_dbm,
                       slope_db=self.p.detection_slope_db, offset_db=offset_db)
        seen = np.flatnonzero(np.isfinite(val))
        if not len(seen):
            return None
        return BleScan(stamp_ns=int(stamp_ns), beacon_id=tuple(self.ids[k] for k in seen), rssi_dbm=val[seen],
                       tx_power_dbm=np.full(len(seen), self.p.p1_dbm), name=tuple(self.ids[k] for k in seen),
                       frame_id=frame_id, source=source)

    def along(self, t_ns: np.ndarray, xyz: np.ndarray, floor: np.ndarray, duration_s: float,
              rng: np.random.Generator, name: str = "") -> list[BleScan]:
        """A phone following ``(t_ns, xyz, floor)`` (its motion): one reading of the beacons heard
        every ``1 / rate_hz`` s (stamps relative to the run start, like its WiFi scans)."""
        offset = float(rng.normal(0.0, self.p.device_offset_std_db))
        t_s = np.asarray(t_ns, np.int64) * 1e-9
        out = []
        for t in np.arange(float(rng.uniform(0.0, 1.0 / self.p.rate_hz)), duration_s, 1.0 / self.p.rate_hz):
            k = min(int(np.searchsorted(t_s, t)), len(t_s) - 1)
            pos = np.array([np.interp(t, t_s, xyz[:, j]) for j in range(3)])
            s = self.read(int(round(t * 1e9)), pos, int(floor[k]), rng, offset, "sim", f"{name}/ble_link")
            if s is not None:
                out.append(s)
        return out
