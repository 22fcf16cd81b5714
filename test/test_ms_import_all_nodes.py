"""`indoor-loc import ms-indoor` configures every estimator (hand-written traces in test/data/ms_site):
each floor's link graph from its GeoJSON plan, `tll_pf` given its walk's floor graph, `pdr_kf_node`'s
step length, so `indoor-loc run WALK --nodes imu,wifi,pdr_kf,pf,backend` publishes every estimate of
a freshly imported site; a walk without WiFi scans runs with a warning about the idle node."""
from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml

from indoor_loc.commands.import_ms_indoor import (BACKEND_CALIBRATED_HEADING, KF_CALIBRATED_HEADING,
                                                  MIN_HEADING_STD_RAD, heading_prior_std)

SITE = Path(__file__).parent / "data" / "ms_site"
WALKS = {"B1": "5f0000000000000000000002", "F1": "5f0000000000000000000001"}


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    out = tmp_path_factory.mktemp("ms") / "out"
    args = argparse.Namespace(dataset_dir=SITE, out_dir=out, floors="", walks="", overwrite=False,
                              survey_walks=",".join(WALKS.values()), storey_height_m=5.0)
    assert import_ms_indoor(args) == 0
    return out


def test_heading_prior_std_is_the_circular_spread_of_the_survey_offsets():
    rng = np.random.default_rng(3)
    parts = [rng.normal(1.5, 0.3, 400), rng.normal(1.5, 0.3, 200), np.zeros(0)]
    assert heading_prior_std(parts) == pytest.approx(0.3, abs=0.03)
    assert heading_prior_std([np.zeros(0)]) is None
    assert heading_prior_std([np.full(5, 2.0)]) == MIN_HEADING_STD_RAD


def test_every_floor_gets_its_graph_and_every_walk_its_floors(imported):
    from indoor_loc.graph.io import load_graph
    from indoor_loc.pipeline.imu_stage import ImuStageParams
    params = yaml.safe_load((imported / "params.yaml").read_text())
    assert params["/**/pdr_kf_node"]["ros__parameters"]["step_length_m"] == ImuStageParams().step_length_m
    # the survey walks walk exactly along the calibrated heading: the priors' floor, on every estimator
    sd = MIN_HEADING_STD_RAD
    assert params["/**/tll_pf"]["ros__parameters"] == {"smooth_redrawn": "mixture", "yaw_offset_sigma_rad": sd}
    kf, be = params["/**/pdr_kf_node"]["ros__parameters"], params["/**/backend_node"]["ros__parameters"]
    assert kf["heading_prior_std_rad"] == sd and kf["sigma_dtheta_rad"] == KF_CALIBRATED_HEADING["sigma_dtheta_rad"]
    assert be["gauge_std_rad"] == sd and be["pdr_info"] == BACKEND_CALIBRATED_HEADING["pdr_info"]
    for floor, z in (("B1", -5.0), ("F1", 0.0)):
        key = f"/{floor.lower()}_{WALKS[floor]}/tll_pf"
        graph_file = Path(params[key]["ros__parameters"]["graph_file"])
        assert graph_file == imported / "floors" / floor / "graph.yaml"
        g = load_graph(graph_file)
        assert g.n_links >= 1 and [f.name for f in g.floors] == [floor] and np.all(g.node_xyz[:, 2] == z)
        plan = yaml.safe_load((imported / "floors" / floor / "map.yaml").read_text())
        xy = g.node_xyz[:, :2]                                    # on the floor, in the map frame
        assert np.all((xy >= -1.0) & (xy <= [plan["width_m"] + 1.0, plan["height_m"] + 1.0]))


def test_a_fresh_import_runs_every_estimator(imported, tmp_path):
    from indoor_loc.bag import read_bag
    from indoor_loc.pipeline.offline import run_offline
    ns = f"/b1_{WALKS['B1']}"
    out = tmp_path / "run.mcap"
    s = run_offline([imported / "B1" / f"{WALKS['B1']}.mcap"], out, nodes=["imu", "wifi", "pdr_kf", "pf", "backend"],
                    params=imported / "params.yaml", progress=False)
    assert s.idle == []
    counts = Counter(m.topic for m in read_bag([out]))
    for topic in ("wifi/fix", "pdr_kf/pose", "pdr_kf/path", "pf/pose", "pf/path"):
        assert counts[f"{ns}/{topic}"] >= 1, topic                # before: tll_pf had no graph, nothing
    assert counts[f"/backend{ns}/path"] >= 1
    assert all(v == "0" for kv in s.per_stage.values() for k, v in kv.items() if k == "rejected.total")


def test_a_walk_without_wifi_warns_about_the_idle_node(imported, tmp_path, capsys):
    from indoor_loc.bag import BagWriter, read_bag
    from indoor_loc.cli import main as cli_main
    bag = tmp_path / "no_wifi.mcap"
    with BagWriter(bag) as w:
        for m in read_bag([imported / "B1" / f"{WALKS['B1']}.mcap"]):
            if not m.topic.endswith("/wifi/scan"):
                w.write(m.topic, m.msg, m.stamp_ns)
    out = tmp_path / "run.mcap"
    assert cli_main(["run", str(bag), "--nodes", "imu,wifi,pdr_kf,pf,backend", "--params",
                     str(imported / "params.yaml"), "--out", str(out), "--no-progress"]) == 0
    said = capsys.readouterr()
    assert "warning: nothing to do for node(s) wifi" in said.err and "the other nodes run" in said.err
    assert "4 node instances" in said.out     # imu, pdr_kf, tll_pf in the walk's namespace and the back-end
