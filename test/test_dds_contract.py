"""Every contract message type crosses DDS between two processes under /alice with the contract
QoS, and arrives with exactly the values it was built from (checked with the msg_adapters).

Latched topics (transient_local) are published once by the sender *before* the receiver
subscribes to them: the late subscriber must still get them, like ``amcl_pose`` / maps.
"""
from __future__ import annotations

import signal
import sys

import pytest

from helpers_dds import PEERS, python_peer, ros_node, spin_until
from indoor_loc.contract import TOPICS, Qos, join_ns, msg_class
from indoor_loc.nodes.base import qos_profile

sys.path.insert(0, str(PEERS))
from contract_messages import ALL_TOPICS, NAMESPACE, build, check  # noqa: E402

# a bound for a hung test, above the sum of a test's condition deadlines (which a loaded machine may
# use up one after another), not an expected duration
pytestmark = pytest.mark.timeout(180)


def test_every_contract_topic_has_a_test_message():
    assert set(ALL_TOPICS) == set(TOPICS)
    for t in ALL_TOPICS:
        assert isinstance(build(t), msg_class(TOPICS[t].type)), t
        check(t, build(t))


def test_qos_roles_cover_volatile_latched_and_best_effort():
    roles = {TOPICS[t].qos for t in ALL_TOPICS}
    assert {Qos.SENSOR, Qos.RELIABLE, Qos.LATCHED, Qos.BEST_EFFORT} <= roles
    assert TOPICS["wifi/fix"].qos == Qos.RELIABLE and TOPICS["pf/pose"].qos == Qos.LATCHED


def test_contract_over_dds(ros_domain):
    sender = python_peer("contract_sender.py", "--timeout", "120")     # stopped by SIGINT once checked
    received: dict[str, list] = {t: [] for t in ALL_TOPICS}
    try:
        with ros_node("contract_receiver") as (node, ex):
            def sub(topic: str) -> None:
                node.create_subscription(msg_class(TOPICS[topic].type), join_ns(NAMESPACE, topic),
                                         received[topic].append, qos_profile(TOPICS[topic].qos))

            latched = [t for t in ALL_TOPICS if TOPICS[t].qos == Qos.LATCHED]
            volatile = [t for t in ALL_TOPICS if t not in latched]
            for t in volatile:
                sub(t)
            line = sender.wait_line(r"^LATCHED_SENT", timeout=60)
            assert line is not None, f"sender never published:\n{sender.output()}"
            assert sorted(line.split()[1:]) == sorted(latched)
            for t in latched:       # subscribe only now: a late subscriber
                sub(t)
            ok = spin_until(ex, lambda: all(received.values()), timeout=60)
            missing = [t for t, v in received.items() if not v]
            assert ok, f"nothing received on {missing}\n{sender.output()}"
            for t in ALL_TOPICS:
                check(t, received[t][0])
            for t in latched:       # published once: exactly one copy reaches the late subscriber
                assert len(received[t]) == 1, (t, len(received[t]))
            full = {t: join_ns(NAMESPACE, t) for t in ALL_TOPICS}
            assert full["imu/data_raw"] == "/alice/imu/data_raw" and full["/clock"] == "/clock"
        sender.signal(signal.SIGINT)
        assert sender.wait(timeout=30) == 0
        assert "SENDER_DONE" in sender.output()
    finally:
        sender.stop()
