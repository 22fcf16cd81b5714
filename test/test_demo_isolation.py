"""The demo stays on its machine (localhost discovery, an unused domain unless the user chose), the
player waits for consumers by name, and input counts are reported beside the scores."""
from __future__ import annotations

import pytest

from indoor_loc.dds_isolation import bound_udp_ports, domain_in_use, isolated_env
from indoor_loc.demo_inputs import InputCount, format_inputs
from indoor_loc.errors import ConfigError
from indoor_loc.nodes.consumers import Consumers, met_by_observers, missing_consumers


def test_isolated_env_picks_localhost_and_the_first_domain_no_local_socket_uses():
    # a participant in domain 100 binds 7410 + 250 * 100 (+2 per participant); 101 is free
    env, said = isolated_env({}, ports={7410 + 250 * 100 + 2, 5353})
    assert env == {"ROS_DOMAIN_ID": "101", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    assert "ROS_DOMAIN_ID=101" in said and "nothing leaves this machine" in said
    assert domain_in_use(100, {32410}) and not domain_in_use(100, {32650})     # 7400 + 250 * 101 = 32650


def test_isolated_env_keeps_what_the_user_set():
    env, said = isolated_env({"ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}, ports=set())
    assert env == {"ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}
    assert "ROS_DOMAIN_ID=7 (yours)" in said and "discovery SUBNET (yours)" in said


def test_bound_udp_ports_reads_proc_net(tmp_path):
    (tmp_path / "udp").write_text("  sl  local_address rem_address\n   0: 0100007F:E614 00000000:0000 07\n")
    (tmp_path / "udp6").write_text("  sl  local_address\n   1: 00000000000000000000000000000000:1F4A 0000\n")
    assert bound_udp_ports(tmp_path) == {0xE614, 0x1F4A}
    assert bound_udp_ports(tmp_path / "absent") == set()


def test_consumers_by_relative_or_full_topic_and_node_name():
    c = Consumers(["imu/data_raw=imu_node", "wifi/scan=wifi_fix_node,/backend_node", "/bob/imu/mag=imu_node"])
    assert c("/alice/imu/data_raw") == ("imu_node",) and c("/alice/wifi/scan") == ("wifi_fix_node", "/backend_node")
    assert c("/bob/imu/mag") == ("imu_node",) and c("/alice/imu/mag") == ()
    assert c.unused(["/alice/imu/data_raw", "/alice/wifi/scan"]) == ["/bob/imu/mag"]
    subs = [("view", "/"), ("recorder", "/"), ("wifi_fix_node", "/alice")]
    assert missing_consumers(("wifi_fix_node", "/backend_node"), subs) == ["/backend_node"]
    assert missing_consumers(("imu_node",), [("imu_node", "/alice")]) == []
    for bad in ("imu/data_raw", "imu/data_raw=", "=imu_node", "imu/data_raw=imu node"):
        with pytest.raises(ConfigError, match="play.consumers"):
            Consumers([bad])


def test_input_counts_are_printed_complete_or_with_what_was_lost():
    ok = [InputCount("alice", "imu/data_raw", "imu_node", 1200, 1200, 0, 0)]
    assert format_inputs(ok).startswith("inputs: every played message reached its node (1200 messages")
    short = ok + [InputCount("bob", "imu/data_raw", "imu_node", 1200, 929, 271, 271),
                  InputCount("bob", "wifi/scan", "wifi_fix_node", 15, None, 0, 0)]
    text = format_inputs(short)
    assert "NOT complete" in text and "/bob/imu/data_raw: played 1200, /bob/imu_node 929 received" in text
    assert "lost 271, of which published before its subscription matched 271" in text and "no status recorded" in text
    assert "/alice/" not in text


def test_a_count_met_only_by_the_view_or_the_recorder_is_noticed():
    assert met_by_observers(1, [("view", "/")])
    assert met_by_observers(2, [("view", "/"), ("recorder", "/"), ("imu_node", "/alice")])
    assert not met_by_observers(1, [("view", "/"), ("imu_node", "/alice")])
    assert not met_by_observers(1, []) and not met_by_observers(0, [("view", "/")])
