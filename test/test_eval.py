"""Evaluation metrics on hand-made cases with known answers, CSV round trip, bad input, PUTMC truth."""
from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import dataset

from indoor_loc.errors import DatasetError
from indoor_loc.eval.metrics import (EvalError, interpolate_xy, paper_score, point_segment_distance, pool, score,
                                     scan_time_errors, stats, walk_errors)
from indoor_loc.eval.trajectory import Trajectory, read_csv, read_csv_dir, truth_from_putmc, write_csv

# an L-shaped route: (0,0)-(10,0) and (10,0)-(10,10)
L_ROUTE = np.array([[[0.0, 0.0], [10.0, 0.0]], [[10.0, 0.0], [10.0, 10.0]]])


def _slow_distance(p, segs):
    """Obviously-correct oracle: sample every segment densely."""
    t = np.linspace(0, 1, 20001)[:, None]
    return min(float(np.min(np.hypot(*(p - (a + t * (b - a))).T))) for a, b in segs)


def test_point_segment_distance_known_points():
    pts = np.array([[5.0, 3.0],     # above the first segment: 3
                    [-3.0, 4.0],    # beyond its start: distance to (0,0) = 5
                    [13.0, 5.0],    # right of the second segment: 3
                    [12.0, 14.0],   # beyond the end (10,10): hypot(2,4)
                    [10.0, 0.0],    # on the corner: 0
                    [7.0, 2.0]])    # inside the L: min(2 to first, 3 to second) = 2
    d = point_segment_distance(pts, L_ROUTE)
    np.testing.assert_allclose(d, [3.0, 5.0, 3.0, math.hypot(2, 4), 0.0, 2.0], atol=1e-12)


def test_point_segment_distance_matches_oracle(rng):
    segs = rng.uniform(0, 20, size=(4, 2, 2))
    segs[3, 1] = segs[3, 0]                         # a zero-length segment is a point
    pts = rng.uniform(-5, 25, size=(15, 2))
    d = point_segment_distance(pts, segs)
    oracle = np.array([_slow_distance(p, segs) for p in pts])
    np.testing.assert_allclose(d, oracle, atol=2e-3)


def test_paper_score_squared_convention_and_cut():
    d = np.array([1.0, 2.0, 3.0, 11.0])             # 11 m -> e = 121 >= 100: cut
    p = paper_score(d)
    e = np.array([1.0, 4.0, 9.0])
    assert p.n == 3 and p.n_cut == 1
    assert p.mean == pytest.approx(e.mean())        # mean(d²) = 14/3
    assert p.rmse == pytest.approx(math.sqrt(np.mean(e ** 2)))   # sqrt(mean d⁴) = sqrt(98/3)
    # exactly 10 m is cut too (e < 100 is strict)
    assert paper_score([10.0]).n == 0 and math.isnan(paper_score([10.0]).rmse)
    assert paper_score([9.999]).n == 1


def test_stats_known_values():
    s = stats([3.0, 4.0])
    assert s.n == 2 and s.mean == 3.5 and s.median == 3.5 and s.max == 4.0
    assert s.rmse == pytest.approx(math.sqrt(12.5))
    assert s.p95 == pytest.approx(3.95)
    assert stats([]).n == 0 and math.isnan(stats([]).mean)


def test_interpolation_at_stamps():
    t = np.array([1_000_000_000_000, 1_000_000_002_000, 1_000_000_004_000], dtype=np.int64)
    xy = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 4.0]])
    at = np.array([t[0] + 1000, t[1], t[1] + 500, t[0] - 7, t[2] + 9], dtype=np.int64)
    p, inside = interpolate_xy(t, xy, at)
    np.testing.assert_allclose(p, [[1.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 0.0], [2.0, 4.0]], atol=1e-12)
    assert inside.tolist() == [True, True, True, False, False]
    d, ins = scan_time_errors(t, xy, at[:3], np.array([[1.0, 3.0], [2.0, 0.0], [5.0, 5.0]]))
    np.testing.assert_allclose(d, [3.0, 0.0, 5.0])
    assert ins.all()


