"""Per-user parameters of multi-user nodes (``user_params``, indoor_loc/pipeline/user_params.py): which
entries apply to a user and in what order, start-up checks, and a multi-user stage serving a walker on
PDR and a robot on its wheel odometry (``motion_source: odom``, another input port) exactly as each
one's own per-user stage. Live over DDS: test_user_params_live.py."""
from __future__ import annotations

import dataclasses

import pytest

from indoor_loc.errors import ConfigError
from indoor_loc.contract import Qos
from indoor_loc.params import load_params_file, params_for_node, params_from_dict, require
from indoor_loc.pipeline.multi_user import multi_user
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage
from indoor_loc.pipeline.pf_stage import PfStage
from indoor_loc.pipeline.stage import Port, Stage
from indoor_loc.pipeline.user_params import matching_entries, overrides_for


def test_entries_apply_patterns_shorter_first_then_the_exact_name():
    up = {"robot1": {"n_particles": 300}, "r*": {"n_particles": 100, "smooth": False},
          "robot*": {"n_particles": 200}, "walker?": {"smooth": False}}
    assert matching_entries("robot1", up) == ["r*", "robot*", "robot1"]
    assert overrides_for("robot1", up) == {"n_particles": 300, "smooth": False}
    assert overrides_for("robot2", up) == {"n_particles": 200, "smooth": False}
    assert overrides_for("walker1", up) == {"smooth": False}
    assert overrides_for("alice", up) == {}
    # nested groups flatten to dotted names (as a params file's)
    assert overrides_for("robot1", {"robot1": {"odom": {"min_distance_m": 0.2}}}) == {"odom.min_distance_m": 0.2}


def _multi(cls, **values):
    M = multi_user(cls)
    return M(params_from_dict(M.PARAMS, values))


def test_a_users_overrides_give_it_its_own_ports_and_parameters():
    m = _multi(PdrKfStage, user_params={"robot*": {"motion_source": "odom"}, "robot2": {"odom": {"min_distance_m": 0.3}}})
    assert [p.topic for p in m.user_inputs("alice")][0] == "pdr/odom"
    assert [p.topic for p in m.user_inputs("robot1")][0] == "odom"
    assert {p.topic for p in m.inputs()} >= {"pdr/odom", "odom", "wifi/fix"}
    assert m.user_stage("robot2").params.odom.min_distance_m == 0.3
    assert m.user_stage("robot2").params.motion_source == "odom"
    assert m.user_stage("robot1").params.odom.min_distance_m == PdrKfStage.PARAMS().odom.min_distance_m
    assert m.user_stage("alice").params.motion_source == "pdr"
    assert m.user_params_text("robot2") == "motion_source=odom, odom.min_distance_m=0.3"
    assert m.user_params_text("alice") == ""
    # one template per distinct set of overrides: the node's, robot*'s, robot2's (robot* + its own)
    assert len(m.templates) == 3


@pytest.mark.parametrize("entry, words", [
    ({"robot1": {"motion_sauce": "odom"}}, ["user_params.robot1", "motion_sauce"]),
    ({"robot1": {"motion_source": "wheels"}}, ["user_params.robot1", "motion_source"]),
    ({"robot*": {"shard_count": 2}}, ["user_params.robot*", "shard_count"]),
    ({"robot1": "odom"}, ["user_params.robot1", "mapping"]),
])
def test_bad_entries_fail_the_start_naming_the_entry(entry, words):
    with pytest.raises(ConfigError) as err:
        _multi(PdrKfStage, user_params=entry)
    assert all(w in str(err.value) for w in words), err.value


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> dict:
    from indoor_loc.commands.sim import generate
    from indoor_loc.sim.scenario import SimConfig
    from indoor_loc.sim.walker import ImuParams
    from indoor_loc.sim.rf import ScannerParams
    cfg = SimConfig(walkers=1, robots=1, duration_s=16.0, seed=7, imu=dataclasses.replace(ImuParams(), rate_hz=50.0),
                    scanner=dataclasses.replace(ScannerParams(), period_s=2.5))
    return generate(tmp_path_factory.mktemp("up") / "sim", cfg, quiet=True)


