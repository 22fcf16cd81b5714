"""`indoor-loc run` as a user meets it: stages resolved by topics (any --nodes order), ticks that
follow the data across long gaps, stage exceptions in tick/finish counted not fatal, outputs that
never clobber inputs or existing files, a node with nothing to do is warned about (an error only when no
requested node can run), bag time per user."""
from __future__ import annotations

import sys
from collections import Counter

import numpy as np
import pytest

from helpers_dds import PEERS
from indoor_loc.bag import BagWriter, read_bag
from indoor_loc.cli import main as cli_main
from msg_adapters.imu import imu_to_msg
from msg_adapters.wifi_scan import scan_to_msg
from indoor_loc.pipeline import offline
from indoor_loc.pipeline.offline import run_offline
from indoor_loc.wifi.radiomap import save_radiomap
from indoor_loc.wifi.types import RadioMap, WifiScan

sys.path.insert(0, str(PEERS))
from dummy_node import DummyStage  # noqa: E402

APS = [f"00:11:22:33:44:{i:02x}" for i in range(4)]
AP_XY = np.array([[0, 0], [20, 0], [0, 15], [20, 15]], float)
S = 1_000_000_000


def _rssi(xy):
    return -40.0 - 25.0 * np.log10(np.maximum(np.linalg.norm(AP_XY - xy, axis=1), 1.0))


def _scan_bag(tmp_path, stamps, ns="/alice", name="in.mcap"):
    grid = np.array([[x, y] for x in range(0, 21, 4) for y in range(0, 16, 3)], float)
    rm = RadioMap(positions=grid, bssids=list(APS), rssi_dbm=np.array([_rssi(p) for p in grid]),
                  freq_mhz=np.full(len(APS), 2412.0))
    params = tmp_path / "params.yaml"
    params.write_text(f"/**/wifi_fix_node:\n  ros__parameters:\n    radiomap: {save_radiomap(rm, tmp_path / 'map')}\n")
    bag = tmp_path / name
    with BagWriter(bag) as w:
        for t in stamps:
            scan = WifiScan(stamp_ns=t, bssid=tuple(APS), rssi_dbm=_rssi(np.array([8.0, 6.0])),
                            freq_mhz=np.full(4, 2412.0), ssid=("n",) * 4, frame_id="alice/wifi_link", source="t")
            w.write(f"{ns}/wifi/scan_raw", scan_to_msg(scan), t)
    return bag, params


@pytest.mark.parametrize("order", ["wifi_scan,wifi", "wifi,wifi_scan"])
def test_node_order_does_not_matter(tmp_path, order):
    bag, params = _scan_bag(tmp_path, [2 * S + k * S for k in range(4)])
    out = tmp_path / "out.mcap"
    assert cli_main(["run", str(bag), "--nodes", order, "--params", str(params), "--out", str(out)]) == 0
    counts = Counter(m.topic for m in read_bag([out]))
    assert counts["/alice/wifi/scan"] == 4 and counts["/alice/wifi/fix"] == 4


def test_ticks_follow_the_data_across_a_long_gap(tmp_path):
    day = 86_400 * S                    # two recordings a day apart
    stamps = [2 * S + k * S for k in range(5)] + [day + k * S for k in range(5)]
    bag, params = _scan_bag(tmp_path, stamps)
    summary = run_offline([bag], tmp_path / "out.mcap", nodes=["wifi_scan", "wifi"], params=params)
    assert summary.ticks <= 14                        # one per second of data (+ the gap's edges), not 86 400
    diags = [m for m in read_bag([tmp_path / "out.mcap"]) if m.topic == "/diagnostics"]
    assert len(diags) == 2 * summary.ticks
    assert summary.span_by_ns == {"/alice": pytest.approx((day + 4 * S - 2 * S) * 1e-9)}


class FailingStage(DummyStage):
    def tick(self, now_ns):
        raise RuntimeError("tick bug")

    def finish(self):
        raise ZeroDivisionError("finish bug")


def test_exceptions_in_tick_and_finish_are_counted_not_fatal(tmp_path, monkeypatch):
    bag = tmp_path / "imu.mcap"
    with BagWriter(bag) as w:
        for k in range(30):
            t = S + k * 100_000_000
            w.write("/bob/imu/data_raw", imu_to_msg(t, "bob/imu_link", [1.0, 2.0, 9.8]), t)
    real = offline.stage_class
    monkeypatch.setattr(offline, "stage_class", lambda n: FailingStage if n == "failing" else real(n))
    summary = run_offline([bag], tmp_path / "out.mcap", nodes=["failing"])
    kv = summary.per_stage["/bob/dummy_node"]
    assert int(kv["rejected.internal_error"]) == summary.ticks + 1      # every tick, and finish
    assert kv["out.dummy/pose.count"] == "30"                           # the outputs before are kept
    assert Counter(m.topic for m in read_bag([tmp_path / "out.mcap"]))["/bob/dummy/pose"] == 30


