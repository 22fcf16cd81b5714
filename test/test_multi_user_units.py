"""The pieces of multi-user nodes without DDS: the stage wrapper against per-user stages, shards,
parameters, the Imu CDR packer and the /diagnostics name reader against rclpy's serialiser."""
from __future__ import annotations

import zlib

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Imu

from indoor_loc.bag.cdr_padding import canonical_cdr
from indoor_loc.errors import ConfigError
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.imu_stage import ImuStage
from indoor_loc.pipeline.multi_user import multi_user, serves, shard_of
from msg_adapters.diagnostics import status_array, status_names_cdr
from msg_adapters.imu import imu_to_msg
from msg_adapters.imu_cdr import imu_cdr

SEC = 1_000_000_000


def _walk(rng, n, t0):
    """n IMU samples at 50 Hz of a walker bouncing at 1.8 Hz (a stepometer counts them)."""
    t = t0 + np.arange(n) * SEC // 50
    z = 9.81 + 2.0 * np.sin(2 * np.pi * 1.8 * (t - t0) * 1e-9) + rng.normal(0, 0.05, n)
    return [imu_to_msg(int(ti), "imu_link", np.array([0.1, 0.0, zi]), rng.normal(0, 0.01, 3)) for ti, zi in zip(t, z)]


def test_wrapper_gives_each_user_its_own_stage_outputs(rng):
    users = {"alice": _walk(rng, 600, 10 * SEC), "bob": _walk(rng, 500, 10 * SEC + 7 * SEC // 1000)}
    M = multi_user(ImuStage)
    multi = M(params_from_dict(M.PARAMS, {}))
    single = {u: ImuStage(params_from_dict(ImuStage.PARAMS, {}), namespace=f"/{u}") for u in users}
    got, want = [], []
    for i in range(600):                     # interleaved, as a node receives them
        for u, msgs in users.items():
            if i < len(msgs):
                got += [(t, canonical_cdr(m)) for t, m in multi.process("imu/data_raw", msgs[i], 0, u)]
                want += [(f"/{u}/{t}", canonical_cdr(m)) for t, m in single[u].process("imu/data_raw", msgs[i], 0)]
    got += [(t, canonical_cdr(m)) for t, m in multi.finish_user("bob")]
    want += [(f"/bob/{t}", canonical_cdr(m)) for t, m in single["bob"].run_finish()]
    assert sum(t.endswith("pdr/odom") for t, _ in want) > 10
    assert got == want
    assert sorted(multi.users) == ["alice"]                 # bob's state dropped when it left
    assert multi.users["alice"].odom_frame == "alice/odom"  # its own namespace's frames
    bad = imu_to_msg(20 * SEC, "imu_link", np.array([0.0, 0.0, 9.81]))
    bad.linear_acceleration.z = float("inf")
    multi.process("imu/data_raw", bad, 0, "carol")
    assert multi.diag.rejected and multi.users["carol"].diag.rejected == multi.diag.rejected
    assert multi.diag.last_error.startswith("carol: ")


def test_shards_are_stable_and_cover_every_user():
    assert shard_of("alice", 4) == shard_of("/alice", 4)            # the name, not the namespace's slash
    names = [f"u{i:03d}" for i in range(400)]
    for count in (1, 2, 3, 7):
        parts = [[n for n in names if shard_of(n, count) == i] for i in range(count)]
        assert sorted(sum(parts, [])) == names                     # no gap, no overlap
        assert min(len(p) for p in parts) > 400 / count * 0.7        # spread
    # the same in every process and Python version (str hash is salted per process): CRC-32
    assert [shard_of(n, 7) for n in ("alice", "bob", "carol", "u042")] == [
        zlib.crc32(n.encode()) % 7 for n in ("alice", "bob", "carol", "u042")]


def test_pattern_and_shard_parameters():
    M = multi_user(ImuStage)
    p = params_from_dict(M.PARAMS, {"user_pattern": "floor2_*", "shard_count": 2, "shard_index": 1})
    mine = [u for u in ("floor2_a", "floor2_b", "floor2_c", "floor2_d", "floor3_a") if serves(p, u)]
    assert mine == [u for u in ("floor2_a", "floor2_b", "floor2_c", "floor2_d") if shard_of(u, 2) == 1]
    with pytest.raises(ConfigError, match="shard_index"):
        params_from_dict(M.PARAMS, {"shard_count": 2, "shard_index": 2})
    with pytest.raises(ConfigError, match="shard_count"):
        params_from_dict(M.PARAMS, {"shard_count": 0})
    with pytest.raises(ConfigError, match="heading_source"):      # the stage's own checks still run
        params_from_dict(M.PARAMS, {"heading_source": "compass"})


def test_imu_cdr_is_the_message_rclpy_serialises(rng):
    for frame in ("", "a", "alice/imu_link", "abcdefgh"):
        for gyro in (None, rng.normal(size=3)):
            for quat, cov in ((None, None), (np.array([0.0, 0.0, 0.6, 0.8]), None),
                              (np.array([0.1, 0.2, 0.3, np.sqrt(0.86)]), np.diag([0.1, 0.2, 0.3]))):
                acc = rng.normal(size=3)
                want = imu_to_msg(1_767_225_600_123_456_789, frame, acc, gyro, quat, cov)
                got = imu_cdr(1_767_225_600_123_456_789, frame, acc, gyro, quat, cov)
                assert deserialize_message(got, Imu) == want
                assert len(got) == len(serialize_message(want))
    with pytest.raises(Exception, match="bad_quaternion|quat"):
        imu_cdr(SEC, "f", np.zeros(3), None, np.array([0.0, 0.0, 0.0, 2.0]))
    with pytest.raises(Exception, match="non-finite"):
        imu_cdr(SEC, "f", np.array([0.0, np.nan, 0.0]))


def test_status_names_read_from_cdr(rng):
    arr = DiagnosticArray()
    arr.header.frame_id = "abc"
    names = []
    for i in range(int(rng.integers(5, 15))):
        name = "/" + "x" * int(rng.integers(0, 9)) + f"/imu_node{i}"
        values = {f"k{j}" * int(rng.integers(1, 4)): "v" * int(rng.integers(0, 7)) for j in range(int(rng.integers(0, 6)))}
        arr.status.append(status_array(name, int(rng.integers(0, 3)), "m" * int(rng.integers(0, 5)), values, 1,
                                       "h" * int(rng.integers(0, 3))).status[0])
        names.append(name)
    assert status_names_cdr(serialize_message(arr)) == names
    assert status_names_cdr(serialize_message(DiagnosticArray())) == []
    with pytest.raises(ValueError):
        status_names_cdr(serialize_message(arr)[:40])