def test_walk_score_and_pooling():
    # poses at known distances from L_ROUTE: 1, 2 (first walk), 3 (second walk)
    e1 = walk_errors("a", [0, 10], [[5.0, 1.0], [12.0, 5.0]], L_ROUTE, [5], [[5.0, 0.0]])
    e2 = walk_errors("b", [0], [[5.0, -3.0]], L_ROUTE)
    s1 = score(e1)
    assert s1.paper.mean == pytest.approx((1 + 4) / 2)
    assert s1.route_m.mean == pytest.approx(1.5)
    # at t=5 the trajectory is halfway: (8.5, 3.0); truth (5, 0)
    assert s1.scan_m.mean == pytest.approx(math.hypot(3.5, 3.0))
    pooled = score(pool([e1, e2]))
    assert pooled.n_poses == 3
    assert pooled.paper.mean == pytest.approx((1 + 4 + 9) / 3)     # pooled over poses, not walks
    assert pooled.paper.rmse == pytest.approx(math.sqrt((1 + 16 + 81) / 3))
    assert pooled.scan_m.n == 1


def test_csv_round_trip(tmp_path, rng):
    t = np.cumsum(rng.integers(1, 10**9, size=20)).astype(np.int64) + 10**12
    xy = rng.normal(size=(20, 2)) * 30
    h = rng.uniform(-math.pi, math.pi, size=20)
    h[3] = np.nan
    tr = Trajectory.make("walk05", t, xy, h)
    write_csv(tmp_path / "walk05.csv", tr)
    back = read_csv(tmp_path / "walk05.csv")
    assert back.name == "walk05"
    np.testing.assert_array_equal(back.stamps_ns, t)
    np.testing.assert_array_equal(back.xy, xy)
    np.testing.assert_array_equal(np.isnan(back.heading), np.isnan(h))
    np.testing.assert_array_equal(back.heading[~np.isnan(h)], h[~np.isnan(h)])
    assert set(read_csv_dir(tmp_path)) == {"walk05"}


def test_bad_inputs(tmp_path):
    with pytest.raises(EvalError, match="shape"):
        point_segment_distance([[0.0, 0.0]], np.zeros((2, 2)))
    with pytest.raises(EvalError, match="non-finite"):
        point_segment_distance([[np.nan, 0.0]], L_ROUTE)
    with pytest.raises(EvalError, match="empty"):
        interpolate_xy([], np.zeros((0, 2)), [1])
    with pytest.raises(EvalError, match="non-decreasing"):
        interpolate_xy([2, 1], [[0, 0], [1, 1]], [1])
    with pytest.raises(EvalError, match="stamps"):
        Trajectory.make("x", [1, 2], [[0.0, 0.0]])
    (tmp_path / "bad.csv").write_text("t,x,y\n1,2,3\n")
    with pytest.raises(DatasetError, match="header"):
        read_csv(tmp_path / "bad.csv")
    (tmp_path / "bad2.csv").write_text("stamp_ns,x,y,heading\n1,abc,3,\n")
    with pytest.raises(DatasetError, match="line 2"):
        read_csv(tmp_path / "bad2.csv")


def test_putmc_truth_scores_itself_zero():
    """The true scan positions as a trajectory: zero scan-time error; their route distance is the
    dataset's 0.09-0.64 m per-walk mean."""
    root = dataset("putmc")
    truths = truth_from_putmc(root, [5, 16])
    for name, gt in truths.items():
        e = walk_errors(name, gt.scan_ns, gt.scan_xy, gt.segments, gt.scan_ns, gt.scan_xy)
        s = score(e)
        assert s.scan_m.max == pytest.approx(0.0, abs=1e-9)
        assert 0.05 < s.route_m.mean < 0.7
        assert s.paper.n_cut == 0


def _synthetic_walk(n: int = 5):
    """A tiny PUTMC-like walk (no dataset needed): 3 s of IMU at 100 Hz, 3 scans along y = 2."""
    from indoor_loc.datasets.putmc import Route, Walk
    from indoor_loc.wifi.types import WifiScan

    t0 = 50 * 10**9
    acc_t = t0 + np.arange(300, dtype=np.int64) * 10**7
    ori_t = acc_t[5::2] + 1000
    scan_t = t0 + np.array([5, 15, 25], dtype=np.int64) * 10**8
    scans = [WifiScan(int(t), ("aa:bb:cc:dd:ee:0%d" % i,), np.array([-60.0 - i]), np.array([2412.0]), ("x",),
                      frame_id=f"walk{n:02d}/wifi_link", source="putmc") for i, t in enumerate(scan_t)]
    walk = Walk(walk=n, folder="synthetic", acc_t=acc_t, acc=np.tile([0.1, 0.2, 9.8], (300, 1)), ori_t=ori_t,
                quat_xyzw=np.tile([0.0, 0.0, 0.0, 1.0], (len(ori_t), 1)), heading_acc=np.full(len(ori_t), 0.1745),
                scans=scans, scan_xy=np.array([[1.0, 2.0], [3.0, 2.0], [5.0, 2.0]]), scan_idx=np.arange(3))
    route = Route(n, np.array([[0.0, 2.0], [6.0, 2.0], [6.0, 8.0]]), np.array([[0, 1], [1, 2]]))
    return walk, route


