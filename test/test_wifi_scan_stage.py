"""WifiScanStage: topic input (schema + JSON), bad messages counted, interface scans through real
subprocesses (fake iw / nmcli scripts), offline replay of a bag, and the node over DDS."""
from __future__ import annotations

import dataclasses
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import String

from indoor_loc.errors import ConfigError
from msg_adapters.wifi_json import scan_from_json_msg, scan_to_json_msg
from msg_adapters.wifi_scan import scan_from_msg, scan_to_msg
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.wifi_scan_stage import IFACE_INPUT, WifiScanParams, WifiScanStage
from indoor_loc.wifi.iface import InterfaceScanner
from indoor_loc.wifi.normalize import NormalizeParams
from indoor_loc.wifi.types import WifiScan

DATA = Path(__file__).resolve().parent / "data" / "wifi"
T0 = 1_700_000_000_000_000_000


def _stage(**kw) -> WifiScanStage:
    return WifiScanStage(params_from_dict(WifiScanParams, kw), namespace="/alice")


def _scan(bssids, rssi, freq=None, ssid=None, stamp=T0) -> WifiScan:
    n = len(bssids)
    return WifiScan(stamp_ns=stamp, bssid=tuple(bssids), rssi_dbm=np.array(rssi, float),
                    freq_mhz=np.array(freq if freq is not None else [2412.0] * n, float),
                    ssid=tuple(ssid if ssid is not None else [f"n{i}" for i in range(n)]),
                    frame_id="phone/wifi_link", source="android")


def _script(tmp_path: Path, name: str, body: str) -> Path:
    p = tmp_path / name
    p.write_text("#!/bin/sh\n" + body)
    p.chmod(p.stat().st_mode | stat.S_IXUSR)
    return p


# ------------------------------------------------------------------------------------------------
# parameters
# ------------------------------------------------------------------------------------------------
def test_params_share_normalize_defaults_and_validate():
    p = WifiScanParams()
    assert p.normalize == NormalizeParams()
    from indoor_loc.params import param_docs
    docs = param_docs(WifiScanParams)
    for f in dataclasses.fields(NormalizeParams):
        assert docs[f"normalize.{f.name}"] == f.metadata["doc"]
    with pytest.raises(ConfigError, match="source"):
        params_from_dict(WifiScanParams, {"source": "iwlist"})
    with pytest.raises(ConfigError, match="scan_period_s"):
        params_from_dict(WifiScanParams, {"scan_period_s": 0.0})
    with pytest.raises(ConfigError, match="bands"):
        params_from_dict(WifiScanParams, {"normalize": {"bands": ["2.4", "60"]}})
    with pytest.raises(ConfigError, match="signal_mapping"):
        params_from_dict(WifiScanParams, {"signal_mapping": "linear"})


def test_config_yaml_matches_params():
    from indoor_loc.params import load_params_file, params_for_node
    path = Path(__file__).resolve().parents[1] / "config" / "wifi_scan_node.yaml"
    values = params_for_node(load_params_file(path), "wifi_scan_node", "/alice")
    assert set(values) == {f.name for f in dataclasses.fields(WifiScanParams)}
    assert params_from_dict(WifiScanParams, values) == WifiScanParams()
    text = path.read_text()
    for name in values:                              # every key is commented
        line = next(ln for ln in text.splitlines() if ln.strip().startswith(f"{name}:"))
        assert "#" in line, line


# ------------------------------------------------------------------------------------------------
# topic input
# ------------------------------------------------------------------------------------------------
def test_scan_raw_is_normalised_and_republished():
    st = _stage(**{"normalize.min_rssi_dbm": -90.0})
    raw = _scan(["00:11:22:33:44:55", "DA:A1:19:6B:22:01", "00:11:22:33:44:66", "00:11:22:33:44:77"],
                [-50.0, -40.0, -95.0, -60.0])
    outs = st.process("wifi/scan_raw", scan_to_msg(raw), T0 + 5)
    assert [t for t, _ in outs] == ["wifi/scan"]
    got = scan_from_msg(outs[0][1])
    assert got.bssid == ("00:11:22:33:44:55", "00:11:22:33:44:77")
    assert got.rssi_dbm.tolist() == [-50.0, -60.0]
    assert (got.stamp_ns, got.frame_id, got.source) == (T0, "phone/wifi_link", "android")
    d = st.extra_diagnostics()
    assert d["dropped.random_mac"] == "1" and d["dropped.weak"] == "1"
    assert d["scans.published"] == "1" and d["aps_per_scan.last"] == "2" and d["aps_per_scan.in_mean"] == "4.0"


