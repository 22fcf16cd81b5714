"""PdrKfStage: the linear PDR KF as a stage, fed with contract messages (seeded synthetic walk)."""
from __future__ import annotations

import math

import numpy as np

from msg_adapters.odom import odom_to_msg
from msg_adapters.path import path_from_msg
from msg_adapters.pose import fix_from_msg, fix_to_msg, pose_from_msg
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage, PdrKfStageParams
from indoor_loc.measurements import Fix

STEP = 0.65


def _walk(rng: np.random.Generator, n: int = 120, yaw_offset: float = 1.0):
    """A walk of 2-step intervals around a 20 x 10 m rectangle; PDR in an odom frame rotated by
    an unknown 1 rad (``yaw_offset``) and with noisy heading; WiFi fixes (sigma 2 m) every 3rd interval."""
    t = np.arange(n) * 1_000_000_000 + 5_000_000_000
    true_xy = [np.array([2.0, 2.0])]
    yaw = 0.0
    yaws = []
    for i in range(n):
        if i in (15, 23, 46, 54, 77, 85, 108):
            yaw += math.pi / 2
        yaws.append(yaw)
        true_xy.append(true_xy[-1] + 2 * STEP * np.array([math.cos(yaw), math.sin(yaw)]))
    true_xy = np.array(true_xy[1:])
    odom_yaw = np.array(yaws) + yaw_offset + np.cumsum(rng.normal(0, 0.01, n))
    ox = oy = 0.0
    odoms, fixes = [], []
    for i in range(n):
        ox += 2 * STEP * math.cos(odom_yaw[i])
        oy += 2 * STEP * math.sin(odom_yaw[i])
        odoms.append(odom_to_msg(int(t[i]), "u/odom", "u/base_link", ox, oy, odom_yaw[i], np.eye(3) * 0.1, 1.3, 0.0))
        if i % 3 == 0:
            fixes.append((i, fix_to_msg(Fix(int(t[i]) + 1000, true_xy[i] + rng.normal(0, 2.0, 2), np.eye(2) * 4.0))))
    return t, true_xy, odoms, dict(fixes)


def _run(stage, odoms, fixes):
    poses, paths = [], []
    for i, od in enumerate(odoms):
        for topic, msg in stage.process("pdr/odom", od, 0):
            if topic != "pdr_kf/map_odom":
                (poses if topic == "pdr_kf/pose" else paths).append(msg)
        if i in fixes:
            for topic, msg in stage.process("wifi/fix", fixes[i], 0):
                if topic == "pdr_kf/pose":
                    poses.append(msg)
    paths += [m for topic, m in stage.finish() if topic == "pdr_kf/path"]
    return poses, paths


def test_filter_and_smoother_beat_wifi_alone(rng):
    t, true_xy, odoms, fixes = _walk(rng)
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0}))
    poses, paths = _run(stage, odoms, fixes)
    assert len(paths) == 1 and stage.diag.rejected.total() == 0
    stamps, xy, _ = path_from_msg(paths[0])
    idx = np.searchsorted(t, stamps[1:], side="right") - 1          # first epoch is the init fix
    smooth_err = np.linalg.norm(xy[1:] - true_xy[idx], axis=1)
    wifi_err = np.array([np.linalg.norm(fix_from_msg(m).xy - true_xy[i]) for i, m in fixes.items()])
    last = [fix_from_msg(m) for m in poses][-1]
    assert np.isfinite(last.cov).all()
    # Raitoharju et al. 2015's ordering: smoothed < WiFi-only, with margin
    assert smooth_err[20:].mean() < 0.6 * wifi_err.mean(), (smooth_err.mean(), wifi_err.mean())


def test_bad_odom_is_counted_and_state_untouched(rng):
    t, _, odoms, fixes = _walk(rng, 12)
    stage = PdrKfStage(PdrKfStageParams())
    stage.process("wifi/fix", fixes[0], 0)
    stage.process("pdr/odom", odoms[1], 0)
    x_before = stage.kf.x.copy()
    assert stage.process("pdr/odom", odoms[0], 0) == []               # stamp going backwards
    assert stage.diag.rejected["non_monotonic_stamp"] == 1
    np.testing.assert_array_equal(stage.kf.x, x_before)


