"""The documented back-end run on an `import ms-indoor` output (hand-written traces in test/data/ms_site):
the importer's params.yaml configures backend_node (the survey map, the graph on the front end's
fixes), so `indoor-loc run … --nodes imu,wifi,backend` publishes every user's path."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import yaml

SITE = Path(__file__).parent / "data" / "ms_site"


def test_importer_params_give_the_back_end_its_map_and_fixes(tmp_path):
    pytest.importorskip("rclpy")
    from indoor_loc.backend.graph import FIX_GRAPH_PARAMS
    from indoor_loc.bag import read_bag
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    from indoor_loc.pipeline.offline import run_offline
    from msg_adapters.path import path_from_msg
    from msg_adapters.pose import pose_from_msg

    out = tmp_path / "out"
    args = argparse.Namespace(dataset_dir=SITE, out_dir=out, floors="", walks="", overwrite=False,
                              survey_walks="5f0000000000000000000001,5f0000000000000000000002", storey_height_m=5.0)
    assert import_ms_indoor(args) == 0
    params = yaml.safe_load((out / "params.yaml").read_text())["/**/backend_node"]["ros__parameters"]
    assert Path(params["radiomap"]) == out / "radiomap" and params["wifi_source"] == "fix"
    assert {k: params[k] for k in FIX_GRAPH_PARAMS} == FIX_GRAPH_PARAMS
    # the site has GeoJSON plans: they are the back-end's walkable factor
    assert Path(params["floor_plans"]) == out / "floors" and params["walkable_std_m"] > 0
    assert params["fix_bias_std_m"] > 0                 # whole walks' fixes sit off together: one bias each
    bag = out / "B1" / "5f0000000000000000000002.mcap"
    run_offline([bag], tmp_path / "run.mcap", nodes=["imu", "wifi", "backend"], params=out / "params.yaml",
                progress=False)
    msgs = list(read_bag(tmp_path / "run.mcap"))
    fixes = [pose_from_msg(m.msg) for m in msgs if m.topic.endswith("/wifi/fix")]
    paths = [m.msg for m in msgs if m.topic == "/backend/b1_5f0000000000000000000002/path"]
    assert fixes and paths                            # before: no survey, so no user ever started
    stamps, xy, _ = path_from_msg(paths[-1])
    assert stamps[0] == fixes[0].stamp_ns              # the user starts at its first fix
    assert np.all(np.isfinite(xy))