def _bad_messages() -> dict[str, DiagnosticArray]:
    good = scan_to_msg(_scan(["00:11:22:33:44:55", "00:11:22:33:44:66"], [-50.0, -60.0]))
    wrong_schema = scan_to_msg(_scan(["00:11:22:33:44:55"], [-50.0]))
    wrong_schema.status[0].values[0].value = "wifi_scan.v0"
    empty = DiagnosticArray(status=[DiagnosticStatus(name="scan", values=[KeyValue(key="schema",
                                                                                   value="wifi_scan.v1")])])
    empty.header.stamp = scan_to_msg(_scan(["00:11:22:33:44:55"], [-50.0])).header.stamp
    dup = scan_to_msg(_scan(["00:11:22:33:44:55", "00:11:22:33:44:66"], [-50.0, -60.0]))
    dup.status[2].name = "00:11:22:33:44:55"
    nan = scan_to_msg(_scan(["00:11:22:33:44:55"], [-50.0]))
    nan.status[1].values[0].value = "nan"
    hot = scan_to_msg(_scan(["00:11:22:33:44:55"], [-50.0]))
    hot.status[1].values[0].value = "12.0"
    return {"ok": good, "schema_version": wrong_schema, "empty_scan": empty, "duplicate_bssid": dup,
            "nan": nan, "rssi_range": hot}


def test_bad_messages_are_counted_and_dropped():
    st = _stage()
    published = 0
    for reason, msg in _bad_messages().items():
        outs = st.process("wifi/scan_raw", msg, T0)
        published += len(outs)
        if reason != "ok":
            assert outs == [] and st.diag.rejected[reason] == 1, reason
    for text in ("{not json", '{"type": "rssi"}', '[{"ssid": "no mac"}]'):
        assert st.process("wifi/scan_json", String(data=text), T0) == []
    assert published == 1
    assert st.diag.rejected["json"] == 3
    summary = st.diag.summary()
    assert summary["rejected.total"] == "8" and summary["in.wifi/scan_raw.count"] == "6"


def test_scan_json_topic_cabot_and_receive_time():
    st = _stage()
    # received 1 s after the JSON's own timestamp (a stamp more than time.max_future_s ahead of the
    # node's clock would be rejected)
    outs = st.process("wifi/scan_json", String(data=(DATA / "cabot_esp32.json").read_text()), T0 + 201 * 10**9)
    got = scan_from_msg(outs[0][1])
    assert got.stamp_ns == 1_700_000_200_500_000_000                 # the JSON's own timestamp
    assert got.as_dict() == {"00:1a:2b:3c:4d:5e": -69.0, "3c:37:86:5e:a1:10": -52.0}
    assert got.frame_id == "alice/wifi_link" and got.source == "json"
    assert st.extra_diagnostics()["dropped.duplicate"] == "1"
    later = 1_700_000_300_000_000_007          # received after the first scan's own stamp (else: stamp_backwards)
    outs = st.process("wifi/scan_json", String(data=(DATA / "variants_list.json").read_text()), later)
    got = scan_from_msg(outs[0][1])
    assert got.stamp_ns == later and len(got) == 3                   # no timestamp: receive time
    assert st.extra_diagnostics()["entries_skipped"] == "2"


