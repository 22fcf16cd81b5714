"""PUTMC walks as back-end events (stepometer hops with heading, WiFi scans), without ROS messages.

The same front end as ``imu_node`` with ``heading_source: orientation`` on the imported bags: the
FFT stepometer on the accelerometer, the heading = yaw of the phone's rotation vector rotated into
the map frame (the importer's calibration), looked up at each hop's end. Used by
``indoor-loc bench backend`` and the real-data tests to drive :class:`MultiUserGraph` directly.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import repeat
from operator import itemgetter

import numpy as np

from indoor_loc.datasets.putmc import PUTMC_MAP_YAW_RAD, Walk, map_yaw
from indoor_loc.backend.factors import wrap
from indoor_loc.imu.stepometer import Stepometer
from indoor_loc.imu.stepometer_types import StepometerParams
from indoor_loc.wifi.types import WifiScan

#: The back-end configuration ``indoor-loc import putmc`` writes (``backend_node`` in params.yaml): the
#: paper's joint + step-length graph with its information set from measured noise instead of the
#: paper's weights. The paper's WKNN information (10 I: σ = 0.32 m) trusts a fix ten times more
#: than the WKNN error warrants, so the optimum stays at the WKNN fixes (2.78 m at the scan times,
#: WKNN alone 2.86 m). Measured on the odd walks (1, 3, …, 23) only: WKNN fix error against each
#: scan's true position, robust σ ≈ 1.9 m per axis (MAD; heavy tail: p95 7.1 m) → WiFi information
#: 1/1.9² = 0.28 with a Huber kernel at 1.345 σ ≈ 2.5 m (the usual 95 %-efficiency threshold) for
#: the wrong matches; PDR information 4 (σ = 0.5 m per 1.28 s edge) chosen among 1/4/10/25 by the
#: scan-time error of the odd walks. The even walks are held out (``indoor-loc bench backend``
#: prints both halves).
PUTMC_GRAPH_PARAMS: dict = {"joint": True, "estimate_step_length": True, "wifi_info": 0.28,
                            "pdr_info": [4.0, 4.0, 15.0], "robust_kernel": "huber", "robust_threshold_m": 2.5}


@dataclass
class WalkEvents:
    """One walk: hops (t_start (H,), t_end (H,), steps (H,), yaw (H,) rad) and its scans."""
    name: str
    t_start: np.ndarray
    t_end: np.ndarray
    steps: np.ndarray
    yaw: np.ndarray
    scans: list[WifiScan]

    def events(self) -> list[tuple[int, int, object]]:
        """(stamp, kind 0 = hop / 1 = scan, payload) in stamp order (a hop before a scan of the same stamp)."""
        t_end = self.t_end.tolist()                 # Python ints and floats, column by column
        ev = list(zip(t_end, repeat(0), zip(self.t_start.tolist(), t_end, self.steps.tolist(), self.yaw.tolist())))
        ev += [(int(s.stamp_ns), 1, s) for s in self.scans]
        ev.sort(key=itemgetter(0, 1))
        return ev


def walk_events(walk: Walk, *, stepometer: StepometerParams | None = None,
                map_yaw_rad: float = PUTMC_MAP_YAW_RAD) -> WalkEvents:
    """Stepometer hops and headings of a walk (see module docstring)."""
    sm = Stepometer(stepometer)
    hops = sm.update_many(walk.acc_t, walk.acc) + sm.finish()      # the whole walk in one call
    yaw = map_yaw(walk.quat_xyzw, map_yaw_rad)
    cols = list(zip(*hops)) if hops else [(), (), ()]           # the hops' fields, column by column
    t_start, t_end, steps = np.array(cols[0], np.int64), np.array(cols[1], np.int64), np.array(cols[2], float)
    # linear interpolation of the unwrapped yaw at each hop's end (as HeadingHistory.at in imu_node)
    t0 = int(walk.ori_t[0]) if len(walk.ori_t) else 0
    hy = wrap(np.interp((t_end - t0).astype(float), (walk.ori_t - t0).astype(float), np.unwrap(yaw))) \
        if len(hops) and len(yaw) else np.zeros(len(hops))
    return WalkEvents(walk.name, t_start, t_end, steps, hy, list(walk.scans))
