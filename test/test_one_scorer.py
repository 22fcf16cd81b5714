"""One scorer: the demo's table and ``indoor-loc eval`` give the same numbers for the same estimate,
and both match a hand-computed case where the estimate starts after the truth does."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from test_eval import _synthetic_walk


def test_demo_table_and_eval_agree_on_a_hand_computed_case(tmp_path):
    pytest.importorskip("rclpy")
    from indoor_loc.bag import BagWriter
    from indoor_loc.cli import main as cli_main
    from indoor_loc.datasets.putmc_bags import write_walk_bag
    from indoor_loc.demo import score_run
    from msg_adapters.path import path_to_msg

    walk, route = _synthetic_walk()          # truth (1, 2), (3, 2), (5, 2) at three scans; route along y = 2
    write_walk_bag(walk, route, tmp_path / "imp" / "walk05.mcap", map_yaw_rad=0.0)
    run = tmp_path / "run.mcap"
    est_t, est_xy = walk.scan_t[1:], np.array([[3.0, 3.0], [5.0, 3.0]])    # starts at the second scan
    with BagWriter(run) as bag:
        bag.write("/walk05/pdr_kf/path", path_to_msg(est_t, est_xy), int(est_t[-1]))
    # by hand: at the first scan the estimate's first pose is held: |(3, 3) - (1, 2)| = sqrt(5); then 1 and 1
    mean, mx = (math.sqrt(5) + 2) / 3, math.sqrt(5)
    rows, _ = score_run(run, tmp_path / "imp", ["walk05"])
    (row,) = rows
    assert row.mean_m == pytest.approx(mean) and row.max_m == pytest.approx(mx)
    assert row.coverage == pytest.approx(2 / 3) and row.route_m == pytest.approx(1.0)
    out = tmp_path / "scores.json"
    assert cli_main(["eval", str(run), "--truth", str(tmp_path / "imp"), "--topic", "pdr_kf/path",
                     "--json", str(out)]) == 0
    walk_score = json.loads(out.read_text())["walks"][0]
    assert walk_score["scan_m"]["mean"] == pytest.approx(row.mean_m)
    assert walk_score["scan_m"]["p95"] == pytest.approx(row.p95_m)
    assert walk_score["scan_m"]["max"] == pytest.approx(row.max_m)
    assert walk_score["route_m"]["mean"] == pytest.approx(row.route_m)
    assert walk_score["n_scans_outside"] == 1


def test_eval_table_names_what_its_count_counts(tmp_path, capsys):
    """The count beside the error is of truth instants (a simulation's 5 Hz samples), not WiFi scans."""
    from indoor_loc.commands.eval import format_table
    from indoor_loc.eval.metrics import score, walk_errors
    s = score(walk_errors("w", [0, 10], [[0.0, 0.0], [1.0, 0.0]], [[[0.0, 0.0], [1.0, 0.0]]],
                          [0, 5, 10], [[0.0, 0.0], [0.5, 0.0], [1.0, 0.0]]))
    head = format_table([s]).splitlines()[1]
    assert " at " in head and "scans" not in head
