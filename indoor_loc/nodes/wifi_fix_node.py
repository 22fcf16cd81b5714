"""``ros2 run indoor_loc wifi_fix_node``: WiFi positioning, wifi/scan -> wifi/fix (see
pipeline/wifi_fix_stage.py). Each method's parameters are a group named after the method
(``wknn.k``, ``pathloss.sigma_db``, ``coverage.mimo`` ...), declared, merged and documented by
``--help`` like every stage's parameter groups."""
from __future__ import annotations

from typing import Any

from indoor_loc.nodes.base import StageNode, run_stage_node
from indoor_loc.pipeline.wifi_fix_stage import WifiFixStage


class WifiFixNode(StageNode):
    """The node class, for composing it in a process of one's own (``WifiFixNode(context=...)``)."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__(WifiFixStage, **node_kwargs)


def main(args: list[str] | None = None) -> int:
    return run_stage_node(WifiFixStage, args)


if __name__ == "__main__":
    raise SystemExit(main())
