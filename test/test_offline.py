"""`indoor-loc run`: one stage instance per user namespace, stages chained as over DDS,
/diagnostics once a second of bag time, ground truth copied, bad messages counted not fatal."""
from __future__ import annotations

from collections import Counter

import numpy as np

from indoor_loc.bag import BagWriter, read_bag
from indoor_loc.cli import main as cli_main
from msg_adapters.path import path_to_msg
from msg_adapters.pose import pose_from_msg
from msg_adapters.wifi_scan import scan_to_msg
from indoor_loc.wifi.radiomap import save_radiomap
from indoor_loc.wifi.types import RadioMap, WifiScan

APS = [f"00:11:22:33:44:{i:02x}" for i in range(6)]
AP_XY = np.array([[0, 0], [20, 0], [40, 0], [0, 15], [20, 15], [40, 15]], float)


def _rssi(xy: np.ndarray) -> np.ndarray:
    d = np.linalg.norm(AP_XY - xy, axis=1)
    return -40.0 - 25.0 * np.log10(np.maximum(d, 1.0))


def _map(tmp_path) -> str:
    grid = np.array([[x, y] for x in range(0, 41, 4) for y in range(0, 16, 3)], float)
    rm = RadioMap(positions=grid, bssids=list(APS), rssi_dbm=np.array([_rssi(p) for p in grid]),
                  freq_mhz=np.full(len(APS), 2412.0))
    return str(save_radiomap(rm, tmp_path / "map"))


def test_run_chains_stages_per_user_and_writes_diagnostics(tmp_path):
    radiomap = _map(tmp_path)
    params = tmp_path / "params.yaml"
    params.write_text(f"/**/wifi_fix_node:\n  ros__parameters:\n    radiomap: {radiomap}\n    wknn: {{k: 3}}\n")
    truth = {"/alice": np.array([10.0, 5.0]), "/bob": np.array([30.0, 10.0])}
    bag = tmp_path / "in.mcap"
    with BagWriter(bag) as w:
        for ns, xy in truth.items():
            w.write(f"{ns}/ground_truth", path_to_msg(np.array([1_000_000_000]), xy[None], None), 1_000_000_000)
        for k in range(5):                                   # one scan per user every 1.5 s
            t = 2_000_000_000 + k * 1_500_000_000
            for ns, xy in truth.items():
                scan = WifiScan(stamp_ns=t, bssid=tuple(APS), rssi_dbm=_rssi(xy), freq_mhz=np.full(6, 2412.0),
                                ssid=("net",) * 6, frame_id=f"{ns[1:]}/wifi_link", source="test")
                msg = scan_to_msg(scan)
                if ns == "/bob" and k == 2:
                    msg.status[0].values[0].value = "wifi_scan.v0"      # a bad message mid-stream
                w.write(f"{ns}/wifi/scan_raw", msg, t)
    out = tmp_path / "out.mcap"
    assert cli_main(["run", str(bag), "--nodes", "wifi_scan,wifi", "--params", str(params), "--out", str(out),
                     "--no-progress"]) == 0
    msgs = list(read_bag([out]))
    counts = Counter(m.topic for m in msgs)
    assert counts["/alice/wifi/scan"] == 5 and counts["/bob/wifi/scan"] == 4      # bob's bad scan dropped
    assert counts["/alice/wifi/fix"] == 5 and counts["/bob/wifi/fix"] == 4
    assert counts["/alice/ground_truth"] == 1 and counts["/bob/ground_truth"] == 1
    for ns, xy in truth.items():
        fixes = [pose_from_msg(m.msg) for m in msgs if m.topic == f"{ns}/wifi/fix"]
        assert max(np.linalg.norm(f.xy - xy) for f in fixes) < 3.0      # each user positioned on its own
    diags = [m for m in msgs if m.topic == "/diagnostics"]
    names = {m.msg.status[0].name for m in diags}
    assert names == {"/alice/wifi_scan_node", "/alice/wifi_fix_node", "/bob/wifi_scan_node", "/bob/wifi_fix_node"}
    bob_scan = [m.msg.status[0] for m in diags if m.msg.status[0].name == "/bob/wifi_scan_node"][-1]
    assert {kv.key: kv.value for kv in bob_scan.values}["rejected.schema_version"] == "1"
    stamps = sorted({m.stamp_ns for m in diags})
    assert len(stamps) >= 7 and all(np.diff(stamps[:-1]) == 1_000_000_000)    # 1 Hz in bag time
