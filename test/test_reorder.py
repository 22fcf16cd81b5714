"""The shared cross-topic reorder buffer (indoor_loc/pipeline/reorder.py) and tll_pf taking
pdr/odom and baro/pressure in stamp order whichever arrives first."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.errors import InvalidMessageError
from indoor_loc.graph import save_graph
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.pf_stage import PfStage, PfStageParams
from indoor_loc.pipeline.reorder import ReorderBuffer
from indoor_loc.sim.building import building_graph, make_tower_building
from msg_adapters.pose import pose_from_msg

SEC = 1_000_000_000


def test_the_buffer_releases_what_every_flowing_stream_has_passed_in_stamp_order():
    b = ReorderBuffer()
    for s in (3, 5, 7):
        b.push(s * SEC, 0, ("baro", s))
        b.note("baro", s * SEC)
    assert b.mark(SEC) == 7 * SEC                  # one stream: it alone decides
    b.push(4 * SEC, 1, ("odom", 4))
    b.note("odom", 4 * SEC)
    assert b.mark(4 * SEC) == 4 * SEC              # odometry flows (within the window): wait for it
    assert [p for _, _, p in b.due(b.mark(4 * SEC))] == [("baro", 3), ("odom", 4)]
    assert b.mark(2 * SEC) == 7 * SEC              # odometry 3 s behind a 2 s window: stopped
    assert [p for _, _, p in b.due(b.mark(2 * SEC))] == [("baro", 5), ("baro", 7)]
    with pytest.raises(InvalidMessageError) as e:
        b.push(6 * SEC, 1, ("odom", 6), who="alice: ")
    assert e.value.reason == "too_late" and b.dropped_late == 1
    b.push(8 * SEC, 1, "a")
    b.push(8 * SEC, 0, "b")                        # same stamp: by rank
    assert [p for _, _, p in b.drain()] == ["b", "a"] and b.taken_ns == 8 * SEC


def _feed(order_key):
    """A lift ride (test_floors_live's stream) into one PfStage in the given order; its pf/pose
    (stamp, x, y, z)."""
    from test_floors_live import _stream
    gf = save_graph(building_graph(make_tower_building()), _feed.dir / "tower.graph.yaml")
    st = PfStage(params_from_dict(PfStageParams, {"graph_file": str(gf), "n_particles": 300,
                                                  "monitor": {"enabled": False}}))
    topic = {"odom": "pdr/odom", "fix": "wifi/fix", "baro": "baro/pressure"}
    outs = []
    for t, kind, msg in sorted(_stream(10 * SEC), key=order_key):
        outs += st.process(topic[kind], msg, t)
    outs += st.finish()
    rows = []
    for name, msg in outs:
        if name == "pf/pose":
            ps = pose_from_msg(msg)
            rows.append((ps.stamp_ns, *ps.xy, msg.pose.pose.position.z))
    return np.array(rows), st


def test_pf_takes_pressure_ahead_of_odometry_in_stamp_order(tmp_path):
    _feed.dir = tmp_path
    ordered, _ = _feed(lambda r: r[0])
    ahead, st = _feed(lambda r: r[0] - (SEC // 2 if r[1] == "baro" else 0))   # pressure 0.5 s early
    assert np.all(np.diff(ahead[:, 0]) >= 0)
    # the same poses and floors; positions to rounding
    assert ordered.shape == ahead.shape and np.array_equal(ordered[:, [0, 3]], ahead[:, [0, 3]])
    assert np.abs(ordered[:, 1:3] - ahead[:, 1:3]).max() < 1e-6
    # only the odometry's first hops come late (a stream is known from its first message on)
    assert st.reorder_late <= 2 and ordered[-1, 3] == pytest.approx(3.5)


def test_what_waits_for_a_stream_goes_when_both_stop(tmp_path):
    """The last hops wait for the barometer to reach its stamp; when nothing more comes, the node's
    clock releases it after reorder_window_s (a phone that stopped publishing)."""
    from test_floors_live import _stream
    gf = save_graph(building_graph(make_tower_building()), tmp_path / "tower.graph.yaml")
    st = PfStage(params_from_dict(PfStageParams, {"graph_file": str(gf), "n_particles": 300,
                                                  "monitor": {"enabled": False}}))
    topic = {"odom": "pdr/odom", "fix": "wifi/fix", "baro": "baro/pressure"}
    rows = [r for r in _stream(10 * SEC) if r[0] < 12 * SEC]
    rows = [r for r in rows if r[1] != "baro" or r[0] < 11_500_000_000]   # the barometer stops first
    last_hop = max(r[0] for r in rows if r[1] == "odom")
    assert last_hop > 11_500_000_000
    for t, kind, msg in rows:
        st.process(topic[kind], msg, t)
    waiting = len(st._order)
    assert waiting >= 1 and st.tracker.estimates[-1].stamp_ns < last_hop        # the last hops wait
    assert st.tick(last_hop + SEC // 2) == [] and len(st._order) == waiting       # within the window
    outs = st.tick(last_hop + int(1.1 * SEC))
    assert len(st._order) == 0 and any(n == "pf/pose" for n, _ in outs)
    assert st.tracker.estimates[-1].stamp_ns == last_hop
