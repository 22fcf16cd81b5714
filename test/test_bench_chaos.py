"""``indoor-loc bench chaos``: the table has its columns, and the figures are what was measured.

The judging is checked on a made-up trial whose counters say what happened (a node that booked fewer
messages than were sent to it has silent losses, one that booked more has an overcount, a process that
exited by itself is a death, a valid output missing after the fault is a sticky failure); one tiny run
over DDS (a clean reference and wifi_fix_node killed and restarted, imu_node beside it) checks the table and that the
bench's own kill is not reported as a death.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from indoor_loc.bench.chaos_faults import SEC, Trial, World, judge
from indoor_loc.bench.chaos_run import Harness, NodeRecord
from indoor_loc.eval.trajectory import Truth

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_000 * SEC


def _world() -> World:
    ts = T0 + np.arange(0, 21) * SEC
    truth = Truth("alice", np.zeros((0, 2, 2)), ts.astype(np.int64), np.stack([np.arange(21.0), np.zeros(21)], 1))
    return World({}, ["alice"], [], T0, T0 + 20 * SEC, {"alice": truth}, {})


def _trial(values: dict[str, dict[str, str]], sent: dict[str, int], poses: dict[str, list[tuple[int, float]]],
           hostile: dict[str, int] | None = None) -> Trial:
    t = Trial("t", 1.0)
    for key, vals in values.items():
        module = {"imu_node": "imu_node", "pdr_kf_node": "pdr_kf_node"}[key.rsplit("/", 1)[-1]]
        rec = NodeRecord(key, module, "/alice")
        rec.settled = vals
        t.nodes[key] = rec
    t.sent = sent
    t.hostile_sent = hostile or {}
    t.outputs = {topic: [(s, x, 0.0, 1.0) for s, x in rows] for topic, rows in poses.items()}
    return t


def test_judge_reports_what_the_counters_and_outputs_say():
    world = _world()
    truth_poses = [(T0 + k * SEC, float(k)) for k in range(21)]
    clean = _trial({"/alice/imu_node": {"in.imu/data_raw.count": "100", "out.pdr/odom.count": "10"},
                    "/alice/pdr_kf_node": {"in.pdr/odom.count": "10"}},
                   {"/alice/imu/data_raw": 100},
                   {"/alice/pdr_kf/pose": truth_poses,
                    "/alice/pdr/odom": [(T0 + k * SEC, 0.0) for k in range(21)]})
    # imu_node: 130 sent (100 valid + 30 hostile), 120 taken + 4 undecodable + 1 lost -> 5 silent;
    # pdr_kf_node: 10 odometry messages sent, 10 taken + 3 lost -> booked 3 beyond what was sent;
    # its poses 0.5 m off after 10 s, and two missing there
    off = [(s, x + (0.5 if s >= T0 + 10 * SEC else 0.0)) for s, x in truth_poses
           if s not in (T0 + 15 * SEC, T0 + 16 * SEC)]
    run = _trial({"/alice/imu_node": {"in.imu/data_raw.count": "120", "rejected.undecodable": "4", "lost.total": "1",
                                      "out.pdr/odom.count": "10"},
                  "/alice/pdr_kf_node": {"in.pdr/odom.count": "10", "lost.total": "3"}},
                 {"/alice/imu/data_raw": 130}, {"/alice/pdr_kf/pose": off,
                                                "/alice/pdr/odom": [(T0 + k * SEC, 0.0) for k in range(21)]},
                 hostile={"/alice/imu/data_raw": 30})
    run.nodes["/alice/pdr_kf_node"].deaths.append("exit 1: boom")
    rows = {r.node: r for r in judge(run, clean, world, from_ns=T0 + 12 * SEC)}
    imu, kf = rows["/alice/imu_node"], rows["/alice/pdr_kf_node"]
    assert (imu.cases, imu.silent, imu.overcount, imu.deaths, imu.sticky) == (30, 5, 0, 0, 0)
    assert imu.accuracy is None                       # imu_node has no pose of its own to score
    assert (kf.cases, kf.silent, kf.overcount, kf.deaths, kf.sticky) == (0, 0, 3, 1, 2)
    assert kf.ref_err_m == pytest.approx(0.0, abs=1e-9) and kf.err_m == pytest.approx(0.5)
    assert any("5 silent" in b for b in imu.broken()) and any("death" in b for b in kf.broken())
    assert any("sticky" in b for b in kf.broken())


def test_a_process_that_exits_by_itself_is_a_death_and_a_bench_kill_is_not():
    from indoor_loc.bench.live import Proc
    died = NodeRecord("/a/imu_node", "imu_node", "/a", proc=Proc([sys.executable, "-c", "raise SystemExit(3)"], {}))
    died.proc.proc.wait(timeout=10)
    fake = types.SimpleNamespace(nodes={died.key: died})
    Harness.check_deaths(fake)                         # type: ignore[arg-type]
    Harness.check_deaths(fake)                         # type: ignore[arg-type]
    assert len(died.deaths) == 1 and died.deaths[0].startswith("exit 3")
    kept = NodeRecord("/a/pdr_kf_node", "pdr_kf_node", "/a",
                      proc=Proc([sys.executable, "-c", "import time; time.sleep(30)"], {}))
    fake = types.SimpleNamespace(nodes={kept.key: kept})
    try:
        Harness.kill(fake, kept.key)                   # type: ignore[arg-type]
        Harness.check_deaths(fake)                     # type: ignore[arg-type]
    finally:
        if kept.proc.proc.poll() is None:
            kept.proc.proc.kill()
    assert kept.deaths == [] and kept.killed_by_bench == 1


COLUMNS = ["fault", "node", "cases tried", "deaths", "hangs", "sticky failures", "silent losses",
           "accuracy after recovery (m, clean m)", "note"]


@pytest.mark.timeout(120)
def test_tiny_run_over_dds(tmp_path, ros_domain):
    """A clean reference and wifi_fix_node killed and restarted (imu_node beside it), 12 s of one walker at 3x."""
    out = tmp_path / "chaos.json"
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), PYTHONUNBUFFERED="1")
    r = subprocess.run([sys.executable, "-m", "indoor_loc.cli", "bench", "chaos", "--faults", "kill",
                        "--kill-nodes", "wifi_fix_node", "--nodes", "imu_node,wifi_fix_node", "--duration", "12",
                        "--rate", "3", "--json", str(out)],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=110)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    head = next(ln for ln in r.stdout.splitlines() if ln.startswith("| fault |"))
    assert [c.strip() for c in head.strip("|").split("|")] == COLUMNS
    res = json.loads(out.read_text())
    rows = {row["node"]: row for row in res["rows"]}
    assert set(rows) == {"/alice/imu_node", "/alice/wifi_fix_node"}
    killed = rows["/alice/wifi_fix_node"]
    assert killed["cases"] == 1 and killed["deaths"] == 0 and killed["silent"] is None
    assert all(row["cases"] == 0 for k, row in rows.items() if k != "/alice/wifi_fix_node")
    # imu_node is fed by the bench alone: every message sent was booked
    assert rows["/alice/imu_node"]["silent"] == 0
    # a broken promise is said on its own line, and only then
    said = [ln for ln in r.stdout.splitlines() if ln.startswith("PROMISE BROKEN")]
    assert len(said) == len(res["broken"])