def test_output_never_clobbers(tmp_path, capsys):
    bag, params = _scan_bag(tmp_path, [2 * S, 3 * S])
    size = bag.stat().st_size
    common = ["--nodes", "wifi_scan,wifi", "--params", str(params)]
    assert cli_main(["run", str(bag), *common, "--out", str(bag)]) == 2
    assert "is also an input" in capsys.readouterr().err and bag.stat().st_size == size
    assert cli_main(["run", str(bag), *common, "--out", str(bag), "--overwrite"]) == 2   # never, even so
    assert bag.stat().st_size == size
    out = tmp_path / "out.mcap"
    out.write_text("precious")
    assert cli_main(["run", str(bag), *common, "--out", str(out)]) == 2
    assert "exists; refusing to overwrite" in capsys.readouterr().err and out.read_text() == "precious"
    assert cli_main(["run", str(bag), *common, "--out", str(out), "--overwrite"]) == 0
    assert Counter(m.topic for m in read_bag([out]))["/alice/wifi/fix"] == 2
    assert not (tmp_path / "out.mcap.partial").exists()


def test_a_node_with_nothing_to_do_is_an_error(tmp_path, capsys):
    bag, params = _scan_bag(tmp_path, [2 * S, 3 * S])
    assert cli_main(["run", str(bag), "--nodes", "pdr_kf", "--out", str(tmp_path / "o.mcap")]) == 2
    err = capsys.readouterr().err
    assert "nothing to do for node(s) pdr_kf" in err and "pdr/odom" in err and not (tmp_path / "o.mcap").exists()
    assert "(e.g. wifi,wifi_scan,pdr_kf)" in err          # pdr/odom has no producer here; wifi/fix does
    assert cli_main(["run", str(bag), "--nodes", "pf", "--out", str(tmp_path / "o.mcap")]) == 2
    assert "(e.g. wifi,wifi_scan,pf)" in capsys.readouterr().err        # the hint names pf's producers


def test_an_idle_node_beside_working_ones_is_a_warning(tmp_path, capsys):
    # a walk without IMU (or, as on a real site, without WiFi scans): the nodes that can run do
    bag, params = _scan_bag(tmp_path, [2 * S, 3 * S])
    out = tmp_path / "o.mcap"
    s = run_offline([bag], out, nodes=["wifi_scan", "wifi", "imu", "pdr_kf"], params=params, progress=False)
    err = capsys.readouterr().err
    assert "warning: nothing to do for node(s) imu" in err and "imu/data_raw" in err
    assert s.idle == ["imu"] and ("indoor-loc run", s.notices[0][1]) == s.notices[0]
    assert Counter(m.topic for m in read_bag([out]))["/alice/wifi/fix"] == 2
    assert cli_main(["run", str(bag), "--nodes", "imu,wifi_scan,wifi", "--params", str(params),
                     "--out", str(tmp_path / "o2.mcap")]) == 0


def test_a_stage_missing_its_radio_map_says_so_at_start(tmp_path, capsys):
    bag, _ = _scan_bag(tmp_path, [2 * S, 3 * S])
    assert cli_main(["run", str(bag), "--nodes", "wifi_scan,wifi", "--out", str(tmp_path / "o.mcap")]) == 0
    err = capsys.readouterr().err
    assert "wifi_fix_node in /alice cannot work: no radio map configured" in err and "no --params given" in err


def test_bag_time_is_reported_per_namespace(tmp_path, capsys):
    a, params = _scan_bag(tmp_path, [2 * S, 12 * S], ns="/alice", name="a.mcap")
    b, _ = _scan_bag(tmp_path, [1000 * S, 1005 * S], ns="/bob", name="b.mcap")
    assert cli_main(["run", str(a), str(b), "--nodes", "wifi_scan,wifi", "--params", str(params),
                     "--out", str(tmp_path / "o.mcap")]) == 0
    assert "bag time /alice 10.0 s, /bob 5.0 s (15.0 s in all)" in capsys.readouterr().out


def test_topics_no_node_takes_count_for_their_user_not_a_root_namespace(tmp_path, capsys):
    bag, params = _scan_bag(tmp_path, [2 * S, 3 * S])
    extra = tmp_path / "extra.mcap"
    with BagWriter(extra) as w:          # the user's truth (taken by no node) outlasts the scans
        for t in (1 * S, 9 * S):
            w.write("/alice/ground_truth_debug", imu_to_msg(t, "map", [0.0, 0.0, 9.8]), t)
    assert cli_main(["run", str(bag), str(extra), "--nodes", "wifi_scan,wifi", "--params", str(params),
                     "--out", str(tmp_path / "o.mcap")]) == 0
    assert "bag time /alice 8.0 s (8.0 s in all)" in capsys.readouterr().out