def test_no_output_before_first_fix(rng):
    _, _, odoms, _ = _walk(rng, 5)
    stage = PdrKfStage(PdrKfStageParams())
    assert all(stage.process("pdr/odom", m, 0) == [] for m in odoms)
    assert stage.finish() == []
    assert "waiting" in stage.extra_diagnostics()["initialised"]


def test_wrong_pdr_turn_restarts_the_filter_at_a_fix(rng):
    """PDR turns left where the walker turned right. A filter confident in its heading model
    (sigma_dtheta 0.05 rad) then gates out the fixes that follow; after ``max_rejected_fixes`` of
    them it restarts at a fix instead of drifting away for tens of metres."""
    n = 90
    t = np.arange(n) * 1_000_000_000
    true_xy = np.array([[2.0 + 2 * STEP * i, 5.0] if i < 30 else [2.0 + 2 * STEP * 29, 5.0 - 2 * STEP * (i - 29)]
                        for i in range(n)])
    odom_yaw = np.where(np.arange(n) < 30, 0.0, math.pi / 2)         # wrong way: left instead of right
    pos = np.cumsum(2 * STEP * np.c_[np.cos(odom_yaw), np.sin(odom_yaw)], axis=0)
    odoms = [odom_to_msg(int(t[i]), "u/odom", "u/base_link", pos[i, 0], pos[i, 1], odom_yaw[i], np.eye(3) * 0.1,
                         1.3, 0.0) for i in range(n)]
    fixes = {i: fix_to_msg(Fix(int(t[i]) + 1000, true_xy[i] + rng.normal(0, 1.0, 2), np.eye(2) * 1.0))
             for i in range(0, n, 3)}
    worst, restarts = {}, {}
    for limit in (0, 2):
        stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"max_rejected_fixes": limit, "smooth_period_s": 0.0,
                                                               "sigma_dtheta_rad": 0.05}))
        poses, _ = _run(stage, odoms, fixes)
        est = [fix_from_msg(m) for m in poses]
        idx = np.minimum(np.array([f.stamp_ns for f in est]) // 1_000_000_000, n - 1)
        worst[limit] = float(np.max(np.linalg.norm(np.array([f.xy for f in est]) - true_xy[idx], axis=1)))
        restarts[limit] = stage.restarts
    assert restarts == {0: 0, 2: 1}
    assert worst[2] < 20.0 and worst[0] > 2 * worst[2], worst


def test_pdr_arriving_late_gives_the_same_track_as_in_order(rng):
    """The stepometer publishes each hop about half a window after its stamp: fixes must wait for
    PDR to reach their stamp, so a 2 s delay of pdr/odom changes nothing."""
    _, _, odoms, fixes = _walk(rng, 60)
    smoothed = []
    for lag in (0, 2):
        stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0}))
        for i in range(len(odoms) + lag):
            if i in fixes:
                stage.process("wifi/fix", fixes[i], 0)           # fix i arrives on time ...
            if 0 <= i - lag < len(odoms):
                stage.process("pdr/odom", odoms[i - lag], 0)     # ... PDR for hop i - lag only now
        (_, path), = stage.finish()
        smoothed.append(path_from_msg(path))
    np.testing.assert_array_equal(smoothed[0][0], smoothed[1][0])
    np.testing.assert_allclose(smoothed[0][1], smoothed[1][1], atol=1e-9)


def test_fix_waits_at_most_max_fix_delay(rng):
    _, _, _, fixes = _walk(rng, 30)
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"max_fix_delay_s": 5.0}))
    outs = [stage.process("wifi/fix", fixes[i], 0) for i in (0, 3, 6)]    # no PDR at all: stamps 0, 3, 6 s
    assert [len(o) for o in outs] == [0, 0, 1]                             # the 0 s fix goes once 6 s arrive
    assert stage.kf is not None


