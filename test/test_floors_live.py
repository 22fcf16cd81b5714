"""Floors live over DDS: tll_pf in a namespace on the three-floor graph, fed pdr/odom, one wifi/fix
and baro/pressure; a lift ride the barometer sees moves pf/pose z to the floor above."""
from __future__ import annotations

import sys
import time
from contextlib import contextmanager

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from helpers_dds import Peer, child_env, ros_node, spin_until
from indoor_loc.baro.height import pressure_at_height_pa
from indoor_loc.contract import Qos
from indoor_loc.graph import save_graph
from indoor_loc.measurements import Fix
from indoor_loc.nodes.base import qos_profile
from indoor_loc.sim.building import building_graph, make_tower_building
from msg_adapters.odom import odom_to_msg
from msg_adapters.pose import fix_to_msg
from msg_adapters.pressure import pressure_to_msg

SEC = 1_000_000_000


@contextmanager
def _pf_in_tower(tmp_path, depth: int):
    """A tll_pf for /alice on the tower building (300 particles, no monitor) and a probe node with
    publishers of its odometry, fixes and pressure, subscribed to its pf/pose: yields (the node's
    process, the probe's executor, the poses received, the publishers by kind)."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import FluidPressure

    gf = save_graph(building_graph(make_tower_building()), tmp_path / "tower.graph.yaml")
    proc = Peer([sys.executable, "-m", "indoor_loc.nodes.tll_pf_node", "--ros-args", "-r", "__ns:=/alice",
                 "-p", f"graph_file:={gf}", "-p", "n_particles:=300", "-p", "monitor.enabled:=false"], env=child_env())
    try:
        with ros_node("probe") as (node, ex):
            poses: list = []
            node.create_subscription(PoseWithCovarianceStamped, "/alice/pf/pose", poses.append,
                                     QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                                                durability=DurabilityPolicy.TRANSIENT_LOCAL))
            pubs = {"odom": node.create_publisher(Odometry, "/alice/pdr/odom", qos_profile(Qos.RELIABLE)),
                    "fix": node.create_publisher(PoseWithCovarianceStamped, "/alice/wifi/fix", qos_profile(Qos.RELIABLE)),
                    "baro": node.create_publisher(FluidPressure, "/alice/baro/pressure", qos_profile(Qos.RELIABLE))}
            assert spin_until(ex, lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 60), proc.output()
            yield proc, ex, poses, pubs
    finally:
        proc.stop()


def _stream(t0: int, still_in_lift: bool = False) -> list[tuple[int, str, object]]:
    """A walker at the west end of floor 0 walks into the lift (2.5 m west), rides one storey up
    (3.5 m in 3.5 s from 8 s) and stands; the barometer at 10 Hz, PDR hops every 0.32 s
    (``still_in_lift``: none once in the lift, as a step detector standing still)."""
    rng = np.random.default_rng(5)
    out: list[tuple[int, str, object]] = [(t0, "fix", fix_to_msg(Fix(t0, np.array([1.0, 10.0]), np.eye(2) * 0.5)))]
    for k in range(1, 90):
        t = t0 + k * 320_000_000
        x = 1.0 - min(2.5, 0.32 * k * 1.2)
        if still_in_lift and 1.0 - 0.32 * (k - 1) * 1.2 <= -1.5:
            break
        out.append((t, "odom", odom_to_msg(t, "alice/odom", "alice/base_link", x - 1.0, 0.0, np.pi, np.eye(3) * 0.01,
                                           1.2 if x > -1.5 else 0.0, 0.0)))
    for k in range(0, 290):
        t = t0 + k * 100_000_000
        h = 1.1 + float(np.clip((k / 10 - 8.0) / 3.5, 0.0, 1.0)) * 3.5
        p = float(pressure_at_height_pa(h, 101325.0)) + rng.normal(0.0, 4.0)
        out.append((t, "baro", pressure_to_msg(t, "alice/imu_link", round(p, 0), 64.0)))
    return sorted(out, key=lambda r: r[0])


@pytest.mark.timeout(240)      # above the sum of the condition deadlines, not an expected duration
def test_a_lift_ride_seen_by_the_barometer_moves_pf_pose_z_up_a_floor(ros_domain, tmp_path):
    with _pf_in_tower(tmp_path, depth=200) as (proc, ex, poses, pubs):
        t0 = 10 * SEC
        stream = _stream(t0)
        start = time.monotonic()
        for t, kind, msg in stream:         # at 5x real time: the node takes its topics side by side
            spin_until(ex, lambda: False, max(0.002, (t - t0) / SEC / 5 - (time.monotonic() - start)))
            pubs[kind].publish(msg)
        last_hop = max(t for t, kind, _ in stream if kind == "odom")

        def stamp_of(p) -> int:
            return p.header.stamp.sec * SEC + p.header.stamp.nanosec
        # every hop taken (a loaded machine: the node may be seconds behind the publisher)
        assert spin_until(ex, lambda: len(poses) >= 60 and stamp_of(poses[-1]) >= last_hop, 60), proc.output()
        spin_until(ex, lambda: False, 1.0)
        stamp = np.array([p.header.stamp.sec * SEC + p.header.stamp.nanosec for p in poses])
        z = np.array([p.pose.pose.position.z for p in poses])
        assert np.all(z[stamp < t0 + 8 * SEC] == 0.0), z             # floor 0 before the ride
        assert z[-1] == pytest.approx(3.5), (z, proc.output())        # floor 1 after it
        assert np.all(z[stamp > t0 + 20 * SEC] == pytest.approx(3.5))


@pytest.mark.timeout(240)      # above the sum of the condition deadlines, not an expected duration
def test_a_lift_ride_without_steps_is_published_when_the_floor_snaps(ros_domain, tmp_path):
    """No pdr/odom and no fix once the walker is in the lift: pf/pose on the floor above is
    published at the barometer sample at which the floor snapped (it used to wait for a step)."""
    with _pf_in_tower(tmp_path, depth=200) as (proc, ex, poses, pubs):
        t0 = 10 * SEC
        stream = _stream(t0, still_in_lift=True)
        assert max(t for t, kind, _ in stream if kind == "odom") < t0 + 3 * SEC
        for _, kind, msg in stream:
            pubs[kind].publish(msg)
            spin_until(ex, lambda: False, 0.002)
        assert spin_until(ex, lambda: any(p.pose.pose.position.z > 3.0 for p in poses), 60), proc.output()
        stamp = np.array([p.header.stamp.sec * SEC + p.header.stamp.nanosec for p in poses])
        z = np.array([p.pose.pose.position.z for p in poses])
        assert np.all(z[stamp < t0 + 8 * SEC] == 0.0), z
        up = stamp[np.isclose(z, 3.5)]
        assert t0 + 8 * SEC < up[0] <= t0 + 12 * SEC, (stamp - t0) / SEC   # the ride ends at 11.5 s


@pytest.mark.timeout(240)      # above the sum of the condition deadlines, not an expected duration
def test_pressure_published_ahead_of_odometry_is_taken_in_stamp_order(ros_domain, tmp_path):
    """The barometer straight from the phone, half a second ahead of pdr/odom (the stepometer reports
    its hops late): tll_pf takes the two topics in stamp order (the shared reorder buffer), so the
    floor change the barometer sees is applied where the walker was at that stamp and pf/pose stays in
    stamp order (taken in arrival order, the pose published at the floor's snap was followed by the
    older hops' poses)."""
    with _pf_in_tower(tmp_path, depth=500) as (proc, ex, poses, pubs):
        t0 = 10 * SEC
        lead = SEC // 2
        stream = sorted(_stream(t0), key=lambda r: r[0] - (lead if r[1] == "baro" else 0))
        start = time.monotonic()
        for t, kind, msg in stream:         # the barometer's samples 0.5 s of stamp time ahead, at 5x real time
            sent = t - (lead if kind == "baro" else 0)
            spin_until(ex, lambda: False, max(0.002, (sent - t0) / SEC / 5 - (time.monotonic() - start)))
            pubs[kind].publish(msg)
        last_hop = max(t for t, kind, _ in stream if kind == "odom")

        def stamp_of(p) -> int:
            return p.header.stamp.sec * SEC + p.header.stamp.nanosec
        assert spin_until(ex, lambda: len(poses) >= 60 and stamp_of(poses[-1]) >= last_hop, 60), proc.output()
        spin_until(ex, lambda: False, 1.0)
        stamp = np.array([stamp_of(p) for p in poses])
        z = np.array([p.pose.pose.position.z for p in poses])
        assert np.all(np.diff(stamp) >= 0), (stamp - t0) / SEC          # pf/pose in stamp order
        assert np.all(z[stamp < t0 + 9 * SEC] == 0.0), z               # floor 0 before the ride
        assert np.all(z[stamp > t0 + 13 * SEC] == pytest.approx(3.5)), z   # floor 1 after it
