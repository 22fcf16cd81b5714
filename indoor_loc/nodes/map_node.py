"""Map publisher: the building's floor plans as ``nav_msgs/OccupancyGrid``, latched, like nav2's map_server.

``indoor_loc_map --plans OUT/sim/floor_plans [--floor 0]`` (or nav2 map YAML files) publishes
``map`` (the floor ``--floor``, default the lowest) and ``map/floor<k>`` for every floor, transient
local (reliable, depth 1): RViz's and Foxglove's map displays show the building without a custom
layout, however late they start. Each grid sits at its floor's height (``height_m`` of the YAML
``indoor-loc sim`` writes; 0 otherwise). The plans are nav2 ``map_server`` YAML files
(:mod:`indoor_loc.graph.nav2_map`): a directory of ``floor<k>.yaml`` or the files themselves.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from indoor_loc.errors import ConfigError, MapError
from indoor_loc.nodes.help import run_option_node

NODE_NAME = "map_publisher"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--plans", type=Path, nargs="+", required=True,
                        help="nav2 map_server YAML files, or a directory of floor<k>.yaml (indoor-loc sim's "
                             "OUT/floor_plans)")
    parser.add_argument("--floor", type=int, default=None, help="floor published on 'map' (default: the lowest)")


def load_plans(paths: list[Path]):
    """{floor: Nav2Map} from YAML files or directories of them (floor from the YAML's ``floor`` key,
    else the file's order)."""
    from indoor_loc.graph.nav2_map import read_nav2_map
    files: list[Path] = []
    for p in paths:
        if p.is_dir():
            found = sorted(p.glob("*.yaml"))
            if not found:
                raise ConfigError(f"map.plans: {p} holds no nav2 map YAML")
            files += found
        elif p.is_file():
            files.append(p)
        else:
            raise ConfigError(f"map.plans: {p} does not exist")
    out = {}
    for i, f in enumerate(files):
        try:
            m = read_nav2_map(f)
        except MapError as err:
            raise ConfigError(f"map.plans: {err}") from err
        out[m.floor if m.floor is not None else i] = m
    return out


class MapNode(Node):
    def __init__(self, plans: dict, floor: int | None = None, **node_kwargs) -> None:
        from nav_msgs.msg import OccupancyGrid

        from msg_adapters.occupancy import occupancy_to_msg
        super().__init__(NODE_NAME, **node_kwargs)
        if floor is not None and floor not in plans:
            raise ConfigError(f"map.floor: {floor} is not among the plans' floors {sorted(plans)}")
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        stamp = self.get_clock().now().nanoseconds
        self.msgs = {}
        for k, m in sorted(plans.items()):
            self.msgs[k] = occupancy_to_msg(m.occupancy(), m.resolution_m, m.origin, z=m.height_m or 0.0,
                                            stamp_ns=stamp)
        self.pubs = {}
        for k, msg in self.msgs.items():
            self.pubs[k] = self.create_publisher(OccupancyGrid, f"map/floor{k}", latched)
            self.pubs[k].publish(msg)
        self.floor = min(plans) if floor is None else floor
        self.main = self.create_publisher(OccupancyGrid, "map", latched)
        self.main.publish(self.msgs[self.floor])
        m = plans[self.floor]
        self.get_logger().info(f"map: floor {self.floor}, {m.grey.shape[1]} x {m.grey.shape[0]} cells of "
                               f"{m.resolution_m:g} m; also map/floor<k> for floors {sorted(plans)}")


def run(options: argparse.Namespace, ros_args: list[str] | None = None) -> int:
    plans = load_plans(list(options.plans))
    rclpy.init(args=ros_args if ros_args is not None else sys.argv[:1])
    node = None
    try:
        node = MapNode(plans, options.floor)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:  # noqa: BLE001 - a signal at start-up shuts the context down under spin(): a stop
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main(args: list[str] | None = None) -> int:
    """``indoor_loc_map`` executable: ``--plans ... [--floor K] [--ros-args ...]``."""
    return run_option_node("indoor_loc_map", __doc__.splitlines()[0], add_arguments, run, args)


if __name__ == "__main__":
    sys.exit(main())
