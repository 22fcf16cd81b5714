"""``indoor_loc.bench.backend_run``: one back-end configuration from scratch in a fresh, lean process."""
from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import dataset
from indoor_loc.bench.backend_run import CONFIG_NAMES, READING, STEPS, configs, load, scratch

#: what the measured process must not import: ROS, plotting, the bench and evaluation front ends
HEAVY = ("rclpy", "matplotlib", "indoor_loc.bench.backend", "indoor_loc.pipeline", "indoor_loc.nodes")


def test_fresh_process_reports_its_work_imports_and_memory():
    data = dataset("putmc").parent
    (r,) = scratch(data, "joint, step-length est.", 1, walks=[1, 2])
    assert r["config"] == "joint, step-length est." and r["walks"] == 2 and r["poses"] > 20
    # the process's CPU time holds start-up, imports and the work, each measured apart
    assert 0 < r["cpu_front_s"] < r["cpu_work_s"]
    assert r["cpu_process_s"] >= r["cpu_start_s"] + r["cpu_imports_s"] + r["cpu_work_s"] - 0.02
    # peak memory since this process started (not the parent's, which getrusage would report)
    assert r["rss_start_mb"] < 40 < r["rss_imports_mb"] <= r["rss_peak_mb"] < 400
    assert not [m for m in r["modules"] if m.startswith(HEAVY)]


def test_unknown_configuration_is_refused_with_the_known_ones(tmp_path):
    res = subprocess.run([sys.executable, "-m", "indoor_loc.bench.backend_run", str(tmp_path), "nope"],
                         capture_output=True, text=True, check=False)
    assert res.returncode == 2
    assert "unknown configuration 'nope'" in res.stderr and "separate, step-length est." in res.stderr
    with pytest.raises(RuntimeError, match="failed"):
        scratch(tmp_path, "nope")
    assert list(configs()) == list(CONFIG_NAMES)


def test_front_end_in_two_processes_gives_the_same_events_and_counts_their_cpu():
    data = dataset("putmc").parent
    one, two = load(data, [3, 1, 2]), load(data, [3, 1, 2], jobs=2)
    assert one.walks == two.walks == [1, 2, 3]
    for n in one.walks:
        a, b = one.events[n], two.events[n]
        for col in ("t_start", "t_end", "steps", "yaw"):
            assert getattr(a, col).tobytes() == getattr(b, col).tobytes()
        assert [s.stamp_ns for s in a.scans] == [s.stamp_ns for s in b.scans]
        assert all(x.tobytes() == y.tobytes() for x, y in zip(one.truth[n], two.truth[n]))
    assert one.survey.rssi_dbm.tobytes() == two.survey.rssi_dbm.tobytes()
    # the workers' CPU time is counted: the stepometer ran only in them
    assert set(two.parts) == {READING, STEPS}
    assert two.parts[STEPS][1] > 0.2 * one.parts[STEPS][1]
    assert two.load_cpu_s > two.parts[STEPS][1]
