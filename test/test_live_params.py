"""Params files in a namespace, as `ros2 run ... -r __ns:=/walk06 --params-file params.yaml` runs
them: `/**/node` keys reach the node, a bare key that cannot is reported loudly, and a node missing
a required input (the radio map) says so at start-up and in /diagnostics as ERROR."""
from __future__ import annotations

import numpy as np
import pytest

from helpers_dds import ros_node, spin_until
from msg_adapters.diagnostics import diagnostics_from_msg
from indoor_loc.nodes.base import params_file_args
from indoor_loc.nodes.wifi_fix_node import WifiFixNode
from indoor_loc.params import params_file_text
from indoor_loc.wifi.radiomap import save_radiomap
from indoor_loc.wifi.types import RadioMap

# a bound for a hung test, above the sum of a test's condition deadlines (which a loaded machine may
# use up one after another), not an expected duration
pytestmark = pytest.mark.timeout(120)


def _radiomap(tmp_path) -> str:
    grid = np.array([[x, y] for x in range(0, 20, 4) for y in range(0, 12, 3)], float)
    aps = [f"00:11:22:33:44:{i:02x}" for i in range(3)]
    rssi = np.array([[-40.0 - 2 * x - i, -50.0 - y, -60.0 + i] for i, (x, y) in enumerate(grid)])
    rm = RadioMap(positions=grid, bssids=aps, rssi_dbm=rssi, freq_mhz=np.full(3, 2412.0))
    return str(save_radiomap(rm, tmp_path / "map"))


def _node(probe, path, ns="/walk06"):
    return WifiFixNode(context=probe.context, namespace=ns, cli_args=["--ros-args", "--params-file", str(path)])


def test_written_params_file_reaches_a_namespaced_node(ros_domain, tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text(params_file_text({"imu_node": {"step_length_m": 0.7},
                                      "wifi_fix_node": {"radiomap": _radiomap(tmp_path), "method": "wknn"}}))
    with ros_node("probe") as (probe, ex):
        node = _node(probe, path)
        ex.add_node(node)
        try:
            assert node.stage.radio_map is not None and node.stage.radio_map.n_scans == 20
            assert node.check_params_files([str(path)]) == []
            # the map is fitted in the background; once it is, the node is OK
            assert spin_until(ex, lambda: node.stage.positioner is not None, 60)
            st = diagnostics_from_msg(node.diagnostics_msg(0))["/walk06/wifi_fix_node"]
            assert st.level == 0, st        # OK
        finally:
            ex.remove_node(node)
            node.destroy_node()


def test_bare_key_in_a_namespace_is_an_error_and_a_missing_map_is_diagnosed(ros_domain, tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text(f"wifi_fix_node:\n  ros__parameters:\n    radiomap: {_radiomap(tmp_path)}\n")
    with ros_node("probe") as (probe, _):
        node = _node(probe, path)
        try:
            assert node.stage.radio_map is None                 # rcl did not apply the bare key
            msgs = node.check_params_files([str(path)])
            assert len(msgs) == 1 and "'/**/wifi_fix_node'" in msgs[0] and "NOT in force" in msgs[0]
            st = diagnostics_from_msg(node.diagnostics_msg(0))["/walk06/wifi_fix_node"]
            assert st.level == 2 and "no radio map" in st.message   # ERROR
        finally:
            node.destroy_node()
        root = _node(probe, path, ns="/")                       # in the root namespace it applies
        try:
            assert root.stage.radio_map is not None and root.check_params_files([str(path)]) == []
        finally:
            root.destroy_node()


def test_params_file_args():
    argv = ["x", "--opt", "--ros-args", "-r", "__ns:=/a", "--params-file", "p1.yaml", "--", "--params-file",
            "no.yaml", "--ros-args", "--params-file", "p2.yaml"]
    assert params_file_args(argv) == ["p1.yaml", "p2.yaml"]
