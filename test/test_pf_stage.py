"""PfStage (tll_pf): contract messages in, pf/* out; unknown odom rotation, bad input, time jumps."""
from __future__ import annotations

import math

import numpy as np
import pytest

from indoor_loc.errors import ConfigError
from indoor_loc.graph import build_graph, save_graph
from indoor_loc.graph.tll import Transitions, cache_path, save_transitions, transition_table
from indoor_loc.measurements import Fix
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.pf_stage import PfStage, PfStageParams
from msg_adapters.odom import odom_to_msg
from msg_adapters.path import path_from_msg
from msg_adapters.pose import fix_from_msg, fix_to_msg, pose_from_msg, pose_to_msg

STEP = 0.65


@pytest.fixture
def graph_file(tmp_path):
    # a 20 x 10 m rectangle of corridors with a 4 m stub (room door) in the middle of the long side
    xy = np.array([[2, 2], [12, 2], [22, 2], [22, 12], [2, 12], [12, -2]], float)
    g = build_graph(range(6), xy, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0), (1, 5)])
    return save_graph(g, tmp_path / "rect.graph.yaml")


def _walk(rng: np.random.Generator, n: int = 90):
    """Clockwise... anticlockwise around the rectangle, 2 steps per 1 s interval; PDR in an odom
    frame rotated by an unknown 1 rad with drifting heading; fixes (sigma 2 m) every 4th interval."""
    t = np.arange(n) * 1_000_000_000 + 5_000_000_000
    pos, yaw = np.array([2.0, 2.0]), 0.0
    true_xy, yaws = [], []
    walked = 0.0
    for _ in range(n):
        seg = walked % 60.0
        yaw = 0.0 if seg < 20 else (math.pi / 2 if seg < 30 else (math.pi if seg < 50 else -math.pi / 2))
        pos = pos + 2 * STEP * np.array([math.cos(yaw), math.sin(yaw)])
        walked += 2 * STEP
        true_xy.append(pos.copy())
        yaws.append(yaw)
    odom_yaw = np.array(yaws) + 1.0 + np.cumsum(rng.normal(0, 0.01, n))
    ox = oy = 0.0
    odoms, fixes = [], {}
    for i in range(n):
        ox += 2 * STEP * math.cos(odom_yaw[i])
        oy += 2 * STEP * math.sin(odom_yaw[i])
        odoms.append(odom_to_msg(int(t[i]), "u/odom", "u/base_link", ox, oy, odom_yaw[i], np.eye(3) * 0.1, 1.3, 0.0))
        if i % 4 == 0:
            fixes[i] = fix_to_msg(Fix(int(t[i]) + 1000, true_xy[i] + rng.normal(0, 2.0, 2), np.eye(2) * 4.0))
    return t, np.array(true_xy), odoms, fixes


def _stage(graph_file, **kw) -> PfStage:
    return PfStage(params_from_dict(PfStageParams, {"graph_file": str(graph_file), "n_particles": 600, **kw}))



def _late_median_error(outs, t, truth) -> float:
    """Median error (m) of the `pf/pose` outputs stamped within the last 30 truth intervals."""
    poses = [pose_from_msg(m) for tp, m in outs if tp == "pf/pose"]
    stamps = np.array([p.stamp_ns for p in poses])
    est = np.array([p.xy for p in poses])
    late = stamps >= t[-30]
    idx = np.searchsorted(t, stamps[late], side="right") - 1        # the truth at the pose's time, not the next
    return float(np.median(np.hypot(*(est[late] - truth[np.clip(idx, 0, len(t) - 1)]).T)))

