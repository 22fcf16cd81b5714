"""A simulated walker seen as a robot stack sees it (for the map -> odom tests): ground truth, an
odometry stream in its own drifting ``<user>/odom`` frame and WiFi-like fixes, from the simulator."""
from __future__ import annotations

import math

import numpy as np

from indoor_loc.graph import save_graph
from indoor_loc.measurements import Fix
from indoor_loc.pipeline.map_odom import compose
from indoor_loc.sim.building import building_graph, sample_building
from indoor_loc.sim.scenario import SimConfig, simulate
from msg_adapters.odom import odom_to_msg
from msg_adapters.pose import fix_to_msg

T0 = 1_000_000_000_000
#: where the odometry frame starts in the map (x, y, yaw): the correction the estimators must find
ODOM_IN_MAP = (12.0, -4.0, 0.9)


class RobotWalk:
    def __init__(self, duration_s: float = 40.0, seed: int = 3, user: str = "alice") -> None:
        run = simulate(sample_building(), SimConfig(walkers=1, duration_s=duration_s, seed=seed))
        m = run.walkers[0].motion
        self.t_ns = T0 + m.t_ns.astype(np.int64)
        self.xy = m.body_xyz[:, :2].copy()
        self.yaw = m.heading.copy()
        self.graph = building_graph(run.building)
        self.user = user
        rng = np.random.default_rng(seed)
        # odometry: the truth seen from an odom frame placed at ODOM_IN_MAP, 3 % scale error and a slow
        # heading drift, one pose every 0.3 s (a robot's would come faster; the mechanism is the same)
        self.odom: list[tuple[int, tuple[float, float, float]]] = []
        inv = (-(math.cos(ODOM_IN_MAP[2]) * ODOM_IN_MAP[0] + math.sin(ODOM_IN_MAP[2]) * ODOM_IN_MAP[1]),
               math.sin(ODOM_IN_MAP[2]) * ODOM_IN_MAP[0] - math.cos(ODOM_IN_MAP[2]) * ODOM_IN_MAP[1],
               -ODOM_IN_MAP[2])
        x, y, _ = compose(inv, (self.xy[0, 0], self.xy[0, 1], self.yaw[0]))   # the start in the odom frame
        prev = self.xy[0]
        for i in range(30, len(self.t_ns), 30):
            d = self.xy[i] - prev
            prev = self.xy[i]
            h = float(self.yaw[i] - ODOM_IN_MAP[2] + 0.002 * i / 30)
            step = 1.03 * float(np.hypot(*d))
            ang = math.atan2(d[1], d[0]) - ODOM_IN_MAP[2] + 0.002 * i / 30
            x, y = x + step * math.cos(ang), y + step * math.sin(ang)
            self.odom.append((int(self.t_ns[i]), (x, y, h)))
        self.fixes = [(int(self.t_ns[i]) + 1000, self.xy[i] + rng.normal(0, 1.0, 2))
                      for i in range(100, len(self.t_ns), 150)]

    def save_graph(self, path):
        return save_graph(self.graph, path)

    def truth_at(self, stamp_ns: int) -> np.ndarray:
        return np.array([np.interp(stamp_ns, self.t_ns, self.xy[:, k]) for k in (0, 1)])

    def messages(self):
        """``(stamp_ns, relative topic, message)`` in stamp order."""
        out = [(s, "pdr/odom", odom_to_msg(s, f"{self.user}/odom", f"{self.user}/base_link", p[0], p[1], p[2],
                                           np.eye(3) * 0.05, 1.2, 0.0)) for s, p in self.odom]
        out += [(s, "wifi/fix", fix_to_msg(Fix(s, xy, np.eye(2) * 1.0))) for s, xy in self.fixes]
        return sorted(out, key=lambda e: e[0])
