"""``ros2 run indoor_loc backend_node``: the multi-user factor-graph back-end (one node for all users)."""
from __future__ import annotations

from indoor_loc.nodes.base import run_stage_node
from indoor_loc.pipeline.backend_stage import BackendStage


def main(args: list[str] | None = None) -> int:
    return run_stage_node(BackendStage, args)


if __name__ == "__main__":
    raise SystemExit(main())