def test_tracks_a_walk_with_unknown_odom_rotation_and_smooths_on_the_graph(graph_file):
    rng = np.random.default_rng(7)
    t, truth, odoms, fixes = _walk(rng)
    # these fixes are drawn from exactly their covariance and the PDR heading drifts by 0.01 rad per
    # step: no fix calibration and a sharp heading likelihood (the defaults are PUTMC's)
    st = _stage(graph_file, fix_cov_scale=1.0, fix_sigma_extra_m=0.0, heading_sigma_rad=0.35)
    assert cache_path(graph_file).exists()                      # TLL table cached beside the map
    outs = []
    for i, od in enumerate(odoms):
        if i in fixes:
            outs += st.process("wifi/fix", fixes[i], 0)
        outs += st.process("pdr/odom", od, 0)
    outs += st.finish()
    assert st.diag.rejected.total() == 0
    topics = [o[0] for o in outs]
    assert topics.count("map/graph") == 1 and "pf/particles" in topics
    # after the first lap the filter has locked on: its error at the last 30 intervals is well below
    # that of the fixes it is given there (sigma 2 m per axis: a median of 2.35 m expected)
    late = [i for i in fixes if t[i] >= t[-30]]
    fix_err = np.median([np.hypot(*(fix_from_msg(fixes[i]).xy - truth[i])) for i in late])
    pf_err = _late_median_error(outs, t, truth)
    assert pf_err < 0.8 * fix_err, (pf_err, fix_err)
    ts, xy, _ = path_from_msg([m for tp, m in outs if tp == "pf/path"][-1])
    assert len(ts) > 50
    assert st.graph.project(xy)[2].max() < 1e-6                 # every smoothed pose on the graph
    # a second stage with the cache present starts from it
    assert _stage(graph_file).cache_hit


def test_bad_messages_are_counted_and_time_jumps_reset(graph_file):
    rng = np.random.default_rng(1)
    t, truth, odoms, fixes = _walk(rng, n=20)
    st = _stage(graph_file)
    for i, od in enumerate(odoms):
        if i in fixes:
            st.process("wifi/fix", fixes[i], 0)
        st.process("pdr/odom", od, 0)
    st.process("pdr/odom", odoms[5], 0)
    # odoms[5] is 14 s older than the newest: held, a straggler or the first of a new pass
    assert st.diag.time_jumps == 0 and st.tracker.initialised
    st.process("pdr/odom", odoms[6], 0)
    st.process("pdr/odom", odoms[7], 0)
    # three in step (time.jump_confirm): a bag loop -> the filter reset, nothing rejected
    assert st.diag.time_jumps == 1
    assert not st.tracker.initialised
    bad = fix_to_msg(Fix(int(t[-1]), np.array([1.0, 1.0]), np.eye(2)))
    bad.pose.pose.position.x = float("nan")
    assert st.process("wifi/fix", bad, 0) == []
    assert st.diag.rejected.total() == 1


def test_initialpose_and_global_localization(graph_file):
    st = _stage(graph_file)
    outs = st.process("initialpose", pose_to_msg(1_000, np.array([22.0, 7.0]), 0.0, np.eye(2) * 0.1), 0)
    p = pose_from_msg([m for tp, m in outs if tp == "pf/pose"][0])
    assert np.hypot(*(p.xy - [22.0, 7.0])) < 1.5
    outs = st.global_localization(2_000)
    p = pose_from_msg([m for tp, m in outs if tp == "pf/pose"][0])
    assert np.trace(p.cov_xy) > 20.0                            # spread over the whole rectangle


def test_invalid_parameters(graph_file, tmp_path):
    st = PfStage(params_from_dict(PfStageParams, {}))          # no graph: starts, rejects every message
    assert st.process("wifi/fix", fix_to_msg(Fix(1, np.array([1.0, 1.0]), np.eye(2))), 0) == []
    assert st.diag.rejected["no_graph"] == 1
    with pytest.raises(ConfigError, match="rule"):
        params_from_dict(PfStageParams, {"graph_file": str(graph_file), "rule": "nope"})
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: indoor_loc.graph\nversion: 1\nnodes: [[0, 0, 0]]\nlinks: []\n")
    with pytest.raises(ConfigError, match="node 0 is on no link"):
        PfStage(params_from_dict(PfStageParams, {"graph_file": str(bad)}))


