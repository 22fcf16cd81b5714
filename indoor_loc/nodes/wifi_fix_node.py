"""``ros2 run indoor_loc wifi_fix_node``: WiFi positioning, wifi/scan -> wifi/fix (see
pipeline/wifi_fix_stage.py). Each method's parameters are a group named after the method
(``wknn.k``, ``pathloss.sigma_db``, ``coverage.mimo`` ...), declared, merged and documented by
``--help`` like every stage's parameter groups."""
from __future__ import annotations

from indoor_loc.nodes.base import run_stage_node
from indoor_loc.pipeline.wifi_fix_stage import WifiFixStage


def main(args: list[str] | None = None) -> int:
    return run_stage_node(WifiFixStage, args)


if __name__ == "__main__":
    raise SystemExit(main())
