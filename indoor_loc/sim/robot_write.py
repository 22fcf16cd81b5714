"""The simulated robots' messages and params (:mod:`indoor_loc.sim.write` puts them in the bag).

Per robot namespace (``/robot1`` …): ``odom`` (nav_msgs/Odometry, ``robot1/odom`` -> ``robot1/base_link``,
the wheel odometry with its covariance, at ``odom_rate_hz``), ``imu`` (sensor_msgs/Imu, ``robot1/imu_link``:
gyro z and gravity, no orientation — on ``imu``, as robot drivers name it, so no stepometer runs for a
robot; an IMU-only robot would remap it to ``imu/data_raw``), ``wifi/scan`` and the ground truth as
for walkers.
"""
from __future__ import annotations

from indoor_loc.contract import join_ns
from indoor_loc.sim.robot import SimRobot

GRAVITY_M_S2 = 9.81
#: the robots' nodes: their own odometry is the estimators' motion input
ROBOT_NODE_PARAMS = {"motion_source": "odom"}


def robot_streams(robots: list[SimRobot], t0_ns: int) -> list[tuple]:
    """(stamps, kind, robot, topic, frame) streams of the robots for the bag merge: kind 3 = odom, 4 = imu."""
    out = []
    for r in robots:
        ns = f"/{r.name}"
        out.append((r.odom.t_ns + t0_ns, 3, r, join_ns(ns, "odom"), f"{r.name}/odom"))
        out.append((r.odom.t_ns + t0_ns, 4, r, join_ns(ns, "imu"), f"{r.name}/imu_link"))
    return out


def robot_message(kind: int, r: SimRobot, i: int, stamp_ns: int):
    """Message ``i`` of a robot stream (see :func:`robot_streams`)."""
    if kind == 3:
        from msg_adapters.odom import odom_to_msg
        o = r.odom
        x, y, yaw = o.pose[i]
        return odom_to_msg(stamp_ns, f"{r.name}/odom", f"{r.name}/base_link", x, y, yaw, o.cov[i],
                           o.twist[i, 0], o.twist[i, 1])
    from msg_adapters.imu import imu_to_msg
    return imu_to_msg(stamp_ns, f"{r.name}/imu_link", [0.0, 0.0, GRAVITY_M_S2], [0.0, 0.0, r.odom.gyro_z[i]])


def robot_node_params(robots: list[SimRobot]) -> dict:
    """Params-file entries configuring each robot's own nodes (exact keys, over the ``/**`` ones)."""
    out: dict = {}
    for r in robots:
        for node in ("tll_pf", "pdr_kf_node"):
            out[f"/{r.name}/{node}"] = {"ros__parameters": dict(ROBOT_NODE_PARAMS)}
    return out


def robot_scenario(robots: list[SimRobot]) -> list[dict]:
    p = [r.params for r in robots]
    return [{"name": r.name, "speed_mps": q.speed_mps, "odom_rate_hz": q.odom_rate_hz,
             "odom_covariance": q.odom_covariance, "scans": len(r.scans),
             **({"kidnap_at_s": round(r.kidnap_ns * 1e-9, 3)} if r.kidnap_ns is not None else {}),
             "route_nodes": [int(n) for n in r.plan.node_seq]} for r, q in zip(robots, p)]
