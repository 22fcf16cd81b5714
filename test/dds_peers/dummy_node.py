"""A tiny Stage run as a real node by the node-base and bring-up tests.

``imu/data_raw`` (Imu) -> ``dummy/pose`` (PoseWithCovarianceStamped, xy = gain * acc[:2]); at the
end of input it publishes one more pose at the origin with the count of accepted messages as its
stamp. ``python dummy_node.py --ros-args -r __ns:=/alice -p gain:=2.0``
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from indoor_loc.params import field, require
from indoor_loc.contract import Qos
from msg_adapters.imu import imu_from_msg
from msg_adapters.pose import pose_to_msg
from indoor_loc.pipeline.stage import Port, Stage


@dataclass(frozen=True)
class DummyParams:
    """Parameters of the dummy stage."""
    gain: float = field(1.0, "output = gain * input acceleration (s^2)")
    label: str = field("dummy", "reported in diagnostics")
    weights: list = field([], "unused list parameter (exercises empty-list declaration)")
    enabled: bool = field(True, "unused bool parameter")

    def validate(self) -> None:
        require(self.gain > 0, "DummyParams", "gain", "> 0", self.gain)
        require(self.label != "", "DummyParams", "label", "a non-empty string", self.label)


class DummyStage(Stage):
    """Dummy stage: imu/data_raw -> dummy/pose (xy = gain * acc[:2])."""
    NODE_NAME = "dummy_node"
    PARAMS = DummyParams

    def __init__(self, params: DummyParams, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        self.accepted = 0
        self.on("imu/data_raw", self._on_imu)

    def inputs(self) -> list[Port]:
        return [Port("imu/data_raw", "sensor_msgs/msg/Imu", Qos.RELIABLE)]

    def outputs(self) -> list[Port]:
        return [Port("dummy/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", Qos.RELIABLE)]

    def _on_imu(self, msg, recv_ns: int):
        s = imu_from_msg(msg)
        self.accepted += 1
        return [("dummy/pose", pose_to_msg(s.stamp_ns, self.params.gain * s.acc[:2]))]

    def finish(self):
        return [("dummy/pose", pose_to_msg(self.accepted, [0.0, 0.0]))]

    def extra_diagnostics(self) -> dict[str, str]:
        return {"gain": repr(self.params.gain), "label": self.params.label,
                "weights": repr(list(self.params.weights))}


def main(args: list[str] | None = None) -> int:
    from indoor_loc.nodes.base import run_stage_node
    return run_stage_node(DummyStage, args)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.exit(main())
