"""msg_adapters/pose_cdr.py against rclpy's serialiser and the correction's reader, and the estimators in
multi-user nodes (raw outputs: poses packed to CDR, the motion message decoded once for the ``map ->
odom`` correction) against the same stages building messages: the same message on every output."""
from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.serialization import deserialize_message, serialize_message

from indoor_loc.errors import InvalidMessageError
from msg_adapters.pose import pose_to_msg
from msg_adapters.pose_cdr import PoseCdr, pose_cdr
from msg_adapters.tf import pose_yaw_var
from msg_adapters.time import MAX_STAMP_NS
from test_user_params import fusion_inputs, own_stage, sim  # noqa: F401  (sim: the module's fixture)


def _cases(rng):
    yaws = [0.0, -0.0, math.pi, -math.pi, 1e-300, -2.5, 7.0] + list(rng.uniform(-4, 4, 30))
    for i, yaw in enumerate(yaws):
        a = rng.normal(size=(2, 2))
        cov = None if i % 5 == 0 else a @ a.T * (-1.0 if i % 7 == 3 else 1.0)
        stamp = [0, MAX_STAMP_NS, 1_700_000_000_123_456_789][i % 3] if i < 6 else int(rng.integers(0, MAX_STAMP_NS))
        frame = ["map", "", "bâtiment_2", "a" * (i % 9)][i % 4]
        yield (stamp, rng.normal(size=2) * 50, yaw, cov), dict(frame_id=frame, yaw_var=[0.1, 3e6, 1e6, 0.0][i % 4],
                                                            z=float(rng.normal() * 3), z_var=abs(float(rng.normal())))


def test_the_bytes_and_the_estimate_are_the_messages(rng):
    n = 0
    for args, kw in _cases(rng):
        got = pose_cdr(*args, **kw)
        msg = pose_to_msg(*args, **kw)
        assert isinstance(got, PoseCdr), (args, kw)
        # the same message (CDR padding bytes are not part of it: rclpy leaves whatever was there)
        assert deserialize_message(bytes(got), PoseWithCovarianceStamped) == msg, (args, kw)
        if (len(kw["frame_id"].encode()) + 1) % 8 == 4:         # no padding: the very bytes
            assert bytes(got) == serialize_message(msg), (args, kw)
        assert got.estimate == pose_yaw_var(msg), (args, kw)
        assert all(math.copysign(1, a) == math.copysign(1, b) for a, b in zip(got.estimate[2], pose_yaw_var(msg)[2]))
        n += 1
    assert n > 30


@pytest.mark.parametrize("args, kw", [
    ((5, [math.nan, 0.0], 0.0, None), {}),
    ((5, [0.0, 0.0], math.inf, None), {}),
    ((5, [0.0, 0.0, 1.0], 0.0, None), {}),
    ((5, [0.0, 0.0], 0.0, np.eye(3)), {}),
    ((-1, [0.0, 0.0], 0.0, None), {}),
    ((MAX_STAMP_NS + 1, [0.0, 0.0], 0.0, None), {}),
])
def test_what_the_packer_does_not_take_is_pose_to_msgs_error(args, kw):
    with pytest.raises(InvalidMessageError) as want:
        pose_to_msg(*args, **kw)
    with pytest.raises(InvalidMessageError) as got:
        pose_cdr(*args, **kw)
    assert got.value.reason == want.value.reason


def test_what_the_packer_does_not_take_is_left_to_pose_to_msg():
    got = pose_cdr(5, [1.0, 2.0], 0.3, [1.0, 0.0, 0.0, 1.0])          # a flat covariance
    assert not isinstance(got, (bytes, bytearray)) and got == pose_to_msg(5, [1.0, 2.0], 0.3, [1.0, 0.0, 0.0, 1.0])
    got = pose_cdr(5, [1.0, 2.0], 0.3, None, z_var=math.nan)           # pose_to_msg does not refuse it
    assert isinstance(got, PoseWithCovarianceStamped) and math.isnan(got.pose.covariance[14])


@pytest.mark.parametrize("which", ["pdr_kf", "pf"])
def test_estimators_give_the_same_bytes_with_raw_outputs(sim, which):  # noqa: F811
    """A walker on PDR and a robot on its odometry: every output of the stage with raw outputs (a
    multi-user node's) is the message the stage building messages gives (the poses, frame "map", no
    CDR padding: the very bytes), the map -> odom corrections included."""
    from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage
    from indoor_loc.pipeline.pf_stage import PfStage
    cls = PdrKfStage if which == "pdr_kf" else PfStage
    msgs = fusion_inputs(sim)
    users = ("alice", "robot1")
    plain = {u: own_stage(cls, sim["params"], u) for u in users}
    raw = {u: own_stage(cls, sim["params"], u) for u in users}
    for st in raw.values():
        st.raw_outputs = True
    got: list = []
    want: list = []
    for topic, msg, recv in msgs:
        _, user, rel = topic.split("/", 2)
        want += [(user, t, serialize_message(m)) for t, m in plain[user].process(rel, msg, recv)]
        got += [(user, t, m if isinstance(m, bytes) else serialize_message(m))
                for t, m in raw[user].process(rel, msg, recv)]
    for user in users:
        want += [(user, t, serialize_message(m)) for t, m in plain[user].run_finish()]
        got += [(user, t, m if isinstance(m, bytes) else serialize_message(m)) for t, m in raw[user].run_finish()]
    topics = {t for _, t, _ in want}
    assert {f"{which}/pose", f"{which}/map_odom"} <= topics, topics
    assert sum(t == f"{which}/map_odom" and u == "robot1" for u, t, _ in want) > 5
    assert [(u, t) for u, t, _ in got] == [(u, t) for u, t, _ in want]
    from indoor_loc.contract import msg_class
    cls_of = {p.topic: msg_class(p.type) for p in plain["alice"].outputs()}
    for (u, t, g), (_, _, w) in zip(got, want):      # (the paths' CDR padding bytes are not the message's)
        assert deserialize_message(g, cls_of[t]) == deserialize_message(w, cls_of[t]), (u, t)
        if t.endswith("pose"):
            assert g == w, (u, t)