def test_bags_truth_and_trajectories_through_cli(tmp_path):
    pytest.importorskip("rclpy")
    import json

    from indoor_loc.bag import BagWriter
    from indoor_loc.cli import main as cli_main
    from indoor_loc.datasets.putmc_bags import write_walk_bag
    from indoor_loc.commands.eval import trajectories_from_bags, truth_from_import
    from msg_adapters.path import path_to_msg
    from msg_adapters.pose import fix_to_msg
    from indoor_loc.measurements import Fix

    walk, route = _synthetic_walk()
    counts = write_walk_bag(walk, route, tmp_path / "imp" / "walk05.mcap", map_yaw_rad=0.0)
    assert counts["/walk05/imu/data"] == 300 and counts["/walk05/wifi/scan"] == 3
    truth = truth_from_import(tmp_path / "imp")["walk05"]
    np.testing.assert_array_equal(truth.scan_ns, walk.scan_t)
    np.testing.assert_allclose(truth.scan_xy, walk.scan_xy)
    np.testing.assert_allclose(truth.segments, route.segments)

    run = tmp_path / "run.mcap"
    with BagWriter(run) as bag:
        for t, xy in zip(walk.scan_t, walk.scan_xy + [[0.0, 3.0], [0.0, 0.0], [4.0, 0.0]]):
            bag.write("/walk05/wifi/fix", fix_to_msg(Fix(int(t), xy, np.eye(2))), int(t))
        bag.write("/walk05/pdr_kf/path", path_to_msg(walk.scan_t[:1], walk.scan_xy[:1]), int(walk.scan_t[0]))
        bag.write("/walk05/pdr_kf/path", path_to_msg(walk.scan_t, walk.scan_xy), int(walk.scan_t[-1]))
    fixes = trajectories_from_bags([run], "wifi/fix")["walk05"]
    assert len(fixes) == 3 and np.all(np.isnan(fixes.heading))
    path = trajectories_from_bags([run], "pdr_kf/path")["walk05"]     # the last Path wins
    np.testing.assert_allclose(path.xy, walk.scan_xy)

    out = tmp_path / "scores.json"
    assert cli_main(["eval", str(run), "--truth", str(tmp_path / "imp"), "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    # fixes (1, 5), (3, 2), (9, 2): errors 3, 0, 4 m at the scans; route distances 3, 0, 3 m
    assert res["pooled"]["scan_m"]["mean"] == pytest.approx(7 / 3)
    assert res["pooled"]["scan_m"]["max"] == pytest.approx(4.0)
    assert res["pooled"]["paper"]["mean"] == pytest.approx((9 + 0 + 9) / 3)
    assert res["pooled"]["route_m"]["max"] == pytest.approx(3.0)
    assert cli_main(["eval", str(run), "--truth", str(tmp_path / "imp"), "--topic", "pdr_kf/path"]) == 0


def _imported_walk_and_run(tmp_path, *, with_odom: bool):
    """An imported synthetic walk (``tmp_path/imp/walk05.mcap``) and a run bag with its ``wifi/fix``
    (and, if asked, ``pdr/odom`` in the odometry frame) at the scan stamps; returns the run bag."""
    pytest.importorskip("rclpy")
    from indoor_loc.bag import BagWriter
    from indoor_loc.datasets.putmc_bags import write_walk_bag
    from indoor_loc.measurements import Fix
    from msg_adapters.odom import odom_to_msg
    from msg_adapters.pose import fix_to_msg

    walk, route = _synthetic_walk()
    write_walk_bag(walk, route, tmp_path / "imp" / "walk05.mcap", map_yaw_rad=0.0)
    run = tmp_path / "run.mcap"
    with BagWriter(run) as bag:
        for t, xy in zip(walk.scan_t, walk.scan_xy):
            if with_odom:
                bag.write("/walk05/pdr/odom", odom_to_msg(int(t), "walk05/odom", "walk05/base_link", xy[0], xy[1],
                                                          0.0, np.eye(3), 1.0, 0.0), int(t))
            bag.write("/walk05/wifi/fix", fix_to_msg(Fix(int(t), xy, np.eye(2))), int(t))
    return run


def test_eval_warns_when_the_track_is_not_in_the_truth_frame(tmp_path, capsys):
    """Scoring ``pdr/odom`` (frame ``<user>/odom``) against map truth gives numbers that are not
    localisation errors: eval says so on stderr; a map-frame track gets no warning."""
    from indoor_loc.cli import main as cli_main
    run = _imported_walk_and_run(tmp_path, with_odom=True)
    assert cli_main(["eval", str(run), "--truth", str(tmp_path / "imp"), "--topic", "pdr/odom"]) == 0
    err = capsys.readouterr().err
    assert "WARNING: walk05: the track is in frame walk05/odom" in err and "'map'" in err
    assert cli_main(["eval", str(run), "--truth", str(tmp_path / "imp"), "--topic", "wifi/fix"]) == 0
    assert "WARNING" not in capsys.readouterr().err


def test_eval_of_a_missing_topic_lists_the_trajectory_topics(tmp_path, capsys):
    """A mistyped ``--topic`` (or an input bag given instead of a run's output) names what is there."""
    from indoor_loc.cli import main as cli_main
    run = _imported_walk_and_run(tmp_path, with_odom=False)
    assert cli_main(["eval", str(run), "--truth", str(tmp_path / "imp"), "--topic", "pdr_kf/pathx"]) == 2
    err = capsys.readouterr().err
    assert "no topic named */pdr_kf/pathx" in err and "trajectory topics there: /walk05/wifi/fix" in err
    # the imported input bag: only its ground truth is a trajectory, the IMU and scan topics are not listed
    bag = str(tmp_path / "imp" / "walk05.mcap")
    assert cli_main(["eval", bag, "--truth", str(tmp_path / "imp"), "--topic", "pdr_kf/path"]) == 2
    err = capsys.readouterr().err
    assert "trajectory topics there: /walk05/ground_truth" in err and "imu/data" not in err.split("there:")[1]


def test_eval_of_an_import_with_floor_directories_and_no_route_markers(tmp_path, capsys):
    """``import ms-indoor`` writes ``OUT/<floor>/<id>.mcap`` with ``ground_truth`` = the waypoints
    (the walk is linear between them) and no route markers: the waypoints' segments are the route."""
    pytest.importorskip("rclpy")
    import json

    from indoor_loc.bag import BagWriter
    from indoor_loc.cli import main as cli_main
    from indoor_loc.commands.eval import truth_from_import
    from indoor_loc.measurements import Fix
    from msg_adapters.path import path_to_msg
    from msg_adapters.pose import fix_to_msg

    s = 10**9
    t_wp = np.array([10, 20, 30], dtype=np.int64) * s
    wp = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    (tmp_path / "imp" / "F3").mkdir(parents=True)
    with BagWriter(tmp_path / "imp" / "F3" / "abc.mcap") as bag:
        bag.write("/f3_5dd38ffd27889b0006b76aca/ground_truth", path_to_msg(t_wp, wp), int(t_wp[0]))
    truth = truth_from_import(tmp_path / "imp")["f3_5dd38ffd27889b0006b76aca"]
    np.testing.assert_allclose(truth.segments, [[[0, 0], [10, 0]], [[10, 0], [10, 10]]])
    run = tmp_path / "run.mcap"
    with BagWriter(run) as bag:       # 1 m beside the route at each waypoint, 2 m off at 15 s
        for t, xy in zip([10 * s, 15 * s, 20 * s, 30 * s], [[0.0, 1.0], [5.0, 2.0], [11.0, 0.0], [11.0, 10.0]]):
            bag.write("/f3_5dd38ffd27889b0006b76aca/wifi/fix", fix_to_msg(Fix(int(t), np.array(xy), np.eye(2))), int(t))
    out = tmp_path / "scores.json"
    assert cli_main(["eval", str(run), "--truth", str(tmp_path / "imp"), "--json", str(out)]) == 0
    table = [ln for ln in capsys.readouterr().out.splitlines() if ln.count("|") == 3]
    assert len(table) == 3 and len({ln.index("|") for ln in table}) == 1   # header, walk, pooled aligned
    pooled = json.loads(out.read_text())["pooled"]
    assert pooled["route_m"]["max"] == pytest.approx(2.0) and pooled["route_m"]["mean"] == pytest.approx(5 / 4)
    assert pooled["scan_m"]["mean"] == pytest.approx(1.0)            # at the three waypoint stamps
    assert cli_main(["eval", str(run), "--truth", str(run)]) == 2
    assert "is not a directory" in capsys.readouterr().err

    # a walk whose truth is one point (no route to draw) is left out, the others are still scored
    with BagWriter(tmp_path / "imp" / "F3" / "one.mcap") as bag:
        bag.write("/f3_one/ground_truth", path_to_msg(t_wp[:1], wp[:1]), int(t_wp[0]))
    with BagWriter(tmp_path / "run2.mcap") as bag:
        for t, xy in zip([10 * s, 20 * s], [[0.0, 1.0], [11.0, 0.0]]):
            for user in ("f3_5dd38ffd27889b0006b76aca", "f3_one"):
                bag.write(f"/{user}/wifi/fix", fix_to_msg(Fix(int(t), np.array(xy), np.eye(2))), int(t))
    assert set(truth_from_import(tmp_path / "imp")) == {"f3_5dd38ffd27889b0006b76aca"}
    assert cli_main(["eval", str(tmp_path / "run2.mcap"), "--truth", str(tmp_path / "imp")]) == 0
    captured = capsys.readouterr()
    assert "f3_one has no" in captured.err and "not scored" in captured.out
    assert any(ln.startswith("f3_5dd38ffd27889b0006b76aca") for ln in captured.out.splitlines())


def test_eval_at_the_scans_of_an_import(tmp_path, capsys):
    """``--at-scans``: the scan-time error at every ``wifi/scan`` inside the waypoint span, against
    the waypoints interpolated there (a scan before the first waypoint is not scored)."""
    pytest.importorskip("rclpy")
    import json

    from indoor_loc.bag import BagWriter
    from indoor_loc.cli import main as cli_main
    from indoor_loc.commands.eval import truth_from_import
    from indoor_loc.measurements import Fix
    from indoor_loc.wifi.types import WifiScan
    from msg_adapters.path import path_to_msg
    from msg_adapters.pose import fix_to_msg
    from msg_adapters.wifi_scan import scan_to_msg

    s = 10**9
    user = "b1_5dd38ffd27889b0006b76aca"
    t_wp = np.array([10, 20, 30], dtype=np.int64) * s
    wp = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    (tmp_path / "imp" / "B1").mkdir(parents=True)
    with BagWriter(tmp_path / "imp" / "B1" / "abc.mcap") as bag:
        bag.write(f"/{user}/ground_truth", path_to_msg(t_wp, wp), int(t_wp[0]))
        for t in (5, 25, 15):                                   # unsorted; 5 s lies before the first waypoint
            scan = WifiScan(t * s, ("aa:bb:cc:dd:ee:ff",), np.array([-60.0]), np.array([2412.0]))
            bag.write(f"/{user}/wifi/scan", scan_to_msg(scan), t * s)
    truth = truth_from_import(tmp_path / "imp", at_scans=True)[user]
    assert truth.scan_ns.tolist() == [15 * s, 25 * s]
    np.testing.assert_allclose(truth.scan_xy, [[5.0, 0.0], [10.0, 5.0]])
    assert truth_from_import(tmp_path / "imp")[user].scan_ns.tolist() == t_wp.tolist()     # default: waypoints
    run = tmp_path / "run.mcap"
    with BagWriter(run) as bag:       # 2 m off at 15 s; (11, 5) at 25 s: 1 m off
        for t, xy in zip([10 * s, 15 * s, 20 * s, 30 * s], [[0.0, 1.0], [5.0, 2.0], [11.0, 0.0], [11.0, 10.0]]):
            bag.write(f"/{user}/wifi/fix", fix_to_msg(Fix(int(t), np.array(xy), np.eye(2))), int(t))
    out = tmp_path / "scores.json"
    assert cli_main(["eval", str(run), "--truth", str(tmp_path / "imp"), "--at-scans", "--json", str(out)]) == 0
    pooled = json.loads(out.read_text())["pooled"]
    assert pooled["scan_m"]["n"] == 2 and pooled["scan_m"]["mean"] == pytest.approx(1.5)
    capsys.readouterr()
    assert cli_main(["eval", str(run), "--dataset", str(tmp_path), "--at-scans"]) != 0     # not silently ignored
    assert "--at-scans needs --truth" in capsys.readouterr().err
