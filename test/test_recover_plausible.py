"""Recovery from plausible but wrong positions (issue #23, docs/recovery.md): a ``wifi/fix`` or an
``initialpose`` inside every contract bound but claiming a precision no such message has, or simply
wrong, must not leave the estimators (``pdr_kf_node``, ``tll_pf``) stuck once true fixes follow.
Seeded synthetic walks through the stages, as the other stage tests."""
from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped

from indoor_loc.fusion.position_trust import FIX_SIGMA_MIN_M, floor_cov
from indoor_loc.measurements import Fix
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage, PdrKfStageParams
from msg_adapters.odom import odom_to_msg
from msg_adapters.pose import fix_to_msg, pose_from_msg
from msg_adapters.time import stamp_from_ns

SEC = 1_000_000_000
STEP = 0.65


def _walk(rng: np.random.Generator, n: int = 90):
    """A walk of 2-step hops (one a second) along an L (30 m east, then north); PDR in an odom frame
    turned by 1 rad; WiFi fixes (sigma 1.5 m, reported covariance 2.25 m²) every 4th hop."""
    yaw = np.where(np.arange(n) < 23, 0.0, math.pi / 2)
    true_xy = np.cumsum(2 * STEP * np.stack([np.cos(yaw), np.sin(yaw)], axis=1), axis=0) + 2.0
    odom_yaw = yaw + 1.0 + np.cumsum(rng.normal(0, 0.01, n))
    oxy = np.cumsum(2 * STEP * np.stack([np.cos(odom_yaw), np.sin(odom_yaw)], axis=1), axis=0)
    t = np.arange(n) * SEC + 5 * SEC
    odoms = [odom_to_msg(int(t[i]), "u/odom", "u/base_link", oxy[i, 0], oxy[i, 1], odom_yaw[i], np.eye(3) * 0.1,
                         1.3, 0.0) for i in range(n)]
    fixes = {i: fix_to_msg(Fix(int(t[i]) + 1000, true_xy[i] + rng.normal(0, 1.5, 2), np.eye(2) * 2.25))
             for i in range(0, n, 4)}
    return t, true_xy, odoms, fixes


def _pose_msg(stamp_ns: int, xy, var: float) -> PoseWithCovarianceStamped:
    m = PoseWithCovarianceStamped()
    m.header.stamp = stamp_from_ns(stamp_ns)
    m.header.frame_id = "map"
    m.pose.pose.position.x, m.pose.pose.position.y = float(xy[0]), float(xy[1])
    m.pose.pose.orientation.w = 1.0
    cov = np.zeros(36)
    cov[0] = cov[7] = var
    cov[14] = cov[21] = cov[28] = cov[35] = 1.0
    m.pose.covariance = cov
    return m


def _run_kf(stage, odoms, fixes, extra: dict[int, list[tuple[str, PoseWithCovarianceStamped]]]):
    """Feed the walk; ``extra[i]``: messages after hop ``i`` (and its fix). Returns {hop: xy}."""
    est = {}
    for i, od in enumerate(odoms):
        for topic, msg in stage.process("pdr/odom", od, 0):
            if topic == "pdr_kf/pose":
                est[i] = pose_from_msg(msg).xy
        for topic, msg in ([("wifi/fix", fixes[i])] if i in fixes else []) + extra.get(i, []):
            stage.process(topic, msg, 0)
    return est


def _err_after(est, true_xy, first: int, last: int) -> float:
    return float(np.mean([np.linalg.norm(est[i] - true_xy[i]) for i in range(first, last) if i in est]))


def test_floor_cov_keeps_the_ellipse_and_raises_the_small_axis():
    c = np.array([[9.0, 0.0], [0.0, 1e-6]])
    f, changed = floor_cov(c, FIX_SIGMA_MIN_M)
    assert changed and np.allclose(f, np.diag([9.0, 1.0]))
    g, changed = floor_cov(np.eye(2) * 2.25, FIX_SIGMA_MIN_M)
    assert not changed and np.allclose(g, np.eye(2) * 2.25)        # a real fix is never changed


def test_pdr_kf_fix_claiming_a_millimetre_is_taken_at_a_metre():
    """A fix 3 m off claiming 1e-6 m² must not pin the filter: counted, and taken at 1 m² — the
    true fixes after it still move the estimate."""
    rng = np.random.default_rng(4)
    t, true_xy, odoms, fixes = _walk(rng)
    k = 40
    bad = fix_to_msg(Fix(int(t[k]) + 2000, true_xy[k] + [3.0, 0.0], np.eye(2) * 1e-6))
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0}))
    _run_kf(stage, odoms[:k + 1], fixes, {k: [("wifi/fix", bad)]})
    stage.process("pdr/odom", odoms[k + 1], 0)           # the fix applied at its place in stamp order
    assert stage.floored == 1
    assert stage.kf is not None and min(np.linalg.eigvalsh(stage.kf.position_cov)) >= 1.0   # 0.48 when taken at 1e-6 m²