def test_json_adapter_round_trip():
    scan = _scan(["00:11:22:33:44:55", "00:11:22:33:44:66"], [-50.25, -60.0], [2412.0, 5955.0], ["a:b", ""])
    back = scan_from_json_msg(scan_to_json_msg(scan))
    assert back.bssid == scan.bssid and back.ssid == scan.ssid and back.stamp_ns == scan.stamp_ns
    assert back.rssi_dbm.tolist() == scan.rssi_dbm.tolist() and back.freq_mhz.tolist() == scan.freq_mhz.tolist()
    assert (back.frame_id, back.source) == (scan.frame_id, scan.source)


def test_filtered_to_empty_is_not_published():
    st = _stage(**{"normalize.ssid_allow": ["corp-*"]})
    assert st.process("wifi/scan_raw", scan_to_msg(_scan(["00:11:22:33:44:55"], [-50.0])), T0) == []
    d = st.extra_diagnostics()
    assert d["scans.empty"] == "1" and d["dropped.ssid_not_allowed"] == "1" and st.diag.rejected == {}


# ------------------------------------------------------------------------------------------------
# interface scans through real subprocesses
# ------------------------------------------------------------------------------------------------
def test_iw_interface_mode_with_fake_command(tmp_path):
    fake = _script(tmp_path, "iw", f'[ "$2" = wlan7 ] || exit 3\ncat "{DATA / "iw_scan_office.txt"}"\n')
    st = _stage(source="iw", interface="wlan7", iw_command=f"{fake} dev {{interface}} scan")
    assert st.inputs() == []                                  # no subscriptions in interface mode
    attempt = st.acquire(lambda: T0)
    assert attempt.error is None and attempt.stamp_ns == T0 and not attempt.fallback
    outs = st.process(IFACE_INPUT, attempt, attempt.stamp_ns)
    got = scan_from_msg(outs[0][1])
    assert got.bssid == ("3c:37:86:5e:a1:10", "3c:37:86:5e:a1:14", "00:1a:2b:3c:4d:5e", "00:1a:2b:3c:4d:5f",
                         "70:f0:96:d2:e0:62")
    assert got.age_ms.tolist() == [24.0, 28.0, 112.0, 96.0, 140.0]
    assert (got.stamp_ns, got.frame_id, got.source) == (T0, "alice/wifi_link", "iw")
    d = st.extra_diagnostics()
    assert d["dropped.random_mac"] == "1" and d["iface.mode"] == "scan" and d["iface.last_error"] == ""


def test_iw_permission_error_falls_back_to_scan_dump(tmp_path):
    body = (f'if [ "$4" = dump ]; then cat "{DATA / "iw6_scan_6ghz.txt"}"; exit 0; fi\n'
            'echo "command failed: Operation not permitted (-1)" >&2\nexit 255\n')
    fake = _script(tmp_path, "iw", body)
    st = _stage(source="iw", iw_command=f"{fake} dev {{interface}} scan", **{"normalize.max_age_ms": 10000.0})
    a = st.acquire(lambda: T0)
    assert a.fallback and a.error is None and a.command[-1] == "dump"
    got = scan_from_msg(st.process(IFACE_INPUT, a, a.stamp_ns)[0][1])
    assert got.source == "iw-dump" and "8c:3b:ad:10:20:41" not in got.bssid      # 31 s old: stale
    d = st.extra_diagnostics()
    assert d["iface.mode"] == "scan dump (fallback)" and "CAP_NET_ADMIN" in d["iface.fallback_reason"]
    assert d["dropped.stale"] == "1"
    # without the fallback the failure is a counted rejection whose message says what to do
    st2 = _stage(source="iw", iw_command=f"{fake} dev {{interface}} scan", iw_dump_fallback=False)
    a2 = st2.acquire(lambda: T0)
    assert st2.process(IFACE_INPUT, a2, T0) == []
    assert st2.diag.rejected["scan_permission"] == 1 and "scan dump" in st2.diag.last_error


def test_scan_timeout_kills_the_command_and_keeps_complete_entries(tmp_path):
    slow = _script(tmp_path, "slow_iw", f'cat "{DATA / "iw_scan_truncated.txt"}"\nsleep 30\n')
    st = _stage(source="iw", iw_command=str(slow), scan_timeout_s=1.0)
    t = time.monotonic()
    a = st.acquire(time.time_ns)
    assert time.monotonic() - t < 5.0                          # sleep (a child of the shell) was killed too
    assert a.error is None and a.result.truncated
    got = scan_from_msg(st.process(IFACE_INPUT, a, a.stamp_ns)[0][1])
    assert len(got) == 3 and st.extra_diagnostics()["scans.truncated"] == "1"
    silent = _script(tmp_path, "silent_iw", "sleep 30\n")
    st2 = _stage(source="iw", iw_command=str(silent), scan_timeout_s=0.5)
    st2.process(IFACE_INPUT, st2.acquire(time.time_ns), T0)
    assert st2.diag.rejected["scan_timeout"] == 1


def test_missing_tool_and_other_failures_are_reported(tmp_path):
    st = _stage(source="iw", iw_command=str(tmp_path / "no-such-iw"))
    st.process(IFACE_INPUT, st.acquire(lambda: T0), T0)
    assert st.diag.rejected["scan_not_found"] == 1
    down = _script(tmp_path, "down", 'echo "command failed: Network is down (-100)" >&2\nexit 156\n')
    st = _stage(source="iw", iw_command=str(down))
    st.process(IFACE_INPUT, st.acquire(lambda: T0), T0)
    assert st.diag.rejected["scan_down"] == 1 and "ip link set" in st.diag.last_error
    junk = _script(tmp_path, "junk", "echo hello\n")
    st = _stage(source="iw", iw_command=str(junk))
    st.process(IFACE_INPUT, st.acquire(lambda: T0), T0)
    assert st.diag.rejected["scan_parse"] == 1


def test_nmcli_interface_mode(tmp_path):
    fake = _script(tmp_path, "nmcli", f'cat "{DATA / "nmcli_terse_ru.txt"}"\n')
    st = _stage(source="nmcli", nmcli_command=str(fake), signal_mapping="half")
    a = st.acquire(lambda: T0)
    got = scan_from_msg(st.process(IFACE_INPUT, a, a.stamp_ns)[0][1])
    assert got.source == "nmcli" and len(got) == 7
    assert got.as_dict()["3c:37:86:5e:a1:10"] == 87 / 2 - 100
    assert InterfaceScanner("nmcli", "wlp2s0").command[-4:] == ["ifname", "wlp2s0", "--rescan", "auto"]


# ------------------------------------------------------------------------------------------------
# bags: offline replay
# ------------------------------------------------------------------------------------------------
def test_offline_run_over_a_bag(tmp_path):
    from indoor_loc.bag import BagWriter, read_bag
    from indoor_loc.pipeline.offline import run_offline
    bag = tmp_path / "in.mcap"
    with BagWriter(bag) as w:
        for i in range(3):
            raw = _scan(["00:11:22:33:44:55", "02:00:00:00:00:01"], [-50.0 - i, -40.0], stamp=T0 + i * 10**9)
            w.write("/walk01/wifi/scan_raw", scan_to_msg(raw), T0 + i * 10**9)
        # logged (received) after the JSON's own timestamp, 1_700_000_123.25 s
        w.write("/walk01/wifi/scan_json", String(data=(DATA / "cabot_iw.json").read_text()), T0 + 124 * 10**9)
    out = tmp_path / "out.mcap"
    summary = run_offline([bag], out, nodes=["wifi_scan"], progress=False)
    scans = [scan_from_msg(m.msg) for m in read_bag([out], topics=["/walk01/wifi/scan"])]
    assert [s.as_dict().get("00:11:22:33:44:55") for s in scans[:3]] == [-50.0, -51.0, -52.0]
    assert all("02:00:00:00:00:01" not in s.bssid for s in scans)
    assert len(scans) == 4 and len(scans[3]) == 4
    assert summary.per_stage["/walk01/wifi_scan_node"]["rejected.total"] == "0"


# ------------------------------------------------------------------------------------------------
# the node as a real process over DDS
# ------------------------------------------------------------------------------------------------
@pytest.mark.timeout(120)      # above the sum of the condition deadlines, not an expected duration
def test_node_process_publishes_interface_scans(ros_domain, tmp_path):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from indoor_loc.nodes.base import qos_profile
    from indoor_loc.contract import Qos

    fake = _script(tmp_path, "iw", f'cat "{DATA / "iw6_scan_6ghz.txt"}"\n')
    node_proc = subprocess.Popen(
        [sys.executable, "-m", "indoor_loc.nodes.wifi_scan_node", "--ros-args", "-r", "__ns:=/bob",
         "-p", "source:=iw", "-p", f"iw_command:={fake}", "-p", "scan_period_s:=0.5"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=os.environ.copy())
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    got: list[DiagnosticArray] = []
    diags: list[DiagnosticArray] = []
    try:
        node = rclpy.create_node("wifi_scan_listener", context=ctx)
        node.create_subscription(DiagnosticArray, "/bob/wifi/scan", got.append, qos_profile(Qos.RELIABLE))
        node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        end = time.monotonic() + 60
        while time.monotonic() < end and (len(got) < 2 or not diags) and node_proc.poll() is None:
            ex.spin_once(timeout_sec=0.2)
        ex.shutdown()
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
        node_proc.terminate()
        log, _ = node_proc.communicate(timeout=15)
    assert len(got) >= 2, log
    scan = scan_from_msg(got[0])
    assert scan.frame_id == "bob/wifi_link" and scan.source == "iw" and len(scan) == 5
    assert scan_from_msg(got[1]).stamp_ns > scan.stamp_ns
    values = {kv.key: kv.value for kv in diags[-1].status[0].values}
    assert diags[-1].status[0].name == "/bob/wifi_scan_node"
    assert values["source"] == "iw" and values["dropped.duplicate"] != "0"


# ------------------------------------------------------------------------------------------------
# indoor-loc wifi scan | parse
# ------------------------------------------------------------------------------------------------
def test_cli_parse_and_scan(tmp_path, capsys):
    from indoor_loc.cli import main
    assert main(["wifi", "parse", str(DATA / "iw_scan_truncated.txt"), "--format", "iw"]) == 0
    out, err = capsys.readouterr()
    assert out.splitlines()[1].split()[:3] == ["3c:37:86:5e:a1:10", "-48.0", "2412.0"]
    assert "3 access points kept of 3 read" in err and "truncated" in err
    assert main(["wifi", "parse", str(DATA / "nmcli_terse.txt"), "--format", "iw"]) == 2      # ParseError
    assert "no 'BSS" in capsys.readouterr().err
    fake = _script(tmp_path, "iw", f'cat "{DATA / "iw_scan_office.txt"}"\n')
    assert main(["wifi", "scan", "--iface", "wlan9", "--command", f"{fake} dev {{interface}} scan",
                 "--keep-random-macs", "--json"]) == 0
    out, err = capsys.readouterr()
    assert len(parse_json_text(out).bssid) == 6 and "6 access points kept of 6" in err
    assert main(["wifi", "scan", "--command", str(tmp_path / "missing")]) == 3
    assert "not_found" in capsys.readouterr().err


def parse_json_text(text: str) -> WifiScan:
    from indoor_loc.wifi.parsers import parse_json
    return parse_json(text).scan


def test_scan_stamps_going_backwards_are_rejected_not_republished():
    st = _stage()
    ap = ["00:11:22:33:44:55", "00:11:22:33:44:66"]
    assert len(st.process("wifi/scan_raw", scan_to_msg(_scan(ap, [-50.0, -60.0], stamp=T0 + 10)), T0)) == 1
    assert st.process("wifi/scan_raw", scan_to_msg(_scan(ap, [-50.0, -60.0], stamp=T0 + 5)), T0) == []
    assert dict(st.diag.rejected) == {"stamp_backwards": 1} and st.scans_published == 1
    assert len(st.process("wifi/scan_raw", scan_to_msg(_scan(ap, [-51.0, -61.0], stamp=T0 + 20)), T0)) == 1
