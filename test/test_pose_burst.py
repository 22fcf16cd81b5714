"""The rate bound on initial poses (``pose_burst``, :class:`indoor_loc.fusion.position_trust.CommandRate`):
a person gives an initial pose by a press-drag-release on a map, so poses received faster than
``pose_interval_min_s`` after the previous one are a program or a fault, refused before they touch
the estimator; a person's next pose after a pause is obeyed. Both estimators, seeded synthetic walks."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.errors import InvalidInputError
from indoor_loc.fusion.position_trust import POSE_INTERVAL_MIN_S, CommandRate
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage, PdrKfStageParams
from msg_adapters.pose import pose_from_msg
from test_recover_plausible import SEC, _pose_msg, _walk

MS = 1_000_000


def test_a_burst_is_refused_while_it_lasts_and_a_click_after_a_pause_is_obeyed():
    rate = CommandRate(POSE_INTERVAL_MIN_S)
    rate.check(100 * SEC)                                   # the first
    for k in range(1, 200):                                 # 2 s of poses every 10 ms: all refused
        with pytest.raises(InvalidInputError) as err:
            rate.check(100 * SEC + k * 10 * MS)
        assert err.value.reason == "pose_burst"
    rate.check(100 * SEC + 1990 * MS + 600 * MS)            # a pause of 0.6 s: obeyed
    rate.check(0)                                           # no clock: never a burst
    rate.check(50 * SEC)                                    # the clock went back: not a burst
    assert rate.refused == 199
    CommandRate(0.0).check(1)                               # 0: no bound
    CommandRate(0.0).check(1)


def _burst(xy, n: int = 40) -> list:
    """A driver gone wrong: ``n`` stamp-0 poses scattered 15-25 m around ``xy``."""
    rng = np.random.default_rng(11)
    return [_pose_msg(0, np.asarray(xy) + rng.uniform(-25, 25, 2), 0.25) for _ in range(n)]


def test_pdr_kf_obeys_a_person_not_a_burst_after_it():
    """A person's pose, then within the next 0.4 s a burst of poses from elsewhere: the filter stays at
    the person's. Before: each pose of the burst restarted the filter, the last one won."""
    rng = np.random.default_rng(6)
    t, true_xy, odoms, fixes = _walk(rng)
    k = 60
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 0.0}))
    for i in range(k + 1):
        stage.process("pdr/odom", odoms[i], int(t[i]))
    recv = int(t[k]) + 100 * MS
    outs = stage.process("initialpose", _pose_msg(0, true_xy[k], 0.25), recv)
    pose = [m for tp, m in outs if tp == "pdr_kf/pose"][-1]
    assert stage.initial_poses == 1 and pose_from_msg(pose).xy == pytest.approx(true_xy[k])
    for j, m in enumerate(_burst(true_xy[k])):
        stage.process("initialpose", m, recv + (j + 1) * 10 * MS)
    assert stage.diag.rejected["pose_burst"] == 40 and stage.initial_poses == 1
    assert stage.kf is not None and np.linalg.norm(stage.kf.state.x[:2] - true_xy[k]) < 1e-6
    stage.process("initialpose", _pose_msg(0, true_xy[k] + [1.0, 0.0], 0.25), recv + 2 * SEC)   # a pause: obeyed
    assert stage.initial_poses == 2


def test_tll_pf_obeys_a_person_not_a_burst_after_it(tmp_path):
    from indoor_loc.graph import build_graph, save_graph
    from indoor_loc.pipeline.pf_stage import PfStage, PfStageParams
    xy = np.array([[2, 2], [40, 2], [40, 40]], float)
    graph = save_graph(build_graph(range(3), xy, [(0, 1), (1, 2)]), tmp_path / "l.graph.yaml")
    rng = np.random.default_rng(7)
    t, true_xy, odoms, fixes = _walk(rng)
    stage = PfStage(params_from_dict(PfStageParams, {"graph_file": str(graph), "n_particles": 300}))
    k = 60
    for i in range(k + 1):
        stage.process("pdr/odom", odoms[i], int(t[i]))
        if i in fixes:
            stage.process("wifi/fix", fixes[i], int(t[i]))
    recv = int(t[k]) + 100 * MS
    stage.process("initialpose", _pose_msg(0, true_xy[k], 0.25), recv)
    at_click = stage.tracker.pf.xy().copy()
    for j, m in enumerate(_burst(true_xy[k])):
        stage.process("initialpose", m, recv + (j + 1) * 10 * MS)
    assert stage.diag.rejected["pose_burst"] == 40
    assert np.array_equal(stage.tracker.pf.xy(), at_click)                  # the particles untouched


def test_backend_obeys_a_person_not_a_burst_after_it():
    """Each initial pose the back-end obeys ends the user's track and starts a new one: a burst would
    cut the track into 40 pieces. Per user: another user's pose is no burst."""
    from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
    st = BackendStage(BackendParams(window_poses=0, wifi_source="fix", joint=False))
    recv = 100 * SEC
    st.process("initialpose", _pose_msg(5 * SEC, [3.0, 4.0], 0.25), recv, "rs")
    for j, m in enumerate(_burst([3.0, 4.0])):
        st.process("initialpose", m, recv + (j + 1) * 10 * MS, "rs")
    st.process("initialpose", _pose_msg(5 * SEC, [3.0, 4.0], 0.25), recv + 20 * MS, "other")
    assert st.diag.rejected["pose_burst"] == 40 and sum(st.diag.rejected.values()) == 40
    assert len(st.graph.users["rs"].poses) == 1


def test_a_set_pose_request_is_not_held_to_the_rate_bound():
    """``~/set_pose`` is answered (success or not), so a program calling it is told: it is obeyed
    whatever the rate, and a topic pose right after it is judged from it."""
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {}))
    recv = 100 * SEC
    stage.process("initialpose", _pose_msg(0, [3.0, 4.0], 0.25), recv)
    stage.set_pose_call = True
    stage.process("initialpose", _pose_msg(0, [5.0, 4.0], 0.25), recv + 10 * MS)
    stage.set_pose_call = False
    assert stage.initial_poses == 2 and stage.diag.rejected["pose_burst"] == 0
    stage.process("initialpose", _pose_msg(0, [7.0, 4.0], 0.25), recv + 20 * MS)
    assert stage.initial_poses == 2 and stage.diag.rejected["pose_burst"] == 1
