"""Each estimator stage with ``motion_source: odom``, offline: a simulated robot's wheel odometry
(20 Hz, its own odom frame) and WiFi in, estimates out, against the robot's true path."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.measurements import Fix
from indoor_loc.params import params_from_dict
from indoor_loc.sim.scenario import T0_NS
from msg_adapters.pose import fix_to_msg, pose_from_msg
from msg_adapters.wifi_scan import scan_to_msg


@pytest.fixture(scope="module")
def robot_world(tmp_path_factory):
    from indoor_loc.graph import save_graph
    from indoor_loc.sim.building import building_graph, sample_building
    from indoor_loc.sim.robot_write import robot_message
    from indoor_loc.sim.scenario import SimConfig, simulate
    from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap, save_radiomap

    d = tmp_path_factory.mktemp("robot")
    run = simulate(sample_building(), SimConfig(walkers=1, robots=1, duration_s=150.0, seed=3))
    r = run.robots[0]
    graph = save_graph(building_graph(run.building), d / "graph.yaml")
    rm = save_radiomap(add_fingerprints(empty_radiomap(), run.survey_xy, run.survey_scans), d / "radiomap")
    rng = np.random.default_rng(0)
    events = [(int(t) + T0_NS, 0, "odom", robot_message(3, r, i, int(t) + T0_NS)) for i, t in enumerate(r.odom.t_ns)]
    scan_ns = np.array([s.stamp_ns for s in r.scans], np.int64) + T0_NS
    for k, s in enumerate(r.scans):
        xy = r.scan_xy[k] + rng.normal(0.0, 1.5, 2)                      # a WiFi fix of 1.5 m per axis
        events.append((int(scan_ns[k]), 1, "wifi/fix", fix_to_msg(Fix(int(scan_ns[k]), xy, np.eye(2) * 2.25))))
        s2 = type(s)(int(scan_ns[k]), s.bssid, s.rssi_dbm, s.freq_mhz, s.ssid, s.age_ms, "robot1/wifi_link", "sim")
        events.append((int(scan_ns[k]), 2, "wifi/scan", scan_to_msg(s2)))
    events.sort(key=lambda e: (e[0], e[1]))
    return {"run": run, "robot": r, "graph": graph, "radiomap": rm, "events": events, "scan_ns": scan_ns}


def _errors(world, outs, topic):
    """Error of the newest estimate at or before each scan (after the first 20 s), m."""
    est = sorted((pose_from_msg(m).stamp_ns, *pose_from_msg(m).xy) for t, m in outs if t == topic)
    a = np.array(est, float)
    sn = world["scan_ns"]
    idx = np.searchsorted(a[:, 0], sn.astype(float), side="right") - 1
    keep = (idx >= 0) & (sn - T0_NS > 20e9)
    return np.hypot(*(a[idx[keep], 1:] - world["robot"].scan_xy[keep]).T), a


def _feed(stage, world, topics, user=None):
    outs = []
    for t, _, topic, msg in world["events"]:
        if topic in topics:
            outs += stage.process(topic, msg, t, user) if user else stage.process(topic, msg, t)
    return outs + (stage.run_finish())


def test_tll_pf_with_robot_odometry(robot_world):
    from indoor_loc.pipeline.pf_stage import PfStage, PfStageParams
    p = params_from_dict(PfStageParams, {"graph_file": str(robot_world["graph"]), "motion_source": "odom",
                                         "n_particles": 500, "smooth": False, "particles_every": 0})
    st = PfStage(p)
    assert [q.topic for q in st.inputs()][0] == "odom"
    outs = _feed(st, robot_world, {"odom", "wifi/fix"})
    e, est = _errors(robot_world, outs, "pf/pose")
    assert not st.diag.rejected, st.diag.rejected
    assert len(est) > 3 * len(robot_world["scan_ns"])        # a pose per increment, not only per fix
    assert e.mean() < 1.3, e.mean()                          # the fixes alone: 1.5 m per axis
    # the same messages to a filter on PDR: the odometry is refused, counted
    st2 = PfStage(params_from_dict(PfStageParams, {"graph_file": str(robot_world["graph"]), "n_particles": 100}))
    _feed(st2, robot_world, {"odom"})
    assert st2.diag.rejected["wrong_motion_source"] == len(robot_world["robot"].odom.t_ns)


def test_pdr_kf_with_robot_odometry(robot_world):
    from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage, PdrKfStageParams
    st = PdrKfStage(params_from_dict(PdrKfStageParams, {"motion_source": "odom"}))
    outs = _feed(st, robot_world, {"odom", "wifi/fix"})
    e, est = _errors(robot_world, outs, "pdr_kf/pose")
    assert not st.diag.rejected, st.diag.rejected
    assert len(est) > 3 * len(robot_world["scan_ns"])
    assert e.mean() < 1.3, e.mean()
    assert st.extra_diagnostics()["odom.increments_message_cov"] != "0"   # the robot's own covariance used


def test_backend_with_robot_odometry(robot_world):
    from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
    st = BackendStage(params_from_dict(BackendParams, {"radiomap": str(robot_world["radiomap"]),
                                                       "motion_source": "odom"}))
    outs = _feed(st, robot_world, {"odom", "wifi/scan"}, user="robot1")
    e, est = _errors(robot_world, outs, "backend/robot1/pose")
    assert not st.diag.rejected, st.diag.rejected
    # the same scans without the robot's motion: WKNN poses only, each on its own
    alone = BackendStage(params_from_dict(BackendParams, {"radiomap": str(robot_world["radiomap"]),
                                                          "motion_source": "odom"}))
    e0, _ = _errors(robot_world, _feed(alone, robot_world, {"wifi/scan"}, user="robot1"), "backend/robot1/pose")
    assert e.mean() < 0.8 * e0.mean(), (e.mean(), e0.mean())
    g = st.graph
    info = g.pdr.view("sqrt_info")
    assert len(info) > 50 and not np.allclose(info, np.sqrt(g.params.pdr_info))   # the odometry's own information


def test_backend_any_takes_each_users_first_motion_topic(robot_world):
    from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
    from msg_adapters.odom import odom_to_msg
    st = BackendStage(params_from_dict(BackendParams, {"radiomap": str(robot_world["radiomap"]),
                                                       "motion_source": "any", "window_poses": 0}))
    assert {p.topic: p.required for p in st.inputs()}.items() >= {"pdr/odom": False, "odom": False}.items()
    ev = [e for e in robot_world["events"] if e[2] == "odom"][:200]
    for t, _, topic, msg in ev:
        st.process(topic, msg, t, "robot1")
    t = ev[-1][0] + 1
    st.process("pdr/odom", odom_to_msg(t, "a/odom", "a/base", 0.0, 0.0, 0.0, np.zeros((3, 3)), 1.0, 0.0), t, "robot1")
    st.process("pdr/odom", odom_to_msg(t, "a/odom", "a/base", 0.0, 0.0, 0.0, np.zeros((3, 3)), 1.0, 0.0), t, "walker")
    assert st.diag.rejected == {"wrong_motion_source": 1}
    assert st.inputs_by_user["robot1"].motion == "odom" and st.inputs_by_user["walker"].motion == "pdr/odom"
