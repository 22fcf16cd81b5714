"""``ros2 run indoor_loc backend_node``: the multi-user factor-graph back-end (one node for all users).

Clock jumps back are said as one WARN each (the stage's notices): a user's own stamps going back
(:class:`~indoor_loc.pipeline.backend_stage.BackendStage`), and, under ``use_sim_time``, ``/clock``
going back by more than ``time_jump_s`` (a bag played with ``--loop`` or a simulation restarted):
every user whose clock is ahead of it starts afresh at its first message of the new pass (no second
message needed, while that pass may still be coming; messages of the old pass still in flight go
into the old track). The jump callback runs in the executor's thread (``/clock`` is this node's
subscription, spun by a single-threaded executor), never alongside a message callback.
"""
from __future__ import annotations

from typing import Any

from rclpy.clock import JumpThreshold, TimeJump
from rclpy.duration import Duration

from indoor_loc.nodes.process import run_stage_node
from indoor_loc.nodes.stage_node import StageNode
from indoor_loc.pipeline.backend_stage import BackendStage


#: parameter values that change the node's topics, named in its ``--help``
PORT_PARAMS = {"wifi_source": ("fix",)}


class BackendNode(StageNode):
    """:class:`StageNode` for :class:`BackendStage`: follows ``/clock`` jumps back (the stage's notices
    are logged as every stage's, by :class:`StageNode`)."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__(BackendStage, **node_kwargs)
        stage = self.backend
        self._jump_handle = None
        if stage.params.time_jump_s:
            self._jump_handle = self.get_clock().create_jump_callback(
                JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-int(stage.params.time_jump_s * 1e9)),
                              on_clock_change=False),
                post_callback=self._on_clock_jump)

    @property
    def backend(self) -> BackendStage:
        assert isinstance(self.stage, BackendStage)
        return self.stage

    def _on_clock_jump(self, jump: TimeJump) -> None:
        """``/clock`` went back (sim time): every user ahead of it starts afresh at its next message."""
        now_ns = self.get_clock().now().nanoseconds
        self._publish(self.backend.run_clock_jump(-jump.delta.nanoseconds, now_ns))
        self._log_rejections()


def main(args: list[str] | None = None) -> int:
    return run_stage_node(BackendStage, args, node_factory=BackendNode, port_params=PORT_PARAMS)


if __name__ == "__main__":
    raise SystemExit(main())
