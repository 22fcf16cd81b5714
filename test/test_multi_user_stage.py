"""Multi-user stages in the Stage / offline-runner layer: one instance for every user namespace,
messages handed over with their user, per-user outputs, merged vs sequential replay."""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
import pytest

from indoor_loc.params import field
from indoor_loc.bag import BagWriter, read_bag
from indoor_loc.contract import Qos
from indoor_loc.errors import ConfigError
from msg_adapters.odom import odom_to_msg
from msg_adapters.path import path_to_msg
from indoor_loc.pipeline import offline, registry
from indoor_loc.pipeline.stage import Port, Stage, namespace_of_user, user_of_namespace

SEC = 1_000_000_000


@dataclass(frozen=True)
class EchoParams:
    offline_order: str = field("merged", "merged or sequential")


class EchoStage(Stage):
    """Remembers (user, stamp) of every pdr/odom; per user publishes its message count as a Path."""
    NODE_NAME = "echo_node"
    PARAMS = EchoParams
    MULTI_USER = True
    log: list = []

    def __init__(self, params, *, namespace=""):
        super().__init__(params, namespace=namespace)
        self.seen: Counter = Counter()
        self.on("pdr/odom", self._on_odom)
        EchoStage.log = []

    def inputs(self):
        return [Port("pdr/odom", "nav_msgs/msg/Odometry", Qos.RELIABLE)]

    def outputs(self):
        return []

    def user_outputs(self):
        return [Port("echo/{user}/count", "nav_msgs/msg/Path", Qos.LATCHED)]

    def offline_order(self):
        return self.params.offline_order

    def _on_odom(self, msg, recv_ns, user):
        stamp = msg.header.stamp.sec * SEC + msg.header.stamp.nanosec
        self.seen[user] += 1
        EchoStage.log.append(("msg", user, stamp))
        return [(f"echo/{user}/count", path_to_msg(np.array([stamp]), np.array([[self.seen[user], 0.0]])))]

    def finish_user(self, user):
        EchoStage.log.append(("finish_user", user, self.seen[user]))
        return []


@pytest.fixture
def echo_registered(monkeypatch):
    monkeypatch.setitem(registry.STAGES, "echo", f"{__name__}:EchoStage")


def _odom(t):
    return odom_to_msg(t, "odom", "base", 0.0, 0.0, 0.0, np.eye(3), 0.0, 0.0)


def _bags(tmp_path):
    """Two users on overlapping clocks, one bag each: alice at 10, 11, 12 s; bob at 10.5, 11.5 s."""
    paths = []
    for user, stamps in (("alice", [10.0, 11.0, 12.0]), ("bob", [10.5, 11.5])):
        p = tmp_path / f"{user}.mcap"
        with BagWriter(p) as w:
            for t in stamps:
                w.write(f"/{user}/pdr/odom", _odom(int(t * SEC)), int(t * SEC))
        paths.append(p)
    return paths


def test_user_names():
    assert user_of_namespace("/walk07") == "walk07" and namespace_of_user("walk07") == "/walk07"
    st = EchoStage(EchoParams())
    assert st.output_port("echo/walk07/count").type == "nav_msgs/msg/Path"
    assert st.output_port("echo//count") is None and st.output_port("other") is None


def test_multi_user_stage_needs_the_user():
    st = EchoStage(EchoParams())
    assert st.process("pdr/odom", _odom(SEC), 0) == []
    assert st.diag.rejected["no_user"] == 1
    assert len(st.process("pdr/odom", _odom(SEC), 0, "alice")) == 1
    assert st.diag.received["alice/pdr/odom"].count == 1


@pytest.mark.parametrize("order", ["merged", "sequential"])
def test_one_instance_sees_every_user_in_the_chosen_order(tmp_path, echo_registered, order):
    bags = _bags(tmp_path)
    out = tmp_path / "out.mcap"
    summary = offline.run_offline(bags, out, nodes=["echo"], progress=False, order=order)
    assert summary.order == order
    msgs = [e for e in EchoStage.log if e[0] == "msg"]
    if order == "merged":      # one stamp order across users
        assert [e[2] for e in msgs] == sorted(e[2] for e in msgs)
        assert [e[1] for e in msgs] == ["alice", "bob", "alice", "bob", "alice"]
    else:                      # alice's whole bag, she finishes, then bob's
        assert [e[1] for e in EchoStage.log] == ["alice"] * 4 + ["bob"] * 3
        assert EchoStage.log[3] == ("finish_user", "alice", 3) and EchoStage.log[-1] == ("finish_user", "bob", 2)
    counts = Counter(m.topic for m in read_bag([out]))
    assert counts["/echo/alice/count"] == 3 and counts["/echo/bob/count"] == 2
    diag = [m.msg.status[0].name for m in read_bag([out]) if m.topic == "/diagnostics"]
    assert set(diag) == {"/echo_node"}                         # one instance, in the root namespace


def test_auto_order_follows_the_stage_params(tmp_path, echo_registered):
    params = tmp_path / "params.yaml"
    params.write_text("echo_node:\n  ros__parameters:\n    offline_order: sequential\n")
    s = offline.run_offline(_bags(tmp_path), tmp_path / "o.mcap", nodes=["echo"], params=params, progress=False)
    assert s.order == "sequential"
    s = offline.run_offline(_bags(tmp_path), tmp_path / "o.mcap", nodes=["echo"], progress=False, overwrite=True)
    assert s.order == "merged"
    with pytest.raises(ConfigError, match="order"):
        offline.run_offline(_bags(tmp_path), tmp_path / "o.mcap", nodes=["echo"], progress=False, order="random")
