"""Long runs: the path histories of tll_pf and pdr_kf_node hold a fixed number of bytes however long
the input (pipeline/path_store.py), and publish the same paths as before."""
from __future__ import annotations

import gc
import math
import tracemalloc

import numpy as np
import pytest

from indoor_loc.graph import build_graph, save_graph
from indoor_loc.measurements import Fix
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline import pf_stage as pf_mod
from indoor_loc.pipeline.path_store import PathStore
from indoor_loc.pipeline.pdr_kf_stage import PdrKfStage, PdrKfStageParams
from indoor_loc.pipeline.pf_stage import PfStage, PfStageParams
from msg_adapters.odom import odom_to_msg
from msg_adapters.path import path_from_msg
from msg_adapters.pose import fix_to_msg

STEP = 0.65
DT = 320_000_000          # a stepometer hop every 0.32 s


def test_path_store_keeps_the_newest_cap_poses_in_order_and_counts_the_rest():
    s = PathStore(5)
    nbytes = s.nbytes
    s.extend(np.arange(3), np.zeros((3, 2)), np.zeros(3), np.zeros(3))
    s.extend(np.arange(3, 7), np.column_stack([np.arange(3, 7), -np.arange(3, 7)]), np.arange(3, 7) * 0.1, np.ones(4))
    st, xy, yaw, z = s.arrays()
    assert st.tolist() == [2, 3, 4, 5, 6] and xy[-1].tolist() == [6, -6] and yaw[1] == pytest.approx(0.3)
    assert z.tolist() == [0, 1, 1, 1, 1] and s.dropped == 2 and len(s) == 5
    s.extend(np.arange(10, 22), np.zeros((12, 2)), np.zeros(12), np.zeros(12))     # more than it holds at once
    assert s.arrays()[0].tolist() == [17, 18, 19, 20, 21] and s.dropped == 2 + 5 + 7
    assert s.nbytes == nbytes                                                        # never grows


def _traced_growth(feed, first: int, then: int) -> int:
    """Bytes still allocated after ``feed(k)`` for k in [first, first + then) that were not after
    the first ``first`` calls (what the stage keeps per input once it has run a while)."""
    tracemalloc.start()
    try:
        for k in range(first):
            feed(k)
        gc.collect()
        before = tracemalloc.get_traced_memory()[0]
        for k in range(first, first + then):
            feed(k)
        gc.collect()
        return tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()


def _kf_feed(stage: PdrKfStage, rng: np.random.Generator):
    state = {"x": 0.0, "y": 0.0, "yaw": 0.0}

    def feed(i: int) -> None:
        t = 5_000_000_000 + i * DT
        if i % 200 == 0:
            state["yaw"] += 0.5
        state["x"] += STEP * math.cos(state["yaw"])
        state["y"] += STEP * math.sin(state["yaw"])
        stage.process("pdr/odom", odom_to_msg(t, "u/odom", "u/base_link", state["x"], state["y"], state["yaw"],
                                              np.eye(3) * 0.1, 2.0, 0.0), 0)
        if i % 10 == 0:
            fix = Fix(t + 1000, np.array([state["x"], state["y"]]) + rng.normal(0, 2.0, 2), np.eye(2) * 4.0)
            stage.process("wifi/fix", fix_to_msg(fix), 0)
    return feed


def test_pdr_kf_path_history_does_not_grow_with_the_input():
    """1 500 more hops (8 min of walking) once its windows (smoother, map->odom odometry) are full: it keeps
    about the per-message timings of its diagnostics (≈ 32 bytes each), not ~190 bytes per final
    pose as a deque of tuples did (≥ 280 kB here)."""
    stage = PdrKfStage(params_from_dict(PdrKfStageParams, {"smooth_period_s": 10.0, "smooth_lag_s": 10.0,
                                                            "step_length_m": STEP}))
    grew = _traced_growth(_kf_feed(stage, np.random.default_rng(3)), 2100, 1500)
    assert stage.diag.rejected.total() == 0 and len(stage._final) > 3000
    assert grew < 150_000, grew


