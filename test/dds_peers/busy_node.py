"""A multi-user stage whose every message costs ``work_ms`` of Python work (a stand-in for the
back-end's per-message computation), run as a real node by the responsiveness test.
``python busy_node.py --ros-args -p users:=[u0,u1] -p work_ms:=20.0``"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass

from indoor_loc.contract import Qos
from indoor_loc.params import field, require
from indoor_loc.pipeline.stage import Port, Stage


@dataclass(frozen=True)
class BusyParams:
    """Parameters of the busy stage."""
    users: list = field([], "user namespaces to follow")
    user_timeout_s: float = field(60.0, "a user without publishers this long has left, s")
    work_ms: float = field(20.0, "Python work per message, ms")

    def validate(self) -> None:
        require(self.work_ms >= 0, "BusyParams", "work_ms", ">= 0", self.work_ms)


class BusyStage(Stage):
    """<user>/pdr/odom -> nothing, after ``work_ms`` of work."""
    NODE_NAME = "busy_node"
    PARAMS = BusyParams
    MULTI_USER = True

    def __init__(self, params: BusyParams, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        self.on("pdr/odom", self._on_odom)

    def inputs(self) -> list[Port]:
        return [Port("pdr/odom", "nav_msgs/msg/Odometry", Qos.RELIABLE)]

    def outputs(self) -> list[Port]:
        return []

    def _on_odom(self, msg, recv_ns: int, user: str):
        end = time.perf_counter() + self.params.work_ms * 1e-3
        n = 0
        while time.perf_counter() < end:      # interpreted work, as a stage's: the GIL switches between threads
            n += 1
        return []


def main(args: list[str] | None = None) -> int:
    from indoor_loc.nodes.process import run_stage_node
    return run_stage_node(BusyStage, args)


if __name__ == "__main__":
    sys.exit(main())
