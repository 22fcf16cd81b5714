"""``indoor_loc.bench.backend_run``: one back-end configuration from scratch in a fresh, lean process."""
from __future__ import annotations

import subprocess
import sys
import time

import pytest

from conftest import dataset
from indoor_loc.bench.backend_run import CONFIG_NAMES, READING, STEPS, configs, from_scratch, load, scratch

#: what the measured process must not import: ROS, plotting, the bench and evaluation front ends
HEAVY = ("rclpy", "matplotlib", "indoor_loc.bench.backend", "indoor_loc.pipeline", "indoor_loc.nodes")


def test_fresh_process_reports_its_work_imports_and_memory():
    data = dataset("putmc").parent
    (r,) = scratch(data, "joint, step-length est.", 1, walks=[1, 2], jobs=2)
    assert r["config"] == "joint, step-length est." and r["walks"] == 2 and r["poses"] > 20 and r["jobs"] == 2
    assert r["wall_process_s"] > r["wall_work_s"] > 0 and r["rss_workers_peak_mb"] > 0
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
        scratch(tmp_path, "nope", pycache=tmp_path / "pyc")
    assert list((tmp_path / "pyc").rglob("backend_run*.pyc"))           # byte code written where asked
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


def test_from_scratch_with_workers_gives_the_same_graph_and_counts_their_cpu():
    from indoor_loc.bench.backend import errors, summary

    data = dataset("putmc").parent
    for name in ("separate, step-length est.", "joint, step-length est."):
        params = configs()[name]
        one = from_scratch(data, params, [4, 1, 7], jobs=1)
        c0 = time.process_time()
        two = from_scratch(data, params, [4, 1, 7], jobs=2)
        own_cpu = time.process_time() - c0
        assert one.jobs == 1 and two.jobs == 2 and one.data.walks == two.data.walks == [1, 4, 7]
        a, b = one.graph, two.graph
        assert a.poses.n == b.poses.n > 30
        for col in ("x", "stamp", "user"):
            assert a.poses.view(col).tobytes() == b.poses.view(col).tobytes()
        assert a.step_len.tobytes() == b.step_len.tobytes() and len(a.step_len) == 3
        assert summary(list(errors(one.data, a).values())) == summary(list(errors(two.data, b).values()))
        # the stepometer ran only in the workers, and their CPU time is in the work's
        assert two.cpu_s - own_cpu >= 0.9 * two.data.parts[STEPS][1] > 0
        assert one.cpu_s >= one.data.load_cpu_s > 0


def test_bench_in_process_rows_time_both_and_check_the_poses():
    from indoor_loc.bench.backend import DEFAULT, in_process

    names = ("separate, no step-length est.", DEFAULT)
    rows = in_process(dataset("putmc").parent, 1, jobs=2, walks=[2, 3], names=names)
    assert tuple(rows) == names
    for r in rows.values():
        assert set(r) == {1, 2} and all(0 < v < 60 for t in r.values() for v in t)


def test_time_only_entry_refuses_an_unknown_configuration(capsys):
    from indoor_loc.bench.backend import main

    with pytest.raises(SystemExit) as e:
        main(["--configs", "joint, step-length est.; nope"])
    assert e.value.code == 2 and "unknown configuration(s) ['nope']" in capsys.readouterr().err


def test_a_walk_that_cannot_be_read_stops_the_workers_with_its_error(monkeypatch):
    import multiprocessing

    from indoor_loc.datasets.putmc import Putmc
    from indoor_loc.errors import DatasetError, InvalidInputError

    data = dataset("putmc").parent
    real = Putmc.walk

    def walk(self, n, **kw):                  # patched before the fork: the workers have it too
        if n == 2:
            raise DatasetError("walk 2: acc.txt is damaged")
        if n == 3:
            raise InvalidInputError("acc", "a NaN stamp")
        return real(self, n, **kw)

    monkeypatch.setattr(Putmc, "walk", walk)
    for jobs in (1, 2):
        with pytest.raises(DatasetError, match="walk 2: acc.txt is damaged"):
            from_scratch(data, configs()["separate, no step-length est."], [1, 2, 4], jobs=jobs)
        with pytest.raises(InvalidInputError) as err:
            load(data, [1, 3], jobs=jobs)
        assert (str(err.value), err.value.reason) == ("acc: a NaN stamp", "acc")     # as raised, also from a worker
        assert multiprocessing.active_children() == []


def _sigint_in_worker(n: int) -> tuple[bool, int, dict]:
    """Stands in for a walk's front end: whether this process ignores SIGINT, and its pid."""
    import os
    import signal
    return signal.getsignal(signal.SIGINT) == signal.SIG_IGN, os.getpid(), {}


def test_the_workers_leave_ctrl_c_to_the_process_that_forked_them(monkeypatch):
    """Ctrl-C reaches the whole process group: the workers ignore it and the forking process, which
    takes it, ends them — a worker interrupted while holding the task queue's lock would leave
    ``Pool.terminate`` waiting for it for ever."""
    import multiprocessing
    import os
    import signal

    from indoor_loc.bench import backend_run

    monkeypatch.setattr(backend_run, "_front_end", _sigint_in_worker)      # before the fork: the workers run it
    with backend_run._FrontEnd(None, [1, 2, 3, 4], jobs=2) as front:
        got = [(ignored, pid) for _, ignored, pid, _ in front.results()]
    assert len(got) == 4 and all(ignored for ignored, _ in got), got
    assert os.getpid() not in {pid for _, pid in got}
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler    # this process still takes Ctrl-C
    assert multiprocessing.active_children() == []