def test_scan_update_from_wifi_scan_messages(graph_file, tmp_path):
    """wifi_update: scan — the filter starts from the first scan and tracks with PDR and scans."""
    from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap, save_radiomap
    from indoor_loc.wifi.types import WifiScan
    from msg_adapters.wifi_scan import scan_to_msg

    aps = np.array([[0.0, -4.0], [24.0, 0.0], [12.0, 14.0], [0.0, 14.0], [24.0, 14.0], [12.0, 6.0]])
    bssids = tuple(f"02:00:00:00:01:{i:02x}" for i in range(len(aps)))
    rng = np.random.default_rng(2)

    def scan(xy, stamp):
        d = np.hypot(*(aps - xy).T)
        return WifiScan(stamp, bssids, -35.0 - 25.0 * np.log10(d + 1.0) + rng.normal(0, 2.0, len(aps)),
                        np.full(len(aps), 2412.0))

    g_pts = np.concatenate([np.column_stack([np.linspace(2, 22, 14), np.full(14, 2.0)]),
                            np.column_stack([np.full(7, 22.0), np.linspace(2, 12, 7)]),
                            np.column_stack([np.linspace(2, 22, 14), np.full(14, 12.0)]),
                            np.column_stack([np.full(7, 2.0), np.linspace(2, 12, 7)]),
                            np.column_stack([np.full(3, 12.0), np.linspace(-2, 2, 3)])])
    rm = add_fingerprints(empty_radiomap(), g_pts, [scan(p, 0) for p in g_pts], "survey")
    rm_dir = save_radiomap(rm, tmp_path / "rm")
    t, truth, odoms, _ = _walk(np.random.default_rng(7))
    st = _stage(graph_file, wifi_update="scan", radiomap=str(rm_dir), **{"scan.sigma_db": 4.0})
    assert [p.topic for p in st.inputs()][1] == "wifi/scan"
    outs = []
    for i, od in enumerate(odoms):
        if i % 3 == 0:
            outs += st.process("wifi/scan", scan_to_msg(scan(truth[i], int(t[i]) + 1000)), 0)
        outs += st.process("pdr/odom", od, 0)
    assert st.diag.rejected.total() == 0
    assert _late_median_error(outs, t, truth) < 2.0
    assert st.extra_diagnostics()["wifi_update"] == "scan"
    # a wifi/fix in scan mode and a scan of unknown APs are counted, not fatal
    st.process("wifi/fix", fix_to_msg(Fix(int(t[-1]), np.zeros(2), np.eye(2))), 0)
    st.process("wifi/scan", scan_to_msg(WifiScan(int(t[-1]), ("02:ff:00:00:00:01",), np.array([-60.0]),
                                                 np.array([2412.0]))), 0)
    assert st.diag.rejected["wrong_wifi_update"] == 1 and st.diag.rejected["no_known_ap"] == 1
    with pytest.raises(ConfigError, match="radiomap"):
        _stage(graph_file, wifi_update="scan")



@pytest.fixture
def tee_file(tmp_path):
    # a 40 m corridor along y = 0 with a 4 m room stub going south at x = 20 (node 1, link 2)
    g = build_graph(range(4), np.array([[0, 0], [20, 0], [40, 0], [20, -4]], float), [(0, 1), (1, 2), (1, 3)])
    return save_graph(g, tmp_path / "tee.graph.yaml")


def _turn_into_stub(stage: PfStage) -> int:
    """Start at (2, 0) heading east, walk 18 m east then 3 m south (into the stub) in 0.65 m
    hops; return the most particles ever seen on the stub link."""
    stage.process("initialpose", pose_to_msg(1_000_000_000, np.array([2.0, 0.0]), 0.0, np.eye(2) * 0.05), 0)
    assert not np.any(stage.tracker.pf.p.link == 2)             # none starts there
    pos, most, t = np.array([2.0, 0.0]), 0, 2_000_000_000
    heads = [0.0] * round(18 / STEP) + [-math.pi / 2] * round(3 / STEP)
    stage.process("pdr/odom", odom_to_msg(t, "u/odom", "u/base_link", *pos, 0.0, np.eye(3) * 0.1, 1.3, 0.0), 0)
    for yaw in heads:
        t += 500_000_000
        pos = pos + STEP * np.array([math.cos(yaw), math.sin(yaw)])
        stage.process("pdr/odom", odom_to_msg(t, "u/odom", "u/base_link", *pos, yaw, np.eye(3) * 0.1, 1.3, 0.0), 0)
        most = max(most, int(np.sum(stage.tracker.pf.p.link == 2)))
    return most


