"""End-to-end real-data regression: import two short PUTMC walks, replay them through the nodes
imu, wifi and pdr_kf exactly as `make demo` does, and score them against the surveyed truth.

Bounds are the figures measured when this test was written plus a margin (walks 16 and 21,
14 WiFi scans): WKNN alone 2.13 m mean scan-time error, RTS-smoothed PDR + WiFi 1.63 m."""
from __future__ import annotations

import pytest
from conftest import dataset

from indoor_loc.cli import main as cli_main
from indoor_loc.commands.eval import evaluate, trajectories_from_bags, truth_from_import
from indoor_loc.pipeline.offline import run_offline


@pytest.fixture(scope="module")
def replay(tmp_path_factory):
    putmc = dataset("putmc")
    out = tmp_path_factory.mktemp("e2e")
    assert cli_main(["import", "putmc", str(putmc), str(out / "import"), "--walks", "16,21"]) == 0
    bags = sorted((out / "import").glob("walk*.mcap"))
    summary = run_offline(bags, out / "run.mcap", nodes=["imu", "wifi", "pdr_kf"],
                          params=out / "import" / "params.yaml", progress=False)
    return out, summary


def _pooled(out, topic):
    scores, _ = evaluate(trajectories_from_bags([out / "run.mcap"], topic), truth_from_import(out / "import"))
    return scores[-1]


def test_replay_rejects_nothing_and_every_user_gets_every_output(replay):
    _, summary = replay
    assert set(summary.per_stage) == {f"/walk{w}/{n}" for w in ("16", "21")
                                      for n in ("imu_node", "wifi_fix_node", "pdr_kf_node")}
    assert all(kv["rejected.total"] == "0" for kv in summary.per_stage.values())
    for name, kv in summary.per_stage.items():
        out_keys = [k for k in kv if k.startswith("out.")]
        assert out_keys and all(int(kv[k]) > 0 for k in out_keys), (name, kv)


def test_smoothed_pdr_plus_wifi_beats_wifi_alone(replay):
    out, _ = replay
    wifi = _pooled(out, "wifi/fix")
    smooth = _pooled(out, "pdr_kf/path")
    assert wifi.scan_m.n == smooth.scan_m.n == 14
    assert wifi.scan_m.mean < 2.6                      # measured 2.13 m
    assert smooth.scan_m.mean < 2.0                    # measured 1.63 m
    assert smooth.scan_m.mean < 0.9 * wifi.scan_m.mean
    assert smooth.route_m.mean < 1.6                   # measured 1.21 m (route distance, metres)
