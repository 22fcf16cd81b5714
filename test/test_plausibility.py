"""Plausibility at the boundary (``contract.BOUNDS``, ``msg_adapters/plausible.py``,
``pipeline/bounds.py``): finite but absurd values are refused by reason, the sentinels the contract
uses pass, the bulk IMU decoder refuses exactly what the per-message adapter refuses, and the cases of
issue #23 item 5 leave every later message and the end of input working."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from diagnostic_msgs.msg import KeyValue
from hypothesis import given, settings, strategies as st
from rclpy.serialization import serialize_message
from std_msgs.msg import String

from backend_synth import survey
from conftest import ROOT
from test_backend_stage import FIX_KW, WKNN, _fix_stream, _messages, _stage as backend_stage
from test_pdr_kf_stage import _run as run_kf, _walk as kf_walk
from test_pf_stage import _stage as pf_stage, _walk as pf_walk, graph_file  # noqa: F401  (fixture)
from backend_synth import corridor_walk
from indoor_loc.bag.bulk import bulk_items
from indoor_loc.bag.cdr_padding import canonical_cdr
from indoor_loc.commands import contract as contract_cmd
from indoor_loc.contract import BOUNDS
from indoor_loc.errors import InvalidInputError, InvalidMessageError
from indoor_loc.imu.pdr import UNKNOWN_YAW_VAR
from indoor_loc.measurements import Fix, OdomPose
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
from indoor_loc.pipeline.bounds import MapBox
from indoor_loc.pipeline.imu_stage import ImuStage, ImuStageParams
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage, PdrKfStageParams
from indoor_loc.pipeline.wifi_scan_stage import WifiScanParams, WifiScanStage
from indoor_loc.wifi.types import WifiScan
from msg_adapters.imu import imu_from_msg, imu_to_msg, mag_from_msg, mag_to_msg
from msg_adapters.odom import OdomJumpGuard, odom_from_msg, odom_to_msg
from msg_adapters.path import path_from_msg
from msg_adapters.pose import fix_from_msg, fix_to_msg, pose_from_msg, pose_to_msg
from msg_adapters.wifi_json import scan_to_json_msg
from msg_adapters.wifi_scan import scan_from_msg, scan_to_msg

T0 = 1_700_000_000 * 1_000_000_000


def _reason(fn, *args, **kw) -> str:
    with pytest.raises(InvalidInputError) as e:
        fn(*args, **kw)
    return e.value.reason


def _scan(n=3, **kw) -> WifiScan:
    return WifiScan(stamp_ns=T0, bssid=tuple(f"00:11:22:33:44:{i:02x}" for i in range(n)),
                    rssi_dbm=np.full(n, -60.0), freq_mhz=np.full(n, 2412.0), ssid=("a",) * n, **kw)


def _set_value(msg, ap: int, key: str, value: str):
    st_ = msg.status[ap]
    st_.values = [kv for kv in st_.values if kv.key != key] + [KeyValue(key=key, value=value)]
    return msg


# -- the table --------------------------------------------------------------------------------------
def test_every_bound_is_documented_and_printed(capsys):
    doc = (ROOT / "docs" / "nodes.md").read_text()
    assert contract_cmd.main(None) == 0
    out = capsys.readouterr().out
    for name, b in BOUNDS.items():
        assert b.lo <= b.hi and b.unit and b.why and b.applies
        assert f"| `{name}` |" in doc, f"docs/nodes.md does not list bound {name}"
        assert f"| `{name}` | [{b.lo:g}, {b.hi:g}] |" in out


# -- adapters: refused by reason, the detail naming field, value and bound -------------------------
def test_imu_values_beyond_any_sensor_are_refused_and_the_detail_says_which():
    ok = imu_to_msg(T0, "imu", [0.1, 0.2, 9.8], [0.01, 0.0, 0.0])
    imu_from_msg(ok)
    for field, axis, value, bound in [("linear_acceleration", "x", 1e308, "acceleration"),
                                      ("linear_acceleration", "z", -250.0, "acceleration"),
                                      ("angular_velocity", "y", 1e5, "angular_rate")]:
        msg = copy.deepcopy(ok)
        setattr(getattr(msg, field), axis, value)
        with pytest.raises(InvalidMessageError) as e:
            imu_from_msg(msg)
        assert e.value.reason == "out_of_range"
        assert f"{field}.{axis}" in e.value.detail and f"{value:.6g}" in e.value.detail and bound in e.value.detail
    no_gyro = imu_to_msg(T0, "imu", [0.0, 0.0, 9.8])          # REP 145: no gyroscope, its rate not read
    no_gyro.angular_velocity.x = 1e308
    assert imu_from_msg(no_gyro).gyro is None
    assert _reason(mag_from_msg, mag_to_msg(T0, "imu", [1e308, 0.0, 0.0])) == "out_of_range"
    assert _reason(mag_from_msg, mag_to_msg(T0, "imu", [0.0, 0.02, 0.0])) == "out_of_range"
    mag_from_msg(mag_to_msg(T0, "imu", [2e-5, -4e-4, 4.5e-5]))     # a disturbed but real field


def test_orientation_covariance_must_be_symmetric_psd_and_bounded_and_its_sentinels_pass():
    q = [0.0, 0.0, 0.0, 1.0]
    imu_from_msg(imu_to_msg(T0, "imu", [0, 0, 9.8], None, q, np.zeros((3, 3))))           # zeros: unknown
    imu_from_msg(imu_to_msg(T0, "imu", [0, 0, 9.8], None, q, np.diag([1e-4, 1e-4, UNKNOWN_YAW_VAR])))
    assert imu_from_msg(imu_to_msg(T0, "imu", [0, 0, 9.8])).orientation_cov is None        # -1: absent
    for cov in (np.array([[1e-3, 5e-4, 0], [0, 1e-3, 0], [0, 0, 1e-2]]),                 # not symmetric
                np.diag([1e-3, -1e-3, 1e-2]),                                           # negative variance
                np.array([[1e-2, 2e-2, 0], [2e-2, 1e-2, 0], [0, 0, 1e-2]]),             # indefinite
                np.diag([1e-3, 1e-3, 1e308])):                                          # beyond 'unknown'
        assert _reason(imu_from_msg, imu_to_msg(T0, "imu", [0, 0, 9.8], None, q, cov)) == "bad_covariance"


def _odom(**kw):
    args = dict(x=1.0, y=2.0, yaw=0.3, cov_xyyaw=np.diag([0.1, 0.1, 0.05]), speed_mps=1.2, yaw_rate=0.1)
    args.update(kw)
    return odom_to_msg(T0, "u/odom", "u/base_link", **args)


def test_odometry_out_of_bounds_is_refused_and_its_unknown_yaw_passes():
    odom_from_msg(_odom(cov_xyyaw=np.diag([0.1, 0.1, UNKNOWN_YAW_VAR]), yaw_rate_var=UNKNOWN_YAW_VAR))
    assert _reason(odom_from_msg, _odom(x=1e308)) == "out_of_range"
    assert _reason(odom_from_msg, _odom(y=-2e5)) == "out_of_range"
    assert _reason(odom_from_msg, _odom(speed_mps=1e9)) == "out_of_range"
    assert _reason(odom_from_msg, _odom(yaw_rate=-1e308)) == "out_of_range"
    assert _reason(odom_from_msg, _odom(cov_xyyaw=np.array([[0.1, 0.05, 0], [0.0, 0.1, 0], [0, 0, 0.05]]))) \
        == "bad_covariance"
    assert _reason(odom_from_msg, _odom(cov_xyyaw=np.diag([-0.1, 0.1, 0.05]))) == "bad_covariance"
    msg = _odom()
    msg.twist.covariance[0] = -1.0
    assert _reason(odom_from_msg, msg) == "bad_covariance"


def test_poses_and_fixes_out_of_bounds_are_refused():
    good = fix_to_msg(Fix(T0, np.array([3.0, 4.0]), np.eye(2) * 4.0))
    fix_from_msg(good)
    asym = copy.deepcopy(good)
    asym.pose.covariance[1] = 2.0                               # cov[0, 1] = 2, cov[1, 0] = 0
    assert _reason(fix_from_msg, asym) == "bad_covariance"
    tiny = fix_to_msg(Fix(T0, np.array([3.0, 4.0]), np.eye(2) * 1e-300))
    assert _reason(fix_from_msg, tiny) == "bad_covariance"
    far = fix_to_msg(Fix(T0, np.array([1e308, 4.0]), np.eye(2)))
    assert _reason(fix_from_msg, far) == "out_of_range"
    rviz = pose_to_msg(T0, [1.0, 2.0], 0.5, np.eye(2) * 0.25, yaw_var=0.0685)        # RViz's 2D Pose Estimate
    pose_from_msg(rviz)
    pose_from_msg(pose_to_msg(T0, [1.0, 2.0], 0.5, None))                              # no covariance: zeros
    bad_yaw = pose_to_msg(T0, [1.0, 2.0], 0.5, np.eye(2), yaw_var=-1.0)
    assert _reason(pose_from_msg, bad_yaw) == "bad_covariance"
    # an estimate whose yaw nothing constrains (a marginal of 1e9 rad²) is written as unknown, so a
    # reader of the output (indoor-loc eval, the next node) takes it
    vague = pose_to_msg(T0, [1.0, 2.0], 0.5, np.eye(2), yaw_var=1e9)
    assert vague.pose.covariance[35] == UNKNOWN_YAW_VAR and pose_from_msg(vague).yaw == pytest.approx(0.5)


def test_scan_frequency_and_age_out_of_bounds_are_refused_and_unknown_frequency_passes():
    ok = WifiScan(stamp_ns=T0, bssid=("00:11:22:33:44:55", "00:11:22:33:44:66", "00:11:22:33:44:77"),
                  rssi_dbm=np.full(3, -60.0), freq_mhz=np.array([0.0, 5180.0, 60480.0]), ssid=("a",) * 3,
                  age_ms=np.array([0.0, np.nan, 3.6e6]))            # 0 MHz: unknown; 60 GHz: 802.11ad
    assert scan_from_msg(scan_to_msg(ok)).freq_mhz.tolist() == [0.0, 5180.0, 60480.0]
    for key, value in (("frequency_mhz", "1e308"), ("frequency_mhz", "-2412.0"), ("frequency_mhz", "2.412"),
                       ("age_ms", "1e308"), ("age_ms", "-1.0")):
        msg = _set_value(scan_to_msg(_scan()), 2, key, value)
        with pytest.raises(InvalidMessageError) as e:
            scan_from_msg(msg)
        assert e.value.reason == "out_of_range" and key in e.value.detail, e.value.detail
        assert f"{float(value):.6g}" in e.value.detail


def test_a_drivers_scan_loses_only_the_absurd_reading():
    st = WifiScanStage(params_from_dict(WifiScanParams, {"normalize.keep_random_macs": True}))
    raw = _set_value(scan_to_msg(_scan()), 2, "frequency_mhz", "1e308")
    assert st.process("wifi/scan_raw", raw, T0) == []
    assert st.diag.rejected == {"out_of_range": 1}
    doc = scan_to_json_msg(_scan(age_ms=np.array([10.0, 20.0, 30.0])))
    text = doc.data.replace('"last_seen_ms": 20.0', '"last_seen_ms": 1e308')
    (topic, msg), = st.process("wifi/scan_json", String(data=text), T0)
    assert len(scan_from_msg(msg)) == 2 and st.dropped == {"bad_age": 1}


# -- the bulk decoder refuses exactly what the adapter refuses -------------------------------------
edge = st.sampled_from([0.0, 9.81, -199.99, 200.0, 200.00000001, -200.5, 99.9, 100.0, 100.1, 1e308, -1e308])
cov_kinds = st.sampled_from(["absent", "zeros", "diag", "unknown_yaw", "asym", "negative", "huge", "round_asym"])


def _imu_msg(i: int, acc, gyro, cov_kind: str):
    q = [0.0, 0.0, math.sin(0.1 * i), math.cos(0.1 * i)]
    cov = {"zeros": np.zeros((3, 3)), "diag": np.diag([1e-3, 1e-3, 1e-2]), "unknown_yaw": np.diag([1e-3, 1e-3, 1e6]),
           "asym": np.array([[1e-3, 1e-4, 0], [0, 1e-3, 0], [0, 0, 1e-2]]), "negative": np.diag([1e-3, 1e-3, -1e-2]),
           "huge": np.diag([1e-3, 1e-3, 2e6]),
           "round_asym": np.array([[1e-3, 1e-4 + 1e-19, 0], [1e-4, 1e-3, 0], [0, 0, 1e-2]])}.get(cov_kind)
    msg = imu_to_msg(T0 + i * 5_000_000, "imu", [0.0, 0.0, 9.8], gyro, None if cov_kind == "absent" else q, cov)
    msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = acc
    return msg


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.tuples(edge, edge, edge), st.one_of(st.none(), st.tuples(edge, edge, edge)), cov_kinds),
                min_size=1, max_size=4))
def test_bulk_imu_decoding_refuses_a_run_exactly_when_a_message_would_be_refused(rows):
    msgs = [_imu_msg(i, acc, gyro, kind) for i, (acc, gyro, kind) in enumerate(rows)]
    refused = 0
    for m in msgs:
        try:
            imu_from_msg(m)
        except InvalidMessageError:
            refused += 1
    items = bulk_items("sensor_msgs/msg/Imu", [serialize_message(m) for m in msgs])
    assert (items is None) == (refused > 0)
    if items is not None:
        for m, s in zip(msgs, items):
            ref = imu_from_msg(m)
            assert np.array_equal(s.acc, ref.acc) and (s.orientation_cov is None) == (ref.orientation_cov is None)


def test_bulk_mag_decoding_refuses_a_field_beyond_any_magnetometer():
    good = [serialize_message(mag_to_msg(T0 + i, "imu", [2e-5, 0.0, 4e-5])) for i in range(3)]
    assert bulk_items("sensor_msgs/msg/MagneticField", good) is not None
    bad = good[:2] + [serialize_message(mag_to_msg(T0 + 2, "imu", [1e308, 0.0, 4e-5]))]
    assert bulk_items("sensor_msgs/msg/MagneticField", bad) is None


# -- stage level: off the map, odometry jumps ------------------------------------------------------
def test_map_box_refuses_beyond_its_margin_only():
    box = MapBox.around(np.array([[0.0, 0.0], [50.0, 20.0]]))
    assert box is not None and MapBox.around(np.zeros((0, 2))) is None
    box.check("fix", [150.0, 20.0])                     # exactly 100 m off
    box.check("fix", [25.0, -99.0])
    with pytest.raises(InvalidInputError) as e:
        box.check("fix", [25.0, 1e5])
    assert e.value.reason == "off_map" and "100000" in e.value.detail


def _od(t_s: float, x: float, y: float = 0.0) -> OdomPose:
    return OdomPose(T0 + int(t_s * 1e9), x, y, 0.0, np.zeros((3, 3)), 1.0, 0.0)


def test_an_odometry_jump_is_refused_without_becoming_the_reference_and_a_restart_is_taken_in_time():
    g = OdomJumpGuard()
    g.check(_od(0.0, 500.0))                            # the first pose of a stream: anywhere
    g.accept(_od(0.0, 500.0))
    g.check(_od(0.3, 501.0))
    g.accept(_od(0.3, 501.0))
    with pytest.raises(InvalidInputError) as e:
        g.check(_od(0.6, 5e4))
    assert e.value.reason == "odom_jump"
    g.check(_od(0.9, 502.0))                            # measured from 501 m, not from 5e4
    with pytest.raises(InvalidInputError):
        g.check(_od(1.0, 0.0))                          # odometry restarted at its origin: 501 m in 0.7 s
    g.check(_od(60.0, 0.0))                             # a minute later the stamps allow it


# -- issue #23 item 5, as regression tests ---------------------------------------------------------
def test_one_absurd_odometry_among_valid_ones_leaves_the_kalman_filter_and_its_smoother_working():
    rng = np.random.default_rng(3)
    _, _, odoms, fixes = kf_walk(rng)
    clean = PdrKfStage(params_from_dict(PdrKfStageParams, {}))
    clean_poses, clean_paths = run_kf(clean, odoms, fixes)
    bad = copy.deepcopy(odoms[40])
    bad.pose.pose.position.x = 1e308
    bad.header.stamp.nanosec = 500_000_000                  # between its neighbours
    st = PdrKfStage(params_from_dict(PdrKfStageParams, {}))
    poses, paths = run_kf(st, odoms[:41] + [bad] + odoms[41:], {i + (i > 40): f for i, f in fixes.items()})
    assert dict(st.diag.rejected) == {"out_of_range": 1}
    assert st.smoother_runs == clean.smoother_runs and paths
    assert [canonical_cdr(p) for p in poses] == [canonical_cdr(p) for p in clean_poses]
    s, xy, _ = path_from_msg(paths[-1])
    s0, xy0, _ = path_from_msg(clean_paths[-1])
    assert np.array_equal(s, s0) and np.array_equal(xy, xy0)


def test_one_absurd_odometry_leaves_the_back_end_and_its_end_of_input_working():
    msgs = _messages(corridor_walk("alice", 2, 50, 0, np.random.default_rng(21)))
    k = [i for i, (_, topic, _) in enumerate(msgs) if topic == "pdr/odom"][30]
    bad = copy.deepcopy(msgs[k][2])
    bad.pose.pose.position.x = 1e308
    bad.header.stamp.nanosec += 1
    runs = []
    for stream in (msgs, msgs[:k + 1] + [(0, "pdr/odom", bad)] + msgs[k + 1:]):
        st = backend_stage()
        outs = [o for _, topic, m in stream for o in st.process(topic, m, 0, "alice")]
        outs += st.run_finish()
        runs.append((st, outs))
    (clean, clean_outs), (st, outs) = runs
    assert dict(st.diag.rejected) == {"out_of_range": 1} and not clean.diag.rejected
    topics = [t for t, _ in outs]
    assert "backend/wifi_map" in topics and "backend/alice/path" in topics
    final = path_from_msg([m for t, m in outs if t == "backend/alice/path"][-1])
    final0 = path_from_msg([m for t, m in clean_outs if t == "backend/alice/path"][-1])
    assert np.allclose(final[1], final0[1], atol=1e-9)


def test_an_absurd_imu_sample_leaves_the_odometry_as_without_it():
    rng = np.random.default_rng(4)
    t = T0 + np.arange(1200) * 5_000_000
    acc = np.stack([0.3 * rng.normal(size=1200), 0.3 * rng.normal(size=1200),
                    9.81 + 2.0 * np.sin(2 * np.pi * 1.8 * (t - T0) * 1e-9)], axis=1)
    msgs = [imu_to_msg(int(s), "imu", a, [0.0, 0.0, 0.01]) for s, a in zip(t, acc)]
    bad = imu_to_msg(int(t[600]) + 1, "imu", [1e308, 0.0, 9.8], [0.0, 0.0, 0.01])
    outs = []
    for stream in (msgs, msgs[:601] + [bad] + msgs[601:]):
        st = ImuStage(params_from_dict(ImuStageParams, {"heading_source": "aekf"}))
        odom = [m for msg in stream for topic, m in st.process("imu/data_raw", msg, 0) if topic == "pdr/odom"]
        odom += [m for topic, m in st.run_finish() if topic == "pdr/odom"]
        outs.append([canonical_cdr(m) for m in odom])   # (serialize_message's padding bytes vary)
        rejected = dict(st.diag.rejected)
    assert outs[0] and outs[1] == outs[0] and rejected == {"out_of_range": 1}


def test_a_fix_100_km_away_is_off_the_map_for_the_particle_filter_and_the_back_end(graph_file):  # noqa: F811
    _, _, odoms, fixes = pf_walk(np.random.default_rng(7), n=12)
    pf = pf_stage(graph_file)
    far = fix_to_msg(Fix(T0, np.array([1e5, 2.0]), np.eye(2) * 4.0))
    assert pf.process("wifi/fix", far, 0) == [] and dict(pf.diag.rejected) == {"off_map": 1}
    assert not pf.tracker.initialised
    pose = pose_to_msg(T0, [2.0, -1e5], 0.0, np.eye(2))
    assert pf.process("initialpose", pose, 0) == [] and pf.diag.rejected["off_map"] == 2

    _, stream = _fix_stream(5)
    st = BackendStage(BackendParams(wknn=WKNN, **FIX_KW), survey=survey(0, 60, np.random.default_rng(1)))
    k = next(i for i, (_, topic, _) in enumerate(stream) if topic == "wifi/fix")
    far = fix_to_msg(Fix(stream[k][0], np.array([20.0, 1e5]), np.eye(2) * 4.0))
    outs = [o for _, topic, m in stream[:k] for o in st.process(topic, m, 0, "bob")]
    outs += st.process("wifi/fix", far, 0, "bob")
    outs += [o for _, topic, m in stream[k:] for o in st.process(topic, m, 0, "bob")]
    outs += st.run_finish()
    assert dict(st.diag.rejected) == {"off_map": 1}
    assert "backend/bob/path" in [t for t, _ in outs]