def fusion_inputs(sim) -> list:
    """(full topic, message, stamp ns) of alice's pdr/odom and wifi/fix (its own front-end stages) and
    robot1's odom and wifi/fix, in stamp order, each user's from its first motion message on."""
    from indoor_loc.bag import read_bag
    from indoor_loc.pipeline.imu_stage import ImuStage
    from indoor_loc.pipeline.wifi_fix_stage import WifiFixStage
    out = []
    front = {"imu/data_raw": ImuStage, "imu/mag": ImuStage, "wifi/scan": WifiFixStage}
    stages: dict = {}
    for m in read_bag([sim["bag"]]):
        if m.topic.count("/") < 2:
            continue
        _, user, rel = m.topic.split("/", 2)
        if user == "robot1" and rel == "odom":
            out.append((m.topic, m.msg, m.stamp_ns))
        elif rel in front and user in ("alice", "robot1"):
            cls = front[rel]
            st = stages.get((user, cls))
            if st is None:
                st = stages[(user, cls)] = own_stage(cls, sim["params"], user)
            for t, msg in st.process(rel, m.msg, m.stamp_ns):
                if t in ("pdr/odom", "wifi/fix"):
                    out.append((f"/{user}/{t}", msg, msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec))
    out.sort(key=lambda m: m[2])
    first = {u: min(s for t, _, s in out if t.split("/")[1] == u and t.endswith("odom")) for u in ("alice", "robot1")}
    return [m for m in out if m[2] >= first[m[0].split("/")[1]]]


def own_stage(cls, params_file, user: str):
    """The user's own per-user stage, configured by the params file as its per-user node is
    (``/robot1/tll_pf``: motion_source odom)."""
    vals = params_for_node(load_params_file(params_file), cls.NODE_NAME, f"/{user}")
    return cls(params_from_dict(cls.PARAMS, vals), namespace=f"/{user}")


def _ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


@pytest.mark.parametrize("cls", [PdrKfStage, PfStage])
def test_one_stage_serves_a_walker_and_an_odometry_robot_as_their_own_stages(sim, cls):
    msgs = fusion_inputs(sim)
    assert {t for t, _, _ in msgs} == {"/alice/pdr/odom", "/alice/wifi/fix", "/robot1/odom", "/robot1/wifi/fix"}
    base = params_for_node(load_params_file(sim["params"]), cls.NODE_NAME, "")
    assert base.get("motion_source", "pdr") == "pdr"            # the robot's comes from user_params alone
    M = multi_user(cls)
    multi = M(params_from_dict(M.PARAMS, {**base, "user_params": {"robot*": {"motion_source": "odom"}}}))
    own = {u: own_stage(cls, sim["params"], u) for u in ("alice", "robot1")}
    assert own["robot1"].params.motion_source == "odom"
    got: dict = {}
    want: dict = {}
    for topic, msg, recv in msgs:
        _, user, rel = topic.split("/", 2)
        for t, m in multi.process(rel, msg, recv, user):
            got.setdefault(t, []).append(m)
        for t, m in own[user].process(rel, msg, recv):
            want.setdefault(f"/{user}/{t}", []).append(m)
    out = cls.NODE_NAME == "tll_pf" and "pf/pose" or "pdr_kf/pose"
    for user in own:
        assert len(want[f"/{user}/{out}"]) > 5
        assert got[f"/{user}/{out}"] == want[f"/{user}/{out}"], user
    assert sum(multi.users["robot1"].diag.received[t].count for t in ("odom",)) > 10
    assert not multi.diag.rejected, multi.diag.rejected



@dataclasses.dataclass(frozen=True)
class _LoHi:
    lo: float = 0.0
    hi: float = 1.0

    def validate(self) -> None:
        require(self.lo <= self.hi, "_LoHi", "lo", "<= hi", self.lo)


class _LoHiStage(Stage):
    NODE_NAME = "lohi"
    PARAMS = _LoHi

    def __init__(self, params, *, namespace: str = "") -> None:
        super().__init__(params, namespace=namespace)
        self.on("x", lambda msg, recv_ns: [])

    def inputs(self):
        return [Port("x", "std_msgs/msg/String", Qos.RELIABLE)]

    def outputs(self):
        return []


def test_a_user_whose_patterns_are_not_valid_together_is_refused_and_said():
    """Each entry is valid alone (checked at start-up); a user matching both gets lo 0.5 > hi 0.2: it is
    not served, the stage says so once and its status warns (never a crash of the node)."""
    m = _multi(_LoHiStage, user_params={"a*": {"lo": 0.5}, "*b": {"hi": 0.2}})
    assert m.serves("ax") and m.user_stage("ax").params.lo == 0.5
    assert m.serves("xb") and m.user_stage("xb").params.hi == 0.2
    assert not m.serves("ab")
    assert not m.serves("ab")
    said = m.take_notices()
    assert len(said) == 1 and "'ab'" in said[0] and "lo" in said[0], said
    extra = m.extra_diagnostics()
    assert extra["users.refused"] == "ab" and "not served" in extra["warning"]
