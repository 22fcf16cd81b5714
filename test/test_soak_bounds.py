"""Long runs (docs/benchmarks/soak.md): the back-end's periodic paths go out serialised (their cost
grew with the graph: ~15 us per pose and path as PoseStamped objects), and tll_pf's smoother history
stays within ``smooth_max_mb`` whatever the input rate (its memory followed the rate of steps)."""
from __future__ import annotations

import math

import numpy as np
from rclpy.serialization import deserialize_message
from nav_msgs.msg import Path

from backend_synth import corridor_walk, survey
from indoor_loc.graph import build_graph, save_graph
from indoor_loc.measurements import Fix
from indoor_loc.params import params_from_dict
from indoor_loc.pf.smoother_budget import held_bytes
from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
from indoor_loc.pipeline.pf_stage import PfStage, PfStageParams
from indoor_loc.imu.pdr import Pdr, PdrParams
from msg_adapters.odom import odom_to_msg
from msg_adapters.pose import fix_to_msg
from msg_adapters.wifi_scan import scan_to_msg

WKNN = {"shared_threshold": 0.75, "shared_strict": False}


def _walk_messages(walk):
    pdr = Pdr(PdrParams(step_length_m=0.65))
    out = []
    for _stamp, kind, payload in walk.events:
        if kind == 0:
            p = pdr.update(*payload)
            out.append(("pdr/odom", odom_to_msg(p.stamp_ns, f"{walk.name}/odom", f"{walk.name}/base_link",
                                                p.x, p.y, p.yaw, p.cov, p.speed, p.yaw_rate)))
        else:
            out.append(("wifi/scan", scan_to_msg(payload)))
    return out


def test_backend_periodic_paths_go_out_serialised_and_equal():
    """With raw outputs (every node's stage) each backend/<user>/path is CDR bytes of the very message
    the stage builds otherwise (poses, stamps, floors), not one PoseStamped object per pose."""
    walk = corridor_walk("ann", 2, 58, 0, np.random.default_rng(4))
    msgs = _walk_messages(walk)

    def paths(raw: bool) -> list:
        st = BackendStage(BackendParams(window_poses=10, wknn=WKNN, path_period_s=5.0),
                          survey=survey(0, 60, np.random.default_rng(1)))
        st.raw_outputs = raw
        out = []
        for topic, m in msgs:
            out += [o for t, o in st.process(topic, m, 0, "ann") if t == "backend/ann/path"]
        return out
    raw, plain = paths(True), paths(False)
    assert len(raw) == len(plain) > 3
    assert all(isinstance(b, bytes) for b in raw)
    for b, m in zip(raw, plain):
        assert deserialize_message(b, Path) == m
    assert len(plain[-1].poses) > len(plain[0].poses) > 0


def _loop_graph(tmp_path):
    xy = np.array([[2, 2], [62, 2], [62, 42], [2, 42]], float)      # a 60 x 40 m loop of corridors
    return save_graph(build_graph(range(4), xy, [(0, 1), (1, 2), (2, 3), (3, 0)]), tmp_path / "loop.graph.yaml")


def _fast_odometry(n: int, dt_s: float, seed: int = 5):
    """Walking at 1.3 m/s round the loop, odometry every ``dt_s`` (a robot's rate, not a stepometer's),
    a fix every 4 s."""
    rng = np.random.default_rng(seed)
    out, ox, oy, walked = [], 0.0, 0.0, 0.0
    every_fix = int(round(4.0 / dt_s))
    for i in range(n):
        seg = walked % 200.0
        yaw = 0.0 if seg < 60 else (math.pi / 2 if seg < 100 else (math.pi if seg < 160 else -math.pi / 2))
        d = 1.3 * dt_s
        ox, oy, walked = ox + d * math.cos(yaw), oy + d * math.sin(yaw), walked + d
        t = 5_000_000_000 + int(i * dt_s * 1e9)
        out.append(("pdr/odom", odom_to_msg(t, "u/odom", "u/base_link", ox, oy, yaw, np.eye(3) * 0.1, 1.3, 0.0)))
        if i % every_fix == 0:
            out.append(("wifi/fix", fix_to_msg(Fix(t + 1000, np.array([2 + ox, 2 + oy]) + rng.normal(0, 2.0, 2),
                                                   np.eye(2) * 4.0))))
    return out


def test_pf_smoother_history_stays_within_its_budget_at_any_input_rate(tmp_path):
    """Odometry at 10 Hz for 60 s with a 600 s smoother window: without the budget every step's
    particles stay (≈ 3.4 MB here, and 10x a stepometer's rate is 10x the memory); with
    ``smooth_max_mb`` they stay within it, the newest steps kept, and the smoothed path is still given."""
    graph = _loop_graph(tmp_path)
    msgs = _fast_odometry(600, 0.1)

    def run(max_mb: float) -> PfStage:
        st = PfStage(params_from_dict(PfStageParams, {"graph_file": str(graph), "n_particles": 200,
                                                      "smooth_samples": 5, "seed": 3, "smooth_max_mb": max_mb}))
        for topic, m in msgs:
            st.process(topic, m, 0)
        assert st.diag.rejected.total() == 0
        return st
    unbounded, bounded = run(0.0), run(0.5)
    assert held_bytes(unbounded.tracker) > 3 * 2**20
    held = held_bytes(bounded.tracker)
    assert 0.25 * 2**20 < held <= 0.5 * 2**20 * 1.05      # within the budget (checked every few steps)
    assert int(bounded.extra_diagnostics()["smoother_trimmed"]) > 400
    newest = bounded.tracker.history[-1].stamp_ns
    assert newest == unbounded.tracker.history[-1].stamp_ns
    final = [o for t, o in bounded.finish() if t == "pf/path"]
    assert final and len(final[-1].poses) > 500