def test_invalid_fixes_are_rejected_and_the_path_survives(rng):
    """Negative, singular or asymmetric fix covariances and fixes in another frame are rejected at
    the adapter with a counted reason; the final smoothed path still comes out."""
    t, true_xy, odoms, fixes = _walk(rng, n=60)
    bad = {}
    for k, (i, msg) in enumerate(sorted(fixes.items())[3:7]):
        cov = np.array(msg.pose.covariance).reshape(6, 6)
        if k == 0:
            cov[0, 0] = -4.0                      # negative variance
        elif k == 1:
            cov[:2, :2] = 0.0                     # singular
        elif k == 2:
            cov[0, 1] = 3.0                       # not symmetric
        else:
            msg.header.frame_id = "walk01/odom"   # wrong frame
        msg.pose.covariance = cov.ravel().tolist()
        bad[i] = msg
    fixes = {**fixes, **bad}
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0}))
    poses, paths = _run(stage, odoms, fixes)
    assert stage.diag.rejected["bad_covariance"] == 3 and stage.diag.rejected["wrong_frame"] == 1
    assert "internal_error" not in stage.diag.rejected
    assert len(paths) == 1 and len(path_from_msg(paths[0])[0]) > 50


def test_a_failing_smoother_keeps_the_filtered_track(rng, monkeypatch):
    """An estimator error in the smoother must not lose what was estimated: the segment falls back
    to the filtered estimates, the error is counted."""
    from indoor_loc.pipeline import pdr_kf_stage

    t, true_xy, odoms, fixes = _walk(rng, n=40)
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0}))

    def broken(track):
        raise np.linalg.LinAlgError("Singular matrix")
    monkeypatch.setattr(pdr_kf_stage, "rts_smooth", broken)
    poses, paths = _run(stage, odoms, fixes)
    assert len(paths) == 1 and stage.diag.rejected["smoother_failed"] >= 1
    stamps, xy, _ = path_from_msg(paths[0])
    assert len(stamps) > 30 and np.all(np.isfinite(xy))


def test_long_runs_have_bounded_window_and_path(rng):
    """Fixed-lag smoothing: however long the input, the smoother window and the path stay bounded
    (the 8 h figures are in `indoor-loc bench live`)."""
    n, dt = 4_000, 320_000_000                  # ≈ 21 min of 0.32 s hops, lag 10 s
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 10.0, "smooth_lag_s": 10.0,
                                                            "path_max_poses": 1000, "step_length_m": STEP}))
    x = y = yaw = 0.0
    max_window = 0
    for i in range(n):
        t = 5_000_000_000 + i * dt
        if i % 200 == 0:
            yaw += 0.5
        x += STEP * math.cos(yaw)
        y += STEP * math.sin(yaw)
        stage.process("pdr/odom", odom_to_msg(t, "u/odom", "u/base_link", x, y, yaw, np.eye(3) * 0.1, 2.0, 0.0), 0)
        if i % 10 == 0:
            fix = Fix(t + 1000, np.array([x, y]) + rng.normal(0, 2.0, 2), np.eye(2) * 4.0)
            stage.process("wifi/fix", fix_to_msg(fix), 0)
        max_window = max(max_window, len(stage._epochs))
    assert stage.diag.rejected.total() == 0
    assert max_window <= 2 * 10 / 0.32 + 2 * 10 / 3.2 + 5      # 2 lags of epochs (odom + fix epochs)
    stamps, xy, _ = stage.smoothed()
    assert len(stamps) == 1000 and np.all(np.diff(stamps) > 0)
    assert stamps[-1] == 5_000_000_000 + (n - 1) * dt           # the newest poses are the ones kept
    assert stage.smoother_runs > 100


def _poses_xy(outs):
    return [(fix_from_msg(m).stamp_ns, tuple(fix_from_msg(m).xy)) for topic, m in outs if topic == "pdr_kf/pose"]


