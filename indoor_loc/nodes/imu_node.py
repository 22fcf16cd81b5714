"""``ros2 run indoor_loc imu_node``: FFT stepometer + AEKF/orientation heading -> pdr/odom, imu/data."""
from __future__ import annotations

from indoor_loc.nodes.process import run_stage_node
from indoor_loc.pipeline.imu_stage import ImuStage


#: parameter values that change the node's topics, named in its ``--help``
PORT_PARAMS = {"heading_source": ("orientation",)}


def main(args: list[str] | None = None) -> int:
    return run_stage_node(ImuStage, args, port_params=PORT_PARAMS)


if __name__ == "__main__":
    raise SystemExit(main())
