"""The building on ``/map`` (nav_msgs/OccupancyGrid, latched) from the nav2 map_server plans the
simulator writes; ``map draw --plan floor0.yaml``; a layout for the actual users; ``--version``;
executable names that shadow no other program."""
from __future__ import annotations

import ast
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers_dds import Peer, child_env, ros_node, spin_until

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def plans(tmp_path_factory) -> Path:
    from indoor_loc.sim.building import load_building, sample_building_path, save_floor_plans
    d = tmp_path_factory.mktemp("plans")
    save_floor_plans(load_building(sample_building_path()), d)
    return d


def test_nav2_map_reads_the_simulators_plans_with_map_server_thresholds(plans, tmp_path):
    from PIL import Image

    from indoor_loc.errors import MapError
    from indoor_loc.graph.nav2_map import read_nav2_map
    m = read_nav2_map(plans / "floor0.yaml")
    assert m.resolution_m == 0.05 and m.floor == 0 and m.origin == (-1.0, -1.0, 0.0)
    occ = m.occupancy()
    assert occ.shape == m.grey.shape and set(np.unique(occ)) <= {-1, 0, 100}
    assert (occ == 100).any() and (occ == 0).any()
    # by hand: black -> occupied, white -> free, mid grey (p = 0.5) -> unknown; row 0 of the grid is the
    # image's bottom row
    Image.fromarray(np.array([[0, 255], [128, 255]], np.uint8)).save(tmp_path / "t.png")
    (tmp_path / "t.yaml").write_text("image: t.png\nresolution: 0.1\norigin: [1.0, 2.0, 0.0]\nnegate: 0\n"
                                     "occupied_thresh: 0.65\nfree_thresh: 0.25\n")
    np.testing.assert_array_equal(read_nav2_map(tmp_path / "t.yaml").occupancy(), [[-1, 0], [100, 0]])
    (tmp_path / "bad.yaml").write_text("image: t.png\n")
    with pytest.raises(MapError, match="resolution"):
        read_nav2_map(tmp_path / "bad.yaml")


def test_map_draw_takes_the_nav2_yaml_as_plan(plans, tmp_path, capsys):
    from indoor_loc.cli import main as cli_main
    from indoor_loc.graph.io import save_graph
    from indoor_loc.sim.building import building_graph, load_building, sample_building_path
    graph = save_graph(building_graph(load_building(sample_building_path())), tmp_path / "g.graph.yaml")
    out = tmp_path / "draw.png"
    assert cli_main(["map", "draw", str(graph), "-o", str(out), "--plan", str(plans / "floor0.yaml")]) == 0, \
        capsys.readouterr().err
    assert out.stat().st_size > 10_000


def test_occupancy_grid_adapter_layout():
    from msg_adapters.occupancy import occupancy_to_msg
    from indoor_loc.errors import InvalidMessageError
    msg = occupancy_to_msg(np.array([[0, 100, -1], [0, 0, 100]], np.int8), 0.05, (1.0, 2.0, 0.0), z=3.5)
    assert (msg.info.width, msg.info.height, msg.info.resolution) == (3, 2, pytest.approx(0.05))
    assert list(msg.data) == [0, 100, -1, 0, 0, 100] and msg.header.frame_id == "map"
    assert (msg.info.origin.position.x, msg.info.origin.position.y, msg.info.origin.position.z) == (1.0, 2.0, 3.5)
    with pytest.raises(InvalidMessageError):
        occupancy_to_msg(np.array([[101]]), 0.05, (0, 0, 0))


@pytest.mark.timeout(90)
def test_map_node_latches_every_floor_on_map(ros_domain, plans):
    from nav_msgs.msg import OccupancyGrid
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from indoor_loc.graph.nav2_map import read_nav2_map
    node_proc = Peer([sys.executable, "-m", "indoor_loc.nodes.map_node", "--plans", str(plans), "--floor", "1"],
                     env=child_env())
    try:
        assert node_proc.wait_line(r"map: floor 1", timeout=60), node_proc.output()
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        got: dict[str, OccupancyGrid] = {}
        with ros_node("map_probe") as (node, ex):          # subscribes after the maps were published
            for t in ("/map", "/map/floor0", "/map/floor1"):
                node.create_subscription(OccupancyGrid, t, lambda m, t=t: got.__setitem__(t, m), latched)
            assert spin_until(ex, lambda: len(got) == 3, 30), (sorted(got), node_proc.output())
    finally:
        node_proc.stop()
    want = read_nav2_map(plans / "floor1.yaml")
    grid = got["/map"]
    assert (grid.info.height, grid.info.width) == want.grey.shape
    np.testing.assert_array_equal(np.frombuffer(bytes(grid.data), np.int8).reshape(want.grey.shape), want.occupancy())
    assert grid.info.origin.position.z == pytest.approx(want.height_m) and want.height_m > 0
    assert got["/map/floor0"].info.origin.position.z == 0.0


def test_layout_is_generated_for_the_users_and_the_shipped_one_is_its_default():
    from indoor_loc.demo import layout_path
    from indoor_loc.foxglove_layout import layout_for
    assert json.loads(layout_path().read_text()) == layout_for(["alice", "bob", "carol"])
    doc = layout_for(["robot1", "robot2"])
    panel = doc["configById"]["3D!indoorloc"]
    text = json.dumps(doc)
    assert "alice" not in text and "/robot2/pf/pose" in panel["topics"] and "/map" in panel["topics"]
    assert panel["publish"]["poseEstimateTopic"] == "/robot1/initialpose"
    assert doc["configById"]["RawMessages!pdr"]["topicPath"] == "/robot1/pdr/odom"


def test_version_is_the_packages(capsys):
    from indoor_loc.cli import main as cli_main
    with pytest.raises(SystemExit) as stop:
        cli_main(["--version"])
    assert stop.value.code == 0
    version = re.search(r"<version>([^<]+)</version>", (ROOT / "package.xml").read_text()).group(1)
    assert capsys.readouterr().out.strip() == f"indoor-loc {version}"


def test_no_executable_shadows_a_system_program():
    tree = ast.parse((ROOT / "setup.py").read_text())
    nodes = next(ast.literal_eval(n.value) for n in ast.walk(tree)
                 if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "NODES")
    assert "view" not in nodes           # vim's view
    assert {"indoor_loc_view", "indoor_loc_map"} <= set(nodes)