def test_odom_hold_keeps_stamp_order_when_fixes_arrive_late(rng):
    """Live, a wifi/fix can reach the node after PDR hops stamped later (a busy machine, a replay
    at 5x). Unheld, such a fix is applied out of stamp order (and counted as late); with
    ``odom_hold_s`` covering the delay, every output equals the in-order (offline) run."""
    t, _, odoms, fixes = _walk(rng, 60)

    def run(delay: int, hold: float):
        st = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0, "odom_hold_s": hold}))
        outs, waiting = [], {}
        for i, od in enumerate(odoms):
            if i in fixes:
                waiting[i + delay] = fixes[i]     # the fix arrives `delay` hops late
            if delay == 0 and i in waiting:
                outs += st.process("wifi/fix", waiting.pop(i), 0)
            outs += st.process("pdr/odom", od, 0)
            if delay and i in waiting:
                outs += st.process("wifi/fix", waiting.pop(i), 0)
        for fix in waiting.values():
            outs += st.process("wifi/fix", fix, 0)
        outs += st.finish()
        return st, outs

    ref_stage, ref = run(0, 0.0)
    late_stage, late = run(2, 0.0)
    held_stage, held = run(2, 3.0)
    assert ref_stage.late_fixes == 0 and late_stage.late_fixes > 0 and held_stage.late_fixes == 0
    assert _poses_xy(late) != _poses_xy(ref)
    assert _poses_xy(held) == _poses_xy(ref)
    paths = [path_from_msg([m for topic, m in o if topic == "pdr_kf/path"][-1]) for o in (ref, held)]
    np.testing.assert_array_equal(paths[0][1], paths[1][1])


def test_pose_heading_from_the_step_vector(rng):
    """pdr_kf/pose carries the heading of the KF's footstep vector with its first-order variance
    (RViz arrows point along the walk), and 'unknown' (1e6) until fixes make it observable."""
    t, true_xy, odoms, fixes = _walk(rng)
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0}))
    poses, _ = _run(stage, odoms, fixes)
    true_yaw = np.arctan2(*np.diff(true_xy, axis=0).T[::-1])
    first = poses[0]
    assert first.pose.covariance[35] == 1e6                       # at the first fix: no heading yet
    known = err = 0
    for m in poses:
        p = pose_from_msg(m)
        var = m.pose.covariance[35]
        i = int(np.searchsorted(t, p.stamp_ns, side="right")) - 1
        if var < 1e5 and 1 <= i < len(true_yaw):
            known += 1
            d = abs((p.yaw - true_yaw[i - 1] + math.pi) % (2 * math.pi) - math.pi)
            err += d > 3 * math.sqrt(var) + 0.35                    # turns make the one-step lag differ
    assert known > len(poses) // 2 and err <= 0.1 * known, (known, err, len(poses))


def test_a_calibrated_odom_heading_starts_the_filter_on_course(rng):
    # odometry whose yaw is the map heading (an importer calibrated the phone's offset): with
    # heading_prior_std_rad the causal filter walks the right way from its first fix; without, its
    # step vector starts at zero and only the fixes turn it
    t, true_xy, odoms, fixes = _walk(rng, n=15, yaw_offset=0.0)
    err = {}
    for sd in (0.0, 0.3):
        stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0, "heading_prior_std_rad": sd}))
        poses, _ = _run(stage, odoms, fixes)
        est = [(p.stamp_ns, p.xy) for p in map(pose_from_msg, poses)]
        idx = np.searchsorted(t, [s for s, _ in est], side="right") - 1
        err[sd] = float(np.mean([np.linalg.norm(xy - true_xy[i]) for (_, xy), i in zip(est, idx)]))
    assert err[0.3] < 0.85 * err[0.0], err


