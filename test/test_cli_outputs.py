"""The command line as a new user meets it: outputs are never clobbered by accident, and a wrong
input gets an error that says what is missing (exit 2, nothing written)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from indoor_loc.bag import BagWriter, bag_topics  # noqa: E402
from indoor_loc.cli import main  # noqa: E402

T0 = 1_700_000_000 * 10**9
BSSIDS = ("aa:bb:cc:00:00:01", "aa:bb:cc:00:00:02")


def _imu_bag(path: Path, n: int = 20) -> None:
    from sensor_msgs.msg import Imu
    with BagWriter(path) as w:
        for i in range(n):
            w.write("/u/imu/data", Imu(), T0 + i * 10**8)


def _survey_bag(path: Path, *, truth: bool = True) -> None:
    """One user walking (0, 0) → (10, 0) in 10 s with a scan every second."""
    from msg_adapters.path import path_to_msg
    from msg_adapters.wifi_scan import scan_to_msg
    from indoor_loc.wifi.types import WifiScan
    s = 10**9
    with BagWriter(path) as w:
        if truth:
            w.write("/alice/ground_truth", path_to_msg(T0 + np.array([0, 10]) * s, [[0, 0], [10, 0]]), T0)
        for k in range(1, 10):
            scan = WifiScan(T0 + k * s, BSSIDS, np.array([-40.0 - k, -70.0 + k]), np.array([2412.0, 5180.0]),
                            frame_id="alice/wifi_link", source="test")
            w.write("/alice/wifi/scan", scan_to_msg(scan), T0 + k * s)


def test_bag_recover_refuses_an_existing_output_unless_overwrite(tmp_path, capsys):
    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    _imu_bag(src)
    dst.write_bytes(b"an earlier recording")
    assert main(["bag", "recover", str(src), str(dst)]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "--overwrite" in err
    assert dst.read_bytes() == b"an earlier recording"                 # untouched
    assert main(["bag", "recover", str(src), str(src), "--overwrite"]) == 2   # never its own input
    assert "also an input" in capsys.readouterr().err
    assert main(["bag", "recover", str(tmp_path / "none.mcap"), str(tmp_path / "x.mcap")]) == 2
    assert "does not exist" in capsys.readouterr().err and not (tmp_path / "x.mcap").exists()
    assert main(["bag", "recover", str(src), str(dst), "--overwrite"]) == 0
    assert bag_topics(dst)["/u/imu/data"][1] == 20


def test_radiomap_build_refuses_an_existing_map_unless_overwrite(tmp_path, capsys):
    bag, out = tmp_path / "walk.mcap", tmp_path / "map"
    _survey_bag(bag)
    assert main(["radiomap", "build", str(bag), "--out", str(out)]) == 0
    first = (out / "fingerprints.csv").read_text()
    capsys.readouterr()
    assert main(["radiomap", "build", str(bag), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "fingerprints.csv" in err and "--overwrite" in err
    assert main(["radiomap", "build", str(bag), "--out", str(out), "--overwrite"]) == 0
    assert (out / "fingerprints.csv").read_text().count("\n") == first.count("\n")
    assert main(["radiomap", "build", str(bag), "--out", str(out / "params.yaml"), "--overwrite"]) == 2
    assert "not a directory" in capsys.readouterr().err


def test_radiomap_build_says_what_the_bags_lack(tmp_path, capsys):
    imu_only, no_truth = tmp_path / "imu.mcap", tmp_path / "notruth.mcap"
    _imu_bag(imu_only)
    _survey_bag(no_truth, truth=False)
    assert main(["radiomap", "build", str(imu_only), "--out", str(tmp_path / "a")]) == 2
    assert "hold no */wifi/scan messages" in capsys.readouterr().err
    assert main(["radiomap", "build", str(no_truth), "--out", str(tmp_path / "b")]) == 2
    assert "/alice: 9 scans, 0 outside the truth's time span, 9 without */ground_truth" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_output_into_a_closed_pipe_ends_quietly(monkeypatch, capsys):
    """``indoor-loc contract | head -1``: the reader goes away; no traceback, the shell's 141."""
    class ClosedPipe:
        def write(self, text: str) -> int:
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self) -> None:
            raise BrokenPipeError(32, "Broken pipe")

        def fileno(self) -> int:
            raise ValueError("not a real file")

    monkeypatch.setattr("sys.stdout", ClosedPipe())
    assert main(["contract"]) == 141
    assert "Traceback" not in capsys.readouterr().err


def test_the_bringup_example_plays_only_once_its_nodes_subscribe():
    """Started side by side, a node can take seconds longer than the player to come up on a busy
    machine; what is played before it subscribes never reaches it. The shipped example (and the
    launch file that mirrors it) hold the player until imu_node, wifi_fix_node and the recorder
    subscribe."""
    from indoor_loc.supervisor import load_config
    root = Path(__file__).resolve().parents[1]
    nodes = load_config(root / "config" / "bringup_example.yaml").nodes
    player = nodes[0]
    # the recorder refuses an existing output (a second run of the example): then nothing runs in vain
    assert [n.required for n in nodes if n.name == "recorder"] == [True]
    cmd = player.command()
    assert "--wait-for-subscribers" in cmd
    i = cmd.index("--min-subscribers")
    assert {"imu/data=2", "wifi/scan=2"} <= set(cmd[i + 1:cmd.index("--ros-args")])
    launch = (root / "launch" / "indoor_loc.launch.py").read_text()
    assert '"--wait-for-subscribers"' in launch and '"imu/data=2", "wifi/scan=2"' in launch


def test_import_ms_indoor_with_a_bad_option_leaves_no_directory(tmp_path, capsys):
    site = Path(__file__).parent / "data" / "ms_site"
    out = tmp_path / "o"
    assert main(["import", "ms-indoor", str(site), str(out), "--walks", "zzz"]) == 2
    assert "--walks: 'zzz' matches 0" in capsys.readouterr().err
    assert not out.exists()
    (tmp_path / "f").write_text("x")
    assert main(["import", "ms-indoor", str(site), str(tmp_path / "f")]) == 2
    assert "not a directory" in capsys.readouterr().err
