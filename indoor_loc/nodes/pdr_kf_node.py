"""``ros2 run indoor_loc pdr_kf_node``: Raitoharju et al. 2015 linear PDR Kalman filter + RTS smoother."""
from __future__ import annotations

from indoor_loc.nodes.process import run_stage_node
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage


#: parameter values that change the node's topics, named in its ``--help``
PORT_PARAMS = {"motion_source": ("odom",)}


def main(args: list[str] | None = None) -> int:
    return run_stage_node(PdrKfStage, args, port_params=PORT_PARAMS)


if __name__ == "__main__":
    raise SystemExit(main())
