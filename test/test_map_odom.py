"""The map -> odom correction (pipeline/map_odom.py): its math, the odometry interpolation, and every
estimator stage returning it so that map -> odom -> base_link is the estimate at its stamp."""
from __future__ import annotations

import math

import numpy as np
import pytest

from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.map_odom import OdomTrack, compose, correction, inverse
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage, PdrKfStageParams
from indoor_loc.pipeline.pf_stage import PfStage, PfStageParams
from msg_adapters.tf import pose_yaw_var, tf_message, transform_from_msg, transform_to_msg
from robot_walk import ODOM_IN_MAP, RobotWalk


def test_correction_composes_back_to_the_estimate(rng):
    for _ in range(50):
        est = (rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-math.pi, math.pi))
        odo = (rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-math.pi, math.pi))
        c = correction(est, odo)
        back = compose(c, odo)
        assert np.allclose(back[:2], est[:2]) and math.isclose(math.cos(back[2] - est[2]), 1.0)
        assert np.allclose(compose(inverse(odo), odo), (0, 0, 0), atol=1e-9)
        # a given yaw (the estimate's unknown): positions still agree, the rotation is the one given
        c2 = correction(est, odo, yaw=0.3)
        assert np.allclose(compose(c2, odo)[:2], est[:2]) and math.isclose(c2[2], 0.3)


def test_odom_track_interpolates_and_takes_late_poses():
    tr = OdomTrack(maxlen=4)
    assert tr.at(5) is None
    tr.add(0, (0.0, 0.0, math.pi - 0.1), "u/odom")
    tr.add(10, (10.0, 2.0, -math.pi + 0.1), "u/odom")
    x, y, yaw = tr.at(5)
    assert (x, y) == (5.0, 1.0) and abs(abs(yaw) - math.pi) < 1e-9        # across +-pi the short way
    assert tr.at(-3) == (0.0, 0.0, math.pi - 0.1) and tr.at(99) == (10.0, 2.0, -math.pi + 0.1)
    tr.add(4, (4.0, 0.0, 0.0), "u/odom")                                      # late (stamp order ANY)
    assert list(tr.stamps) == [0, 4, 10] and tr.at(2)[0] == 2.0


def test_transform_adapters_round_trip_and_future_date():
    t = transform_to_msg(5_000_000_000, "map", "alice/odom", 1.5, -2.0, 0.4)
    stamp, parent, child, (x, y, yaw) = transform_from_msg(t)
    assert (stamp, parent, child) == (5_000_000_000, "map", "alice/odom")
    assert (x, y) == (1.5, -2.0) and math.isclose(yaw, 0.4)
    m = tf_message([t], future_dating_ns=500_000_000)
    assert m.transforms[0].header.stamp.sec == 5 and m.transforms[0].header.stamp.nanosec == 500_000_000
    assert t.header.stamp.nanosec == 0                                         # the topic's copy untouched


@pytest.mark.parametrize("which", ["pf", "pdr_kf"])
def test_stage_chain_is_the_estimate_and_near_the_truth(which, tmp_path):
    w = RobotWalk()
    if which == "pf":
        stage = PfStage(params_from_dict(PfStageParams, {"graph_file": str(w.save_graph(tmp_path / "g.graph.yaml")),
                                                         "n_particles": 500}))
    else:
        stage = PdrKfStage(params_from_dict(PdrKfStageParams, {}))
    track = OdomTrack()
    for s, p in w.odom:
        track.add(s, p, "alice/odom")
    poses, corrections = {}, []
    for s, topic, msg in w.messages():
        for t, m in stage.process(topic, msg, s):
            if t == f"{which}/pose":
                poses[pose_yaw_var(m)[0]] = pose_yaw_var(m)[2]
            elif t == f"{which}/map_odom":
                corrections.append(transform_from_msg(m))
    assert len(corrections) > 100 and not stage.diag.rejected
    errs = []
    for stamp, parent, child, c in corrections:
        assert (parent, child) == ("map", "alice/odom")
        chain = compose(c, track.at(stamp))
        assert np.allclose(chain[:2], poses[stamp][:2], atol=1e-9)          # map->odom->base_link = estimate
        errs.append(float(np.hypot(*(np.array(chain[:2]) - w.truth_at(stamp)))))
    assert np.mean(errs) < 1.5
    # the odometry frame's place in the map is found (it drifts 3 % in scale and slowly in heading)
    first_good = corrections[len(corrections) // 4][3]
    assert abs(math.remainder(first_good[2] - ODOM_IN_MAP[2], 2 * math.pi)) < 0.6


def test_backend_corrections_per_user():
    """backend_node's per-user correction: backend/<user>/map_odom composes back to the backend/<user>/pose
    of the same update (the back-end re-optimises, so a later pose at an old stamp may differ)."""
    from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
    w = RobotWalk()
    stage = BackendStage(params_from_dict(BackendParams, {"wifi_source": "fix"}))
    track = OdomTrack()
    for s, p in w.odom:
        track.add(s, p, "alice/odom")
    pairs = []
    for s, topic, msg in w.messages():
        outs = stage.process(topic, msg, s, "alice")
        poses = {pose_yaw_var(m)[0]: pose_yaw_var(m)[2] for t, m in outs if t == "backend/alice/pose"}
        pairs += [(transform_from_msg(m), poses) for t, m in outs if t == "backend/alice/map_odom"]
    assert len(pairs) > 10 and not stage.diag.rejected, stage.diag.rejected
    for (stamp, parent, child, c), poses in pairs:
        assert (parent, child) == ("map", "alice/odom")
        if stamp in poses:                  # (else a pose that waited for the odometry: made in an earlier call)
            assert np.allclose(compose(c, track.at(stamp))[:2], poses[stamp][:2], atol=1e-9)
    assert sum(stamp in poses for (stamp, *_), poses in pairs) > 10
