"""tll_pf live over DDS: the node in a namespace, fed pdr/odom + wifi/fix, publishes pf/pose,
map/graph (latched) and answers ~/global_localization."""
from __future__ import annotations

import sys

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from helpers_dds import Peer, child_env, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.graph import build_graph, save_graph
from indoor_loc.measurements import Fix
from indoor_loc.nodes.base import qos_profile
from msg_adapters.odom import odom_to_msg
from msg_adapters.pose import fix_to_msg, pose_from_msg


@pytest.mark.timeout(240)      # above the sum of the condition deadlines, not an expected duration
def test_tll_pf_node_in_a_namespace(ros_domain, tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from std_srvs.srv import Empty
    from visualization_msgs.msg import MarkerArray

    g = build_graph([0, 1, 2], np.array([[0, 0], [20, 0], [20, 10]], float), [(0, 1), (1, 2)])
    gf = save_graph(g, tmp_path / "g.graph.yaml")
    proc = Peer([sys.executable, "-m", "indoor_loc.nodes.tll_pf_node", "--ros-args", "-r", "__ns:=/alice",
                 "-p", f"graph_file:={gf}", "-p", "n_particles:=300"], env=child_env())
    try:
        with ros_node("probe") as (node, ex):
            poses: list = []
            graphs: list = []
            # latched (transient local) like the contract, but a history deep enough that poses the node
            # publishes back to back (a backlog after a stall) wait for this probe instead of replacing each other
            node.create_subscription(PoseWithCovarianceStamped, "/alice/pf/pose", poses.append,
                                     QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                                durability=DurabilityPolicy.TRANSIENT_LOCAL))
            node.create_subscription(MarkerArray, "/alice/map/graph", graphs.append, qos_profile(Qos.LATCHED))
            odom = node.create_publisher(Odometry, "/alice/pdr/odom", qos_profile(Qos.RELIABLE))
            fix = node.create_publisher(PoseWithCovarianceStamped, "/alice/wifi/fix", qos_profile(Qos.RELIABLE))
            assert spin_until(ex, lambda: odom.get_subscription_count() > 0 and fix.get_subscription_count() > 0,
                              60), proc.output()
            t0 = 10_000_000_000
            fix.publish(fix_to_msg(Fix(t0, np.array([1.0, 0.5]), np.eye(2))))
            for i in range(30):                                   # walk east along the first link
                odom.publish(odom_to_msg(t0 + (i + 1) * 320_000_000, "alice/odom", "alice/base_link",
                                         0.4 * (i + 1), 0.0, 0.0, np.eye(3) * 0.1, 1.2, 0.0))
                spin_until(ex, lambda: False, 0.005)
            assert spin_until(ex, lambda: len(poses) >= 20 and len(graphs) >= 1, 40), proc.output()
            last = pose_from_msg(poses[-1])
            assert last.xy[1] < 2.0 and 6.0 < last.xy[0] < 20.0     # on the first link, moved east
            cli = node.create_client(Empty, "/alice/tll_pf/global_localization")
            assert cli.wait_for_service(timeout_sec=40), proc.output()
            fut = cli.call_async(Empty.Request())
            assert spin_until(ex, fut.done, 40), proc.output()
    finally:
        proc.stop()
