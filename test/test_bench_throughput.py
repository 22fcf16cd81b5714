"""`indoor-loc bench throughput`: every message of the bags is counted by each peer and each stage run."""
from __future__ import annotations

import numpy as np

from indoor_loc.bag import BagWriter
from indoor_loc.bench.throughput import format_rows, offline_stage_rates
from msg_adapters.imu import imu_to_msg

S = 1_000_000_000


def test_rates_count_every_message_of_the_same_bags(tmp_path):
    rng = np.random.default_rng(3)
    bag = tmp_path / "in.mcap"
    n = 600                                    # 12 s at 50 Hz, walking-like acceleration
    with BagWriter(bag) as w:
        for k in range(n):
            t = S + k * 20_000_000
            acc = np.array([0.3, 0.1, 9.81 + 2.0 * np.sin(2 * np.pi * 1.8 * k / 50)]) + rng.normal(0, 0.05, 3)
            w.write("/u1/imu/data_raw", imu_to_msg(t, "u1/imu_link", acc, rng.normal(0, 0.01, 3)), t)
    rows = offline_stage_rates([bag], stages=("imu",), scratch=tmp_path)
    by = {r["what"]: r for r in rows}
    assert set(by) == {"mcap raw", "rosbags decode", "run --nodes imu", "run --nodes imu --no-batch"}
    for r in rows:
        assert r["messages"] == n and r["imu_messages"] == n
        assert r["wall_s"] > 0 and r["cpu_s"] > 0 and r["msgs_per_s"] > 0
    assert by["rosbags decode"]["vs_rosbags"] == 1.0
    assert "| run --nodes imu | 600 | 600 |" in format_rows(rows)
    assert not list(tmp_path.glob("tmp*"))     # the scratch outputs are removed
