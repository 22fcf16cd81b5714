"""Every params file in ``config/`` loads into its node (through rcl's ``--params-file``, in a
namespace) with every parameter documented at its default, and every node's ``--help`` lists its
parameters with their dotted group names."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from indoor_loc.params import leaves, load_params_file, params_for_node, params_from_dict
from indoor_loc.pipeline.registry import STAGES, stage_class

ROOT = Path(__file__).resolve().parents[1]
STAGE_BY_NODE = {stage_class(name).NODE_NAME: stage_class(name) for name in STAGES}
NODE_FILES = sorted(p for p in (ROOT / "config").glob("*.yaml")
                    if any(str(k).rsplit("/", 1)[-1] in STAGE_BY_NODE for k in (yaml.safe_load(p.read_text()) or {})))


def _node_of(path: Path) -> str:
    keys = [str(k).rsplit("/", 1)[-1] for k in yaml.safe_load(path.read_text())]
    nodes = [k for k in keys if k in STAGE_BY_NODE]
    assert len(set(nodes)) == 1, f"{path.name}: expected the parameters of one node, got keys {keys}"
    return nodes[0]


def test_every_stage_node_ships_a_params_file():
    shipped = {_node_of(p) for p in NODE_FILES}
    assert {"imu_node", "wifi_fix_node", "wifi_scan_node"} <= shipped


@pytest.mark.parametrize("path", NODE_FILES, ids=lambda p: p.name)
def test_params_file_documents_every_parameter_at_its_default(path):
    node = _node_of(path)
    cls = STAGE_BY_NODE[node].PARAMS
    values = params_for_node(load_params_file(path), node, "/alice")
    params = params_from_dict(cls, values)
    names = {name for name, _, default in leaves(cls) if not isinstance(default, dict)}  # dicts: free-form
    missing = sorted(names - set(_flat_keys(values)))
    assert not missing, f"{path.name} lacks {missing}"
    defaults = cls()
    differ = [name for name in names if _get(params, name) != _get(defaults, name)]
    assert not differ, f"{path.name}: values differ from the defaults: {differ}"


@pytest.mark.parametrize("path", NODE_FILES, ids=lambda p: p.name)
def test_params_file_loads_into_the_live_node_in_a_namespace(path, ros_domain):
    """What ``ros2 run indoor_loc NODE --ros-args -r __ns:=/alice --params-file FILE`` does, in process."""
    rclpy = pytest.importorskip("rclpy")
    from indoor_loc.nodes.base import StageNode
    node_name = _node_of(path)
    stage_cls = STAGE_BY_NODE[node_name]
    ctx = rclpy.Context()
    rclpy.init(context=ctx, args=["x", "--ros-args", "-r", "__ns:=/alice", "--params-file", str(path)])
    try:
        node = StageNode(stage_cls, context=ctx)
        try:
            assert node.get_fully_qualified_name() == f"/alice/{node_name}"
            values = params_for_node(load_params_file(path), node_name, "/alice")
            for name, _, default in leaves(stage_cls.PARAMS):
                if isinstance(default, dict):     # a free-form mapping: the keys the file gives
                    assert all(node.has_parameter(k) for k in _flat_keys(values) if k.startswith(name + ".")), name
                else:
                    assert node.has_parameter(name), name
            expected = params_from_dict(stage_cls.PARAMS, values)
            assert node.stage.params == expected
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


@pytest.mark.parametrize("module", ["imu_node", "wifi_fix_node", "wifi_scan_node", "pdr_kf_node"])
def test_node_help_lists_every_parameter(module):
    r = subprocess.run([sys.executable, "-m", f"indoor_loc.nodes.{module}", "--help"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    stage_cls = STAGE_BY_NODE[module]
    for name, _, default in leaves(stage_cls.PARAMS):
        assert f"  {name} (default {default!r})" in r.stdout, name


def _flat_keys(values: dict, prefix: str = "") -> list[str]:
    out = []
    for k, v in values.items():
        out += _flat_keys(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}"]
    return out


def _get(obj, dotted: str):
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj
