"""wifi_fix_node fits its radio map in the background: it answers requests and reports "fitting" at
WARN meanwhile, keeps the scans received and locates them in order afterwards (exactly as the
synchronous stage does), reports a failed fit as an ERROR and keeps running."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rcl_interfaces.srv import GetParameters
from rclpy.event_handler import PublisherEventCallbacks

from helpers_dds import child_env, python_peer, ros_node, spin_until
from indoor_loc.contract import Qos
from indoor_loc.errors import MapError
from indoor_loc.nodes.base import qos_profile
from indoor_loc.nodes.wifi_fix_node import WifiFixNode
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.wifi_fix_stage import WifiFixParams, WifiFixStage
from indoor_loc.wifi.radiomap import save_radiomap
from msg_adapters.diagnostics import diagnostics_from_msg
from msg_adapters.pose import pose_from_msg
from msg_adapters.wifi_scan import scan_to_msg
from test_wifi_fix_stage import grid_map, scan_at

# a bound for a hung test, above the sum of a test's condition deadlines (which a loaded machine may
# use up one after another), not an expected duration
pytestmark = pytest.mark.timeout(300)
S = 1_000_000_000
NAME = "/alice/wifi_fix_node"


def _scans(n: int, first_s: int = 5) -> list:
    rng = np.random.default_rng(3)
    return [scan_to_msg(scan_at(rng.uniform(0.5, 9.5, 2), (first_s + i) * S)) for i in range(n)]


def _reference(map_dir, scans) -> list:
    """The fixes of the synchronous stage (offline ``indoor-loc run``) for these scans."""
    st = WifiFixStage(params_from_dict(WifiFixParams, {"radiomap": str(map_dir)}), namespace="/alice")
    return [m for i, s in enumerate(scans) for _, m in st.process("wifi/scan", s, i)]


def _same_fix(a: PoseWithCovarianceStamped, b: PoseWithCovarianceStamped) -> bool:
    pa, pb = pose_from_msg(a), pose_from_msg(b)
    return pa.stamp_ns == pb.stamp_ns and np.array_equal(pa.xy, pb.xy) and \
        list(a.pose.covariance) == list(b.pose.covariance)


class _Probe:
    """The test's side of the DDS link: scans out, fixes and the node's diagnostics in."""

    def __init__(self, node) -> None:
        self.fixes: list[PoseWithCovarianceStamped] = []
        self.diags: list = []
        self.matched: list[int] = []
        self.pub = node.create_publisher(scan_to_msg(scan_at([1, 1])).__class__, "/alice/wifi/scan",
                                         qos_profile(Qos.RELIABLE), event_callbacks=PublisherEventCallbacks(
                                             matched=lambda st: self.matched.append(st.current_count)))
        node.create_subscription(PoseWithCovarianceStamped, "/alice/wifi/fix", self.fixes.append,
                                 qos_profile(Qos.RELIABLE))
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, qos_profile(Qos.RELIABLE))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        d = diagnostics_from_msg(msg)
        if NAME in d:
            self.diags.append(d[NAME])

    def last(self):
        return self.diags[-1] if self.diags else None


def _open_gate(gate, text: str) -> None:
    """Let the held fit run (``go``) or fail (``fail``): the file appears with its text in one step
    (written aside, then renamed), so the node never reads it half written."""
    aside = gate.with_name(gate.name + ".new")
    aside.write_text(text)
    aside.replace(gate)


def _start(tmp_path, ros_domain):
    map_dir = save_radiomap(grid_map(), tmp_path / "rm")
    gate = tmp_path / "gate"
    peer = python_peer("gated_wifi_fix_node.py", "--ros-args", "-r", "__ns:=/alice", "-p", f"radiomap:={map_dir}",
                       env=child_env(GATE=str(gate)))
    return map_dir, gate, peer


def test_scans_sent_while_fitting_are_located_afterwards(tmp_path, ros_domain):
    map_dir, gate, peer = _start(tmp_path, ros_domain)
    scans = _scans(6)
    try:
        with ros_node("probe") as (node, ex):
            probe = _Probe(node)
            # the node is up and says it is fitting, at WARN, while the fit is held
            assert spin_until(ex, lambda: bool(probe.matched) and probe.matched[-1] > 0 and probe.last() is not None,
                              60), peer.output()
            d = probe.last()
            assert d.level == 1 and d.message.startswith("fitting the radio map (36 scans"), d
            assert d.values["fit.state"] == "fitting" and d.values["fit.map_scans"] == "36"
            # ... and answers a parameter request meanwhile
            client = node.create_client(GetParameters, f"{NAME}/get_parameters")
            assert client.wait_for_service(timeout_sec=30)
            fut = client.call_async(GetParameters.Request(names=["method", "radiomap"]))
            assert spin_until(ex, fut.done, 30)
            assert [v.string_value for v in fut.result().values] == ["wknn", str(map_dir)]

            for s in scans:
                probe.pub.publish(s)
            assert spin_until(ex, lambda: probe.last().values.get("fit.queued") == "6", 30), probe.last()
            assert probe.last().level == 1 and "6 scan(s) queued" in probe.last().message
            assert probe.fixes == []                                 # nothing located before the fit
            assert not gate.exists() and peer.proc.poll() is None

            _open_gate(gate, "go")                                   # the fit may now run
            assert spin_until(ex, lambda: len(probe.fixes) == 6, 60), peer.output()
            want = _reference(map_dir, scans)
            assert len(want) == 6 and all(_same_fix(a, b) for a, b in zip(probe.fixes, want))
            # later scans are located at once; health is back to OK
            probe.pub.publish(_scans(1, first_s=20)[0])
            assert spin_until(ex, lambda: len(probe.fixes) == 7, 30)
            assert spin_until(ex, lambda: probe.last().values["fixes"] == "7", 30)
            d = probe.last()
            assert d.level == 0 and "fit.state" not in d.values and d.values["fit.located_late"] == "6"
            assert d.values["rejected.total"] == "0" and d.values["map.scans"] == "36"
        # the node's log reaches us through a pipe, its messages through DDS: either can come first
        assert peer.wait_seen(r"radio map fitted in .*located the 6 scan\(s\)", 30), peer.output()
    finally:
        peer.stop()


def test_failed_fit_is_an_error_and_the_node_keeps_running(tmp_path, ros_domain):
    map_dir, gate, peer = _start(tmp_path, ros_domain)
    try:
        with ros_node("probe") as (node, ex):
            probe = _Probe(node)
            assert spin_until(ex, lambda: bool(probe.matched) and probe.matched[-1] > 0 and probe.last() is not None,
                              60), peer.output()
            for s in _scans(3):
                probe.pub.publish(s)
            assert spin_until(ex, lambda: probe.last().values.get("fit.queued") == "3", 30), probe.last()
            _open_gate(gate, "fail")
            assert spin_until(ex, lambda: probe.last().level == 2, 30), probe.last()
            d = probe.last()
            assert "fitting the radio map (36 scans) failed: MapError" in d.message and "test gate" in d.message
            assert d.values["rejected.fit_failed"] == "3"              # the queued scans: dropped, counted
            n = len(probe.diags)
            probe.pub.publish(_scans(1, first_s=30)[0])
            assert spin_until(ex, lambda: probe.last().values.get("rejected.fit_failed") == "4"
                              and len(probe.diags) > n, 30)
            assert probe.last().level == 2 and probe.fixes == []
            assert peer.proc.poll() is None, "the node died on a failed fit"
        assert peer.wait_seen(r"failed: MapError", 30), peer.output()
        assert "Traceback" not in peer.output()
    finally:
        peer.stop()


# -- the stage's steps and a live map reload, in-process --------------------------------------------

def test_deferred_fit_equals_the_synchronous_stage_and_overflow_is_counted(tmp_path):
    map_dir = save_radiomap(grid_map(), tmp_path / "rm")
    params = params_from_dict(WifiFixParams, {"radiomap": str(map_dir)})
    scans = _scans(5)
    st = WifiFixStage(params, namespace="/alice", fit_now=False, pending_max=3)
    assert st.waiting_for_fit() and st.extra_diagnostics()["fit.queued"] == "0"
    assert "error" not in st.extra_diagnostics()
    assert all(st.process("wifi/scan", s, i) == [] for i, s in enumerate(scans))
    assert len(st.pending) == 3 and st.diag.rejected == {"fit_queue_full": 2}       # the two oldest dropped
    outs = st.end_fit(st.fit_job, st.fit_positioner(st.fitting))
    want = _reference(map_dir, scans)[2:]
    assert len(outs) == 3 and all(_same_fix(m, w) for (_, m), w in zip(outs, want))
    assert st.diag.published["wifi/fix"] == 3 and st.extra_diagnostics()["fit.located_late"] == "3"

    # a superseded job is ignored; input ending during a fit counts the queued scans
    st2 = WifiFixStage(params, namespace="/alice", fit_now=False)
    old = st2.fit_job
    st2.begin_fit(grid_map())
    assert st2.end_fit(old, st2.fit_positioner(grid_map())) == [] and st2.waiting_for_fit()
    st2.process("wifi/scan", scans[0], 0)
    assert st2.run_finish() == [] and st2.diag.rejected == {"fit_unfinished": 1}


def test_set_radio_map_refits_without_blocking_the_executor(tmp_path, ros_domain, monkeypatch):
    map_dir = save_radiomap(grid_map(), tmp_path / "rm")
    gate = threading.Event()
    real = WifiFixStage.fit_positioner

    def gated(self, rm):
        if rm.n_scans != 36:          # the new map waits for the gate
            assert gate.wait(120)
        return real(self, rm)
    monkeypatch.setattr(WifiFixStage, "fit_positioner", gated)
    with ros_node("probe") as (probe, ex):
        from rclpy.parameter import Parameter
        node = WifiFixNode(context=probe.context, namespace="/alice",
                           parameter_overrides=[Parameter("radiomap", value=str(map_dir))])
        ex.add_node(node)
        try:
            assert spin_until(ex, lambda: node.stage.positioner is not None, 40)
            first = node.stage.positioner
            half = grid_map()
            half = type(half)(positions=half.positions[::2], bssids=half.bssids, rssi_dbm=half.rssi_dbm[::2],
                              freq_mhz=half.freq_mhz)
            ticks: list[float] = []
            probe.create_timer(0.05, lambda: ticks.append(time.monotonic()))
            node.set_radio_map(half)
            assert spin_until(ex, lambda: len(ticks) >= 10, 20)          # the executor keeps running
            assert node.stage.positioner is first and not node.stage.waiting_for_fit()
            d = diagnostics_from_msg(node.diagnostics_msg(1))[NAME]
            assert d.level == 0 and d.values["fit.state"] == "fitting" and d.values["fit.map_scans"] == "18"
            outs = node.stage.process("wifi/scan", _scans(1)[0], 1)     # the previous map still answers
            assert [t for t, _ in outs] == ["wifi/fix"] and node.stage.extra_diagnostics()["map.scans"] == "36"
            gate.set()
            assert spin_until(ex, lambda: node.stage.extra_diagnostics().get("map.scans") == "18", 40)
            assert node.stage.positioner is not first and node.stage.fitting is None
        finally:
            gate.set()
            ex.remove_node(node)
            node.destroy_node()


def test_a_map_that_cannot_be_fitted_fails_the_stage_cleanly(tmp_path):
    st = WifiFixStage(params_from_dict(WifiFixParams, {}), namespace="/alice", fit_now=False)
    job = st.begin_fit(grid_map())
    st.process("wifi/scan", _scans(1)[0], 1)
    st.fit_failed(job, MapError("broken"))
    assert st.extra_diagnostics()["error"] == "fitting the radio map (36 scans) failed: MapError: broken"
    assert st.diag.rejected == {"fit_failed": 1}


def test_a_second_node_loads_the_saved_fit_and_logs_it(tmp_path, ros_domain, monkeypatch):
    """The first node on a map fits and saves (fit_cache); the next one on the same map and params loads
    the saved fit (no fit), says so in its log, and gives the fixes of the first."""
    from rclpy.parameter import Parameter
    from indoor_loc.pipeline import wifi_fix_stage
    from indoor_loc.wifi.powed_knn import PowedKnn
    map_dir = save_radiomap(grid_map(), tmp_path / "rm")
    scans = _scans(5)
    logged: list[str] = []
    logs: list = []
    real_fit = wifi_fix_stage.fit_positioner

    def spy(pos, rm, store, log, **kw):                 # what the store tells the node's log
        logs.append(log)
        return real_fit(pos, rm, store, lambda level, text: (logged.append(text), log(level, text)), **kw)
    monkeypatch.setattr(wifi_fix_stage, "fit_positioner", spy)

    def start(probe, ex):
        node = WifiFixNode(context=probe.context, namespace="/alice", parameter_overrides=[
            Parameter("radiomap", value=str(map_dir)), Parameter("method", value="powed")])
        ex.add_node(node)
        return node

    fixes = []
    for run in range(2):
        with ros_node("probe") as (probe, ex):
            node = start(probe, ex)
            try:
                assert spin_until(ex, lambda node=node: node.stage.positioner is not None, 60)
                assert logs[-1] is node.stage.fit_log                  # the node's logger, not stderr
                fixes.append([m for i, s in enumerate(scans) for _, m in node.stage.process("wifi/scan", s, i)])
            finally:
                ex.remove_node(node)
                node.destroy_node()
        if run == 0:
            assert any(t.startswith("saved the fitted radio map") for t in logged), logged
            assert len(list((map_dir / "fit_cache").glob("wifi_fit_*.fit"))) == 1
            logged.clear()
            monkeypatch.setattr(PowedKnn, "fit", lambda self, rm: pytest.fail("fitted instead of loaded"))
    assert len(logged) == 1 and logged[0].startswith("loaded the fitted radio map from " + str(map_dir / "fit_cache"))
    assert len(fixes[0]) == len(scans) and all(_same_fix(a, b) for a, b in zip(fixes[0], fixes[1]))