@pytest.fixture
def graph_file(tmp_path):
    xy = np.array([[2, 2], [62, 2], [62, 42], [2, 42]], float)      # a 60 x 40 m loop of corridors
    g = build_graph(range(4), xy, [(0, 1), (1, 2), (2, 3), (3, 0)])
    return save_graph(g, tmp_path / "loop.graph.yaml")


def _pf_messages(n: int, seed: int = 5):
    """A walk around the loop: a 2-step hop every second, a fix every 4th."""
    rng = np.random.default_rng(seed)
    out = []
    ox = oy = 0.0
    walked = 0.0
    for i in range(n):
        seg = walked % 200.0
        yaw = 0.0 if seg < 60 else (math.pi / 2 if seg < 100 else (math.pi if seg < 160 else -math.pi / 2))
        ox += 2 * STEP * math.cos(yaw)
        oy += 2 * STEP * math.sin(yaw)
        walked += 2 * STEP
        t = 5_000_000_000 + i * 1_000_000_000
        out.append(("pdr/odom", odom_to_msg(t, "u/odom", "u/base_link", ox, oy, yaw, np.eye(3) * 0.1, 1.3, 0.0)))
        if i % 4 == 0:
            out.append(("wifi/fix", fix_to_msg(Fix(t + 1000, np.array([2 + ox, 2 + oy]) + rng.normal(0, 2.0, 2),
                                                   np.eye(2) * 4.0))))
    return out


def _pf(graph_file, **kw) -> PfStage:
    return PfStage(params_from_dict(PfStageParams, {"graph_file": str(graph_file), "n_particles": 200,
                                                    "smooth_window_s": 20.0, "seed": 3, **kw}))


def test_pf_estimate_history_does_not_grow_with_the_input(graph_file):
    """Beyond its smoother's window, tll_pf keeps a fixed number of bytes for its path: 600 more
    messages (≈ 600 poses) cost the per-message timings of its diagnostics (≈ 20 kB), its map->odom
    odometry track (bounded at 2 000; ≈ 85 kB here) and at most ARCHIVE_EVERY estimates not moved yet
    (≤ 120 kB), not ~460 bytes per pose on top as the tracker's list of estimates did (≈ 450 kB)."""
    st = _pf(graph_file)
    msgs = _pf_messages(560)            # 700 messages: 100 to fill its smoother window, 600 measured

    def feed(k: int) -> None:
        st.process(*msgs[k], 0)
    grew = _traced_growth(feed, len(msgs) - 600, 600)
    assert st.diag.rejected.total() == 0
    assert grew < 300_000, grew
    assert len(st.tracker.estimates) <= pf_mod.ESTIMATES_KEPT + pf_mod.ARCHIVE_EVERY


@pytest.mark.parametrize("cap", [20000, 250])
def test_pf_publishes_the_same_paths_with_the_history_archived(graph_file, monkeypatch, cap):
    """Periodic and final pf/path (smoothed window + filtered before it) are those of the tracker's
    full list of estimates, with the path cap reached or not."""
    msgs = _pf_messages(480)

    def paths(st: PfStage) -> list:
        out = []
        for topic, m in msgs:
            out += [path_from_msg(o) for tp, o in st.process(topic, m, 0) if tp == "pf/path"]
        return out + [path_from_msg(o) for tp, o in st.finish() if tp == "pf/path"]
    archived = paths(_pf(graph_file, path_max_poses=cap))
    monkeypatch.setattr(pf_mod, "ARCHIVE_EVERY", 10**9)           # every estimate kept as an object
    kept = paths(_pf(graph_file, path_max_poses=cap))
    assert len(archived) == len(kept) > 10
    for a, b in zip(archived, kept):
        if cap < 20000 and len(b[0]) > cap:      # the list was trimmed lazily (up to 1.25 cap): the newest cap
            b = tuple(v[-cap:] for v in b)
        assert len(a[0]) == len(b[0]) and np.array_equal(a[0], b[0])
        assert np.allclose(a[1], b[1])
    assert len(archived[-1][0]) == min(cap, len(archived[-1][0]))
