"""Per-user parameters live over DDS: one multi-user ``pdr_kf_node`` and one multi-user ``tll_pf``
serve a walker on its PDR (``pdr/odom``) and a robot on its wheel odometry (``odom``, by
``-p user_params.robot1.motion_source:=odom``), each user's outputs message for message as its own
per-user stage gives them (configured as its per-user node is, by the params file's ``/robot1/...``
entry); the robot's status shows its overrides."""
from __future__ import annotations

import pytest

from helpers_dds import ros_node, spin_until
from test_multi_user_live import _collect, _diagnostics, _node, _ns, _play
from test_user_params import fusion_inputs, own_stage, sim  # noqa: F401  (sim: the module's fixture)

pytestmark = pytest.mark.timeout(300)

USERS = ("alice", "robot1")


def test_one_node_serves_a_walker_and_an_odometry_robot_as_their_own_nodes(ros_domain, sim):  # noqa: F811
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage
    from indoor_loc.pipeline.pf_stage import PfStage

    msgs = fusion_inputs(sim)
    want: dict[str, list] = {}
    for cls in (PdrKfStage, PfStage):
        own = {u: own_stage(cls, sim["params"], u) for u in USERS}
        for topic, msg, recv in msgs:
            _, user, rel = topic.split("/", 2)
            for t, m in own[user].process(rel, msg, recv):
                want.setdefault(f"/{user}/{t}", []).append(m)
    robot = ("-p", "user_params.robot1.motion_source:=odom")
    nodes = [_node("pdr_kf_node", sim["params"], *robot), _node("tll_pf_node", sim["params"], *robot)]
    try:
        with ros_node("probe") as (node, ex):
            diags = _diagnostics(node)
            topics = {f"/{u}/{k}": PoseWithCovarianceStamped for u in USERS for k in ("pdr_kf/pose", "pf/pose")}
            got = _collect(node, topics)
            _play(node, ex, msgs, nodes, rate=2.0, subscribers=2)
            if not spin_until(ex, lambda: all(len(got[t]) >= len(want.get(t, [])) for t in topics), 60):
                pytest.fail(str(({t: (len(got[t]), len(want.get(t, []))) for t in topics},
                                 [n.output()[-1500:] for n in nodes])))
            for t in topics:
                assert len(want[t]) > 3, t
                assert got[t] == want[t], (t, [_ns(m) for m in got[t][:3]], [_ns(m) for m in want[t][:3]])
            assert spin_until(ex, lambda: all(f"/robot1/{n}" in diags for n in ("pdr_kf_node", "tll_pf")), 15)
            for n in ("pdr_kf_node", "tll_pf"):
                st = diags[f"/robot1/{n}"].values
                assert st.get("user_params") == "motion_source=odom", st
                assert int(st["in.odom.count"]) > 10 and "in.pdr/odom.count" not in st, st
                assert "user_params" not in diags[f"/alice/{n}"].values
    finally:
        for n in nodes:
            n.stop()