def test_the_floor_follows_the_barometer_and_not_a_lone_fix(rng):
    """pdr_kf/pose z: the floor of consistent fixes; one fix on another floor does not move it, a
    lift ride in baro/pressure does (pose z = the floor's height), and the path's z follows."""
    from indoor_loc.baro.height import pressure_at_height_pa
    from msg_adapters.pressure import pressure_to_msg
    t, true_xy, odoms, fixes = _walk(rng, 60)
    ride = (30, 34)                                   # interval indices of a 3.5 m lift ride
    floor_of = {i: 0.0 for i in fixes}
    floor_of[9] = 3.5                                 # one wrong-floor fix before the ride
    for i in fixes:
        if i > ride[1] + 6:
            floor_of[i] = 3.5
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0}))
    zs, sec = [], 1_000_000_000
    baro = []
    for k in range(0, 600):                           # 10 Hz over the 60 s
        ts = int(t[0]) + k * sec // 10
        h = 1.1 + 3.5 * float(np.clip((ts - t[ride[0]]) / (t[ride[1]] - t[ride[0]]), 0, 1))
        baro.append((ts, pressure_to_msg(ts, "u/imu_link", float(pressure_at_height_pa(h, 101000.0)) + rng.normal(0, 4))))
    b = 0
    for i, od in enumerate(odoms):
        while b < len(baro) and baro[b][0] <= t[i]:
            stage.process("baro/pressure", baro[b][1], 0)
            b += 1
        msgs = stage.process("pdr/odom", od, 0)
        if i in fixes:
            f = fix_from_msg(fixes[i])
            msgs += stage.process("wifi/fix", fix_to_msg(Fix(f.stamp_ns, f.xy, f.cov, z=floor_of[i])), 0)
        zs += [(i, m.pose.pose.position.z) for topic, m in msgs if topic == "pdr_kf/pose"]
    assert stage.diag.rejected == {} or not any(stage.diag.rejected.values())
    z = dict(zs)
    assert all(v == 0.0 for i, v in z.items() if i < ride[0]), z            # the lone fix at 3.5 m did not move it
    assert all(v == 3.5 for i, v in z.items() if i > ride[1] + 6), z        # the ride did (a few s of detection)
    path = [m for topic, m in stage.finish() if topic == "pdr_kf/path"][-1]
    pz = np.array([p.pose.position.z for p in path.poses])
    assert pz[0] == 0.0 and pz[-1] == 3.5


def test_a_floor_change_while_standing_in_a_lift_is_published_at_once(rng):
    """No step and no fix during a lift ride and after it: the floor the barometer sees change is
    published in a pdr_kf/pose stamped at the barometer sample (it used to wait for the next step
    or fix, seconds after the walker arrived)."""
    from indoor_loc.baro.height import pressure_at_height_pa
    from msg_adapters.pressure import pressure_to_msg
    t, true_xy, odoms, fixes = _walk(rng, 20)
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0}))
    sec = 1_000_000_000
    ride0 = int(t[-1]) + 5 * sec                        # 3.5 m up in 3.5 s, 5 s after the last step
    events = [(int(t[i]), "pdr/odom", od) for i, od in enumerate(odoms)]
    events += [(int(t[i]) + 1000, "wifi/fix", fixes[i]) for i in fixes]
    f9 = fix_from_msg(fixes[9])                         # one fix on floor 1: its height is known
    events[len(odoms) + 3] = (f9.stamp_ns, "wifi/fix", fix_to_msg(Fix(f9.stamp_ns, f9.xy, f9.cov, z=3.5)))
    for k in range(int((ride0 - int(t[0])) / sec * 10) + 150):
        ts = int(t[0]) + k * sec // 10
        h = 1.1 + 3.5 * float(np.clip((ts - ride0) / (3.5 * sec), 0, 1))
        p = float(pressure_at_height_pa(h, 101000.0)) + rng.normal(0, 4)
        events.append((ts, "baro/pressure", pressure_to_msg(ts, "u/imu_link", p)))
    poses = []
    for _, topic, msg in sorted(events, key=lambda e: (e[0], e[1])):
        poses += [m for tp, m in stage.process(topic, msg, 0) if tp == "pdr_kf/pose"]
    st = np.array([m.header.stamp.sec * sec + m.header.stamp.nanosec for m in poses])
    z = np.array([m.pose.pose.position.z for m in poses])
    assert np.all(z[st < ride0] == 0.0)
    up = st[z == 3.5]
    assert len(up) and ride0 < up[0] <= ride0 + int(4.5 * sec), (st - ride0) / sec   # arrival at +3.5 s