def test_a_learned_transition_table_is_used_and_must_match_the_graph(tee_file, tmp_path):
    quiet = {"yaw_offset_sigma_rad": 0.05, "monitor.enabled": False, "smooth": False}
    # the rule's own table lets the particles follow the walker into the stub
    assert _turn_into_stub(_stage(tee_file, **quiet)) > 50
    # a hand-made table for this graph that never enters the stub from the corridor (at node 1)
    g = _stage(tee_file).graph
    probs = np.array(transition_table(g).probs)
    slots = np.arange(g.adj_ptr[1], g.adj_ptr[2])
    stub_col = int(np.flatnonzero(g.adj_link[slots] == 2)[0])
    rows = slots[g.adj_link[slots] != 2]                        # arriving over the corridor
    probs[rows, stub_col] = 0.0
    probs[rows] /= probs[rows].sum(axis=1, keepdims=True)
    table = save_transitions(Transitions.from_probs(probs, "hand"), tmp_path / "no_stub.npz", tee_file)
    st = _stage(tee_file, transitions_file=str(table), **quiet)
    assert st.transitions.rule == "hand" and st.extra_diagnostics()["tll_cache"] == f"loaded {table}"
    assert _turn_into_stub(st) == 0
    # a table made for another graph, or an unreadable file, stops the start-up
    other = tmp_path / "other.graph.yaml"
    other.write_text(tee_file.read_text() + "\n# another revision of the map\n")
    with pytest.raises(ConfigError, match="transitions_file: .* was made for another graph"):
        PfStage(params_from_dict(PfStageParams, {"graph_file": str(other), "transitions_file": str(table)}))
    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"not a table")
    with pytest.raises(ConfigError, match="transitions_file: cannot read transition table"):
        _stage(tee_file, transitions_file=str(broken))
    with pytest.raises(ConfigError, match="transitions_file: cannot read transition table"):
        _stage(tee_file, transitions_file=str(tmp_path / "missing.npz"))


def test_memory_stays_bounded_in_a_long_run(graph_file):
    """The smoother's particle history (about 40 kB per pose at 1000 particles: the soak saw tll_pf
    grow 570 MB per simulated hour) keeps only ``smooth_window_s`` of stamp time, the estimates the
    newest ``path_max_poses``; the final path is the filtered estimates before the window, then the
    smoothed ones."""
    rng = np.random.default_rng(3)
    t, truth, odoms, fixes = _walk(rng, n=300)
    st = _stage(graph_file, n_particles=200, smooth_samples=5, smooth_window_s=30.0, path_max_poses=120)
    spans = []
    for i, od in enumerate(odoms):
        if i in fixes:
            st.process("wifi/fix", fixes[i], 0)
        st.process("pdr/odom", od, 0)
        steps = [s for seg in st.tracker.segments + [st.tracker.history] for s in seg]
        spans.append((steps[-1].stamp_ns - steps[0].stamp_ns) * 1e-9 if steps else 0.0)
        assert len(st.tracker.estimates) <= 150
    assert max(spans) <= 30.0 * 1.25 + 1.0 and spans[-1] >= 25.0
    stamps, xy, _ = path_from_msg([m for tp, m in st.finish() if tp == "pf/path"][-1])
    assert len(stamps) == 120 and np.all(np.diff(stamps) > 0)
    assert stamps[-1] == t[-1] or stamps[-1] >= t[-2]
