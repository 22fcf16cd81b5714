"""``ros2 run indoor_loc wifi_fix_node``: WiFi positioning, wifi/scan -> wifi/fix
(see pipeline/wifi_fix_stage.py).

Besides the stage's plain parameters, each method's parameters are declared under the method's
name as a prefix (``wknn.k``, ``pathloss.sigma_db``, ``coverage.mimo`` ...) with the defaults and
docs of its Params dataclass, so ``ros2 param list`` shows them and a params file may set them as
a nested mapping (``wknn: {k: 5}``) or ``-p wknn.k:=5``. Unknown names stop start-up as usual.
"""
from __future__ import annotations

import dataclasses
import sys
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult

from indoor_loc.errors import ConfigError
from indoor_loc.nodes.base import StageNode, _default_of, _py_value, _ros_value, node_usage, run_stage_node
from indoor_loc.pipeline.wifi_fix_stage import WifiFixStage
from indoor_loc.wifi.methods import METHODS, params_class


class WifiFixNode(StageNode):
    """StageNode for :class:`WifiFixStage` with method parameters as dotted ROS parameters."""

    def __init__(self, **node_kwargs: Any) -> None:
        self._nested: dict[str, list[str]] = {}
        super().__init__(WifiFixStage, **node_kwargs)

    def _declare_params(self, params_cls: type) -> dict[str, Any]:
        nested: dict[str, dict[str, Any]] = {}
        for method in METHODS:
            try:
                pcls = params_class(method)
            except ConfigError:
                continue     # method not available: its parameters stay unknown
            block: dict[str, Any] = {}
            for f in dataclasses.fields(pcls):
                default = _default_of(f)
                desc = ParameterDescriptor(description=f.metadata.get("doc", ""), dynamic_typing=True,
                                           read_only=True)
                p = self.declare_parameter(f"{method}.{f.name}", _ros_value(default), desc)
                value = _py_value(p.value)
                if value is None and isinstance(default, (list, tuple)):
                    value = type(default)()
                if value is not None:
                    block[f.name] = value
            nested[method] = block
            self._nested[method] = [f.name for f in dataclasses.fields(pcls)]
        values = super()._declare_params(params_cls)      # plain fields + the unknown-name check
        values.update(nested)
        return values

    def _on_set_params(self, changes: list) -> SetParametersResult:
        if any(p.name.split(".", 1)[0] in self._nested for p in changes if "." in p.name):
            return SetParametersResult(successful=False,
                                       reason="parameters are read-only at run time; restart the node")
        return super()._on_set_params(changes)


def method_usage() -> str:
    """The dotted method parameters with their defaults and docs (appended to ``--help``)."""
    lines = ["", "method parameters (used for the selected method only):"]
    for method in METHODS:
        try:
            pcls = params_class(method)
        except ConfigError as err:
            lines.append(f"  {method}.*: unavailable ({err})")
            continue
        for f in dataclasses.fields(pcls):
            lines.append(f"  {method}.{f.name} (default {_default_of(f)!r}): {f.metadata.get('doc', '')}")
    return "\n".join(lines)


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    user_args = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if any(a in ("-h", "--help") for a in user_args):
        print(node_usage(WifiFixStage) + method_usage())
        return 0
    return run_stage_node(WifiFixStage, argv, node_factory=WifiFixNode)


if __name__ == "__main__":
    sys.exit(main())
