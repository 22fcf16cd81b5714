"""Robot odometry increments (indoor_loc/odometry/increments.py) and their message adapter."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from indoor_loc.errors import ConfigError, InvalidInputError, InvalidMessageError
from indoor_loc.odometry.increments import (IncrementAccumulator, OdomIncrementParams, compose, integrate,
                                            message_cov, model_cov, odometry_increments, relative_pose)
from indoor_loc.params import params_from_dict
from msg_adapters.odom import odom_to_msg
from msg_adapters.robot_odom import RobotOdomReader

S = 1_000_000_000


def _drive(v: np.ndarray, w: np.ndarray, dt: float = 0.05, yaw0: float = 0.0):
    """Poses (N+1, 3) of a unicycle driven by forward speeds v and yaw rates w (N,)."""
    out = [(0.0, 0.0, yaw0)]
    for vk, wk in zip(v, w):
        x, y, th = out[-1]
        out.append((x + vk * dt * math.cos(th + 0.5 * wk * dt), y + vk * dt * math.sin(th + 0.5 * wk * dt),
                    th + wk * dt))
    return np.array(out)


def test_relative_pose_and_compose_are_inverse():
    a = (1.0, -2.0, 0.7)
    b = (4.0, 1.5, -2.9)
    d = relative_pose(*a, *b)
    x, y, th = compose(*a, *d)
    assert (x, y) == pytest.approx(b[:2], abs=1e-12)
    assert math.isclose(math.remainder(th - b[2], 2 * math.pi), 0.0, abs_tol=1e-12)


def test_straight_drive_gives_forward_increments_at_the_decimation_distance():
    poses = _drive(np.full(200, 0.8), np.zeros(200), yaw0=1.0)     # 8 m at 0.8 m/s, 20 Hz
    t = np.arange(len(poses)) * (S // 20)
    incs = odometry_increments(t, poses[:, :2], poses[:, 2], params=OdomIncrementParams(max_interval_s=10.0))
    assert len(incs) == 16                          # every 0.5 m (13 samples of 4 cm), then the rest flushed
    assert sum(i.distance_m for i in incs) == pytest.approx(8.0)
    for inc in incs:
        assert (0.5 <= inc.dx_m < 0.54 or inc is incs[-1]) and abs(inc.dy_m) < 1e-9
        assert inc.travel_rad == pytest.approx(0.0, abs=1e-9)      # the increment frame starts at yaw 0
        assert not inc.reverse and not inc.from_message


def test_reverse_and_turn_in_place_keep_the_direction_of_travel():
    acc = IncrementAccumulator(OdomIncrementParams(min_distance_m=0.2, max_interval_s=100.0, min_angle_rad=0.5))
    acc.update(0, 0.0, 0.0, 0.0)
    back = acc.update(S, -0.3, 0.0, 0.0)                           # 0.3 m backwards
    assert back is not None and back.reverse and back.distance_m == pytest.approx(0.3)
    assert abs(abs(back.travel_rad) - math.pi) < 1e-9
    turn = acc.update(2 * S, -0.3, 0.0, 0.6)                       # turning in place, still reversing
    assert turn is not None and turn.distance_m == 0.0
    assert turn.dtravel_rad == pytest.approx(0.6)                  # travel follows the yaw


def test_model_covariance_when_the_driver_gives_zeros_or_a_constant():
    p = OdomIncrementParams()
    for cov in (np.zeros((3, 3)), np.diag([0.01, 0.01, 0.05])):    # zeros / diff_drive_controller's constant
        acc = IncrementAccumulator(p)
        acc.update(0, 0.0, 0.0, 0.0, cov)
        inc = acc.update(S, 0.6, 0.0, 0.0, cov)
        assert inc is not None and not inc.from_message
        assert np.allclose(inc.cov, model_cov(p, 0.6, 0.0))
        assert inc.var_along == pytest.approx(p.trans_var_per_m * 0.6 + p.var_floor)


def test_message_covariance_from_its_growth_in_the_start_frame():
    p = OdomIncrementParams(covariance="auto")
    c0 = np.diag([0.1, 0.1, 0.01])
    c1 = c0 + np.diag([0.04, 0.01, 0.002])                          # grew mostly along x (odom frame)
    acc = IncrementAccumulator(p)
    acc.update(0, 0.0, 0.0, math.pi / 2, c0)                       # facing +y: odom x is the robot's right
    inc = acc.update(S, 0.0, 0.6, math.pi / 2, c1)
    assert inc is not None and inc.from_message
    assert inc.cov[0, 0] == pytest.approx(0.01 + p.var_floor)      # forward = odom y
    assert inc.cov[1, 1] == pytest.approx(0.04 + p.var_floor)      # leftward = odom -x
    assert message_cov(0.0, c1, c0) is None                        # shrinking: no increment covariance
    forced = IncrementAccumulator(OdomIncrementParams(covariance="model"))
    forced.update(0, 0.0, 0.0, math.pi / 2, c0)
    assert not forced.update(S, 0.0, 0.6, math.pi / 2, c1).from_message


def test_params_and_inputs_are_checked():
    with pytest.raises(ConfigError, match="covariance"):
        params_from_dict(OdomIncrementParams, {"covariance": "bogus"})
    with pytest.raises(ConfigError, match="min_distance_m"):
        params_from_dict(OdomIncrementParams, {"min_distance_m": 0.0})
    acc = IncrementAccumulator()
    acc.update(5, 0.0, 0.0, 0.0)
    with pytest.raises(InvalidInputError, match="non_monotonic_stamp"):
        acc.update(5, 1.0, 0.0, 0.0)
    assert acc.last_stamp_ns == 5


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-1.2, 1.2), st.floats(-2.0, 2.0)), min_size=2, max_size=120),
       st.floats(-math.pi, math.pi), st.floats(0.05, 2.0), st.floats(0.05, 1.0))
def test_increments_compose_back_to_the_odometry(cmds, yaw0, min_d, min_a):
    """Oracle: the decimated increments, composed from the first pose, land on the last pose exactly
    (SE(2) composition loses nothing), and each closed increment met one of its triggers."""
    v = np.array([c[0] for c in cmds])
    w = np.array([c[1] for c in cmds])
    poses = _drive(v, w, yaw0=yaw0)
    t = np.arange(len(poses), dtype=np.int64) * (S // 20)
    p = OdomIncrementParams(min_distance_m=min_d, min_angle_rad=min_a, max_interval_s=0.7)
    incs = odometry_increments(t, poses[:, :2], poses[:, 2], params=p)
    end = integrate(incs, *poses[0])
    assert end[-1, :2] == pytest.approx(poses[-1, :2], abs=1e-9)
    assert abs(math.remainder(end[-1, 2] - poses[-1, 2], 2 * math.pi)) < 1e-9
    assert [i.t_start_ns for i in incs[1:]] == [i.t_end_ns for i in incs[:-1]]
    for inc in incs[:-1]:
        assert (inc.t_end_ns - inc.t_start_ns) * 1e-9 >= 0.7 - 1e-9 or inc.distance_m > 0 or abs(inc.dyaw_rad) > 0
    for inc in incs:
        assert np.all(np.linalg.eigvalsh(inc.cov) > 0) and np.isfinite(inc.travel_rad)


# -- the adapter ------------------------------------------------------------------------------------
def _msg(t_ns, x, y, yaw, cov=None, frame="r/odom", child="r/base_link"):
    m = odom_to_msg(t_ns, frame, child, x, y, yaw, np.zeros((3, 3)) if cov is None else cov, 0.5, 0.0)
    return m


def test_reader_takes_unknown_covariance_and_refuses_without_changing_anything():
    r = RobotOdomReader(OdomIncrementParams(min_distance_m=0.5, max_interval_s=10.0))
    m = _msg(0, 0.0, 0.0, 0.0)
    m.pose.covariance[0] = -1.0                        # "not given", as drivers write it
    m.twist.covariance[0] = -1.0
    assert r.read(m)[1] is None
    nan = _msg(S, 0.3, 0.0, 0.0)
    nan.pose.pose.position.x = float("nan")
    bad = [nan, _msg(S, 0.3, 0.0, 0.0, frame="other/odom"), _msg(0, 0.3, 0.0, 0.0),
           _msg(S, 500.0, 0.0, 0.0)]
    reasons = []
    for b in bad:
        with pytest.raises(InvalidMessageError) as ei:
            r.read(b)
        reasons.append(ei.value.reason)
    assert reasons == ["nan", "wrong_frame", "non_monotonic_stamp", "odom_jump"]
    _, inc = r.read(_msg(2 * S, 0.6, 0.0, 0.0))         # as if none of the refused ones had come
    assert inc is not None and inc.t_start_ns == 0 and inc.distance_m == pytest.approx(0.6)
    assert r.diagnostics()["odom.messages"] == "2"


# -- any message on the odom port of an estimator ---------------------------------------------------
HOSTILE = [float("nan"), float("inf"), -float("inf"), 1e308, -1e308, -1.0, 1e12, 5e-324, 0.0]
FIELDS = ["pose.pose.position.x", "pose.pose.position.y", "pose.pose.orientation.z", "pose.pose.orientation.w",
          "twist.twist.linear.x", "twist.twist.angular.z"]


def _clean_stream():
    from indoor_loc.measurements import Fix
    from msg_adapters.pose import fix_to_msg
    poses = _drive(np.full(160, 0.8), np.where(np.arange(160) % 80 < 20, 0.8, 0.0), yaw0=0.3)
    ev = []
    for k, p in enumerate(poses):
        t = 10 * S + k * (S // 20)
        ev.append((t, "odom", _msg(t, p[0], p[1], p[2])))
        if k % 40 == 20:
            ev.append((t, "wifi/fix", fix_to_msg(Fix(t, np.array([p[1], -p[0]]), np.eye(2)))))
    return ev


def _run(events):
    from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage, PdrKfStageParams
    st = PdrKfStage(params_from_dict(PdrKfStageParams, {"motion_source": "odom", "smooth_period_s": 0.0}))
    outs = []
    for t, topic, m in events:
        outs += st.process(topic, m, t)
    return st, outs + st.run_finish()


_REF: list = []


@settings(max_examples=8, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 170), st.sampled_from(FIELDS), st.sampled_from(HOSTILE),
                          st.lists(st.sampled_from(HOSTILE), max_size=3)), min_size=1, max_size=6))
def test_hostile_odometry_is_counted_and_leaves_no_state(cases):
    """Any robot odometry message on the KF's odom port: no internal error, finite outputs, and when
    every hostile message was refused the outputs are the clean stream's."""
    import copy
    clean = _clean_stream()
    if not _REF:
        _REF.append(_run(clean)[1])
    ref = _REF[0]
    events = list(clean)
    odom_at = [i for i, e in enumerate(clean) if e[1] == "odom"]
    for where, field, value, covs in sorted(cases, key=lambda c: -c[0]):
        i = odom_at[min(where, len(odom_at) - 1)]
        t, _, m = clean[i]
        h = copy.deepcopy(m)
        obj = h
        *path, last = field.split(".")
        for part in path:
            obj = getattr(obj, part)
        setattr(obj, last, value)
        for k, v in enumerate(covs):
            h.pose.covariance[(7 * k) % 36] = v
        events.insert(i + 1, (t + 1, "odom", h))
    stage, outs = _run(events)
    assert stage.diag.rejected["internal_error"] == 0, stage.diag.last_error
    for _, m in outs:
        if hasattr(m, "pose") and hasattr(m.pose, "pose"):
            assert math.isfinite(m.pose.pose.position.x) and math.isfinite(m.pose.pose.position.y)
    if sum(stage.diag.rejected.values()) == len(cases):
        got = [(t, m.pose.pose.position.x) for t, m in outs if t == "pdr_kf/pose"]
        want = [(t, m.pose.pose.position.x) for t, m in ref if t == "pdr_kf/pose"]
        assert got == want