def test_pdr_kf_refuses_an_initial_pose_older_than_its_newest_fix():
    """A pose that reaches a busy node late, behind the fixes that followed it (the fault benchmark's
    hostile initial poses, worked off seconds after the valid fixes), is superseded by them: refused
    (``superseded_pose``), the filter untouched. Before: the filter restarted at it, at the present,
    and no later fix came to correct it."""
    rng = np.random.default_rng(6)
    t, true_xy, odoms, fixes = _walk(rng)
    k = 60
    late = _pose_msg(int(t[k - 6]), true_xy[k - 6] + [20.0, 0.0], 0.25)       # older than the fix at k - 4
    params = params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0})
    clean = _run_kf(PdrKfStage(params), odoms, fixes, {})
    stage = PdrKfStage(params)
    hostile = _run_kf(stage, odoms, fixes, {k: [("initialpose", late)]})
    assert stage.diag.rejected["superseded_pose"] == 1 and stage.initial_poses == 0
    assert all(np.allclose(hostile[i], clean[i]) for i in clean)
    ahead = _pose_msg(int(t[-1]) + 3600 * SEC, true_xy[-1] + [20.0, 0.0], 0.25)   # an hour ahead of the stream
    stage.process("initialpose", ahead, 0)
    assert stage.diag.rejected["pose_ahead"] == 1 and stage.initial_poses == 0
    now = _pose_msg(0, true_xy[-1], 0.25)                     # a command (stamp 0) is taken, for now
    stage.process("initialpose", now, 0)
    assert stage.initial_poses == 1


def test_tll_pf_refuses_an_initial_pose_older_than_its_newest_fix(tmp_path):
    from indoor_loc.graph import build_graph, save_graph
    from indoor_loc.pipeline.pf_stage import PfStage, PfStageParams
    xy = np.array([[2, 2], [40, 2], [40, 40]], float)
    graph = save_graph(build_graph(range(3), xy, [(0, 1), (1, 2)]), tmp_path / "l.graph.yaml")
    rng = np.random.default_rng(7)
    t, true_xy, odoms, fixes = _walk(rng)
    stage = PfStage(params_from_dict(PfStageParams, {"graph_file": str(graph), "n_particles": 300}))
    k = 60
    for i in range(k + 1):
        stage.process("pdr/odom", odoms[i], 0)
        if i in fixes:
            stage.process("wifi/fix", fixes[i], 0)
    before = stage.tracker.pf.xy().copy()
    stage.process("initialpose", _pose_msg(int(t[k - 6]), true_xy[k - 6] + [0.0, 20.0], 0.25), 0)
    assert stage.diag.rejected["superseded_pose"] == 1
    assert np.array_equal(stage.tracker.pf.xy(), before)                     # the particles untouched
    outs = stage.process("initialpose", _pose_msg(int(t[k]) + 2000, true_xy[k], 0.01), 0)
    assert [tp for tp, _ in outs if tp == "pf/pose"] and stage.floored == 1   # current: taken, at 0.5 m


def test_pdr_kf_refuses_a_fix_that_comes_long_after_the_odometry_passed_it():
    """A fix worked off late by a busy node (the fault benchmark's hostile fixes were handled up to
    30 s after the valid stream) cannot go at its place in time; applied at the present it pulled the
    estimate back to a past (or wrong) place and, after two such, restarted the filter there. Refused
    (``fix_too_late``) when more than ``fix_late_max_s`` behind the newest odometry."""
    rng = np.random.default_rng(8)
    t, true_xy, odoms, fixes = _walk(rng)
    k = 60
    for i in (52, 56, 60):          # the WiFi queue stalled: the late fixes are the topic's newest
        del fixes[i]
    stale = [("wifi/fix", fix_to_msg(Fix(int(t[k - 8]) + 3000 + j, true_xy[k - 8] + [15.0, 0.0], np.eye(2) * 2.25)))
             for j in range(2)]
    params = params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0})
    clean = _run_kf(PdrKfStage(params), odoms, fixes, {})
    stage = PdrKfStage(params)
    hostile = _run_kf(stage, odoms, fixes, {k: stale})
    assert stage.diag.rejected["fix_too_late"] == 2 and stage.restarts == 0
    assert all(np.allclose(hostile[i], clean[i]) for i in clean)


def test_pdr_kf_scattered_wrong_fixes_do_not_restart_it():
    """Two gated-out fixes in a row restart the filter at the latest (the PDR track left the truth) —
    but only when they agree with each other: two plausible fixes 40 m apart, both far from the
    track, are outliers, not a track gone wrong. Before: the filter restarted at the second one."""
    rng = np.random.default_rng(9)
    t, true_xy, odoms, fixes = _walk(rng)
    k = 60
    bad = [("wifi/fix", fix_to_msg(Fix(int(t[k]) + 2000 + j, true_xy[k] + off, np.eye(2) * 2.25)))
           for j, off in enumerate(([25.0, 0.0], [-15.0, 30.0]))]
    params = params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0})
    clean = _run_kf(PdrKfStage(params), odoms, fixes, {})
    stage = PdrKfStage(params)
    hostile = _run_kf(stage, odoms, fixes, {k: bad})
    assert stage.restarts == 0
    assert _err_after(hostile, true_xy, k, len(odoms)) <= 1.05 * _err_after(clean, true_xy, k, len(odoms))
