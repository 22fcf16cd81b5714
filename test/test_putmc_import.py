"""PUTMC parser against the dataset's REFERENCE.md, frames/orientation conventions, bad input, and
the importer's bags read back with an independent reader (rosbags)."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import dataset
from scipy.spatial.transform import Rotation

from indoor_loc.datasets import putmc as P
from indoor_loc.errors import ConfigError, DatasetError


@pytest.fixture(scope="module")
def root() -> Path:
    return dataset("putmc")


@pytest.fixture(scope="module")
def ds(root):
    return P.Putmc(root)


@pytest.fixture(scope="module")
def raw_walks(ds):
    """All 24 walks with their stale samples kept (what the files hold)."""
    return {n: ds.walk(n, keep_stale=True) for n in ds.walk_numbers}


@pytest.fixture(scope="module")
def clean_walks(ds):
    """All 24 walks as imported by default (stale samples dropped)."""
    return {n: ds.walk(n) for n in ds.walk_numbers}


def _reference_rows(root: Path) -> dict[int, dict[str, str]]:
    text = (root / "REFERENCE.md").read_text()
    part = text[text.index("## Per-walk facts"):]
    lines = [ln for ln in part.splitlines() if ln.startswith("| xperia")]
    head = [h.strip() for h in part.splitlines()[2].strip("|").split("|")]
    out = {}
    for ln in lines:
        cells = [c.strip() for c in ln.strip("|").split("|")]
        row = dict(zip(head, cells))
        out[int(row["GT"])] = row
    return out


def test_parser_counts_match_reference(root, ds, raw_walks, clean_walks):
    ref = _reference_rows(root)
    assert sorted(ref) == ds.walk_numbers == list(range(1, 25))
    for n, w in raw_walks.items():
        r = ref[n]
        assert w.folder == r["folder"]
        assert w.raw_counts["acc"] == len(w.acc_t) == int(r["acc lines"]), n
        assert w.raw_counts["orient"] == len(w.ori_t) == int(r["orient lines"]), n
        assert len(w.scans) == len(w.scan_xy) == int(r["wifi scans"]), n
        assert np.mean([len(s) for s in w.scans]) == pytest.approx(float(r["AP/scan"]), abs=0.06)
        assert (w.end_ns - w.start_ns) * 1e-9 == pytest.approx(float(r["rec. duration s"]), abs=0.06)
        st = w.scan_t
        assert (st[-1] - st[0]) * 1e-9 == pytest.approx(float(r["1st→last WiFi s"]), abs=0.06)
        assert ds.routes[n].length_m == pytest.approx(float(r["GT length m"]), abs=0.06)
        i = P.start_gap(w.acc_t)
        if r["big gap s (start of walk)"] == "-":
            assert i == 0, n
        else:
            gap = (w.acc_t[i] - w.acc_t[i - 1]) * 1e-9
            assert gap == pytest.approx(float(r["big gap s (start of walk)"]), abs=0.11), n
        clean = clean_walks[n] if i else w
        assert (clean.end_ns - clean.start_ns) * 1e-9 == pytest.approx(float(r["walk segment s"]), abs=0.06), n


def test_stale_samples_dropped_and_reported(ds, raw_walks, clean_walks):
    with_stale = 0
    for n, raw in raw_walks.items():
        w = clean_walks[n]
        d = w.dropped
        assert len(w.acc_t) == raw.raw_counts["acc"] - d["acc"]
        assert len(w.ori_t) == raw.raw_counts["orient"] - d["orient"]
        assert len(w.scans) == raw.raw_counts["wifi"] - d["wifi"]
        kinds = {o.kind for o in w.oddities}
        if d["acc"]:
            with_stale += 1
            assert 6 <= d["acc"] <= 42 and {"stale_samples", "start_gap"} <= kinds
            assert np.all(np.diff(w.acc_t) < P.START_GAP_S * 1e9)
        else:
            assert "stale_samples" not in kinds
    assert with_stale == 19
    assert raw_walks[17].raw_counts["acc"] == 4651 and clean_walks[17].dropped == {"acc": 20, "orient": 12, "wifi": 0}


def test_ground_truth_frames_and_survey_map(ds):
    assert any(o.kind == "gt_self_loop" and o.walk == 7 for o in ds.oddities)
    r7 = ds.routes[7]
    assert np.all(r7.links[:, 0] < r7.links[:, 1])
    # image (x, y_down) -> ENU: the image's top-left corner is map (0, Y0)
    np.testing.assert_allclose(P.image_to_enu([[0.0, 0.0], [3.0, P.PUTMC_Y0]]), [[0.0, P.PUTMC_Y0], [3.0, 0.0]])
    x0, x1, y0, y1 = P.map_extent()
    assert (x0, y0) == (0.0, 0.0) and y1 == pytest.approx(36.8004, abs=1e-4) and x1 == pytest.approx(106.963, abs=1e-3)
    rm = ds.survey_map()
    assert rm.n_scans == 114 and rm.n_aps == 119 and rm.frame_id == "map"
    heard = np.sum(~np.isnan(rm.rssi_dbm), axis=1)
    assert heard.min() == 10 and heard.max() == 31
    assert np.nanmin(rm.rssi_dbm) == -91.0 and np.nanmax(rm.rssi_dbm) == -37.0
    for pts in [rm.positions] + [r.node_xy for r in ds.routes.values()]:
        assert np.all((pts[:, 0] > x0) & (pts[:, 0] < x1) & (pts[:, 1] > y0) & (pts[:, 1] < y1))


def test_map_quaternion_rotates_yaw_only(rng):
    q = Rotation.random(50, random_state=np.random.RandomState(7)).as_quat()     # x, y, z, w
    out = P.to_map_quat(q, 0.4)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-12)
    want = (Rotation.from_euler("z", 0.4) * Rotation.from_quat(q)).as_quat()
    np.testing.assert_allclose(np.abs(np.sum(out * want, axis=1)), 1.0, atol=1e-12)   # same rotation
    e_in = Rotation.from_quat(q).as_euler("ZYX")
    e_out = Rotation.from_quat(out).as_euler("ZYX")
    np.testing.assert_allclose(np.angle(np.exp(1j * (e_out[:, 0] - e_in[:, 0]))), 0.4, atol=1e-9)
    np.testing.assert_allclose(e_out[:, 1:], e_in[:, 1:], atol=1e-9)
    np.testing.assert_allclose(P.quat_yaw(q), e_in[:, 0], atol=1e-9)


def test_causal_index():
    ref = np.array([10, 20, 30])
    assert P.causal_index(np.array([5, 10, 15, 20, 35]), ref).tolist() == [-1, 0, 0, 1, 2]


def test_map_yaw_constant_reproduces(clean_walks):
    yaw, per = P.estimate_map_yaw(list(clean_walks.values()))
    assert math.degrees(abs(yaw - P.PUTMC_MAP_YAW_RAD)) < 0.1
    assert len(per) == 24


def test_bad_dataset_input(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        P.Putmc(tmp_path / "nope")
    (tmp_path / "acc.map").write_text("1 0.1 0.2 9.8\n2 0.1 0.2\n")
    with pytest.raises(DatasetError, match="line 2: expected 4 columns"):
        P.read_table(tmp_path / "acc.map", 4)
    (tmp_path / "wifi.map").write_text("100 0 2\naa:bb:cc:dd:ee:ff\tx\t-50.0\t2412\t1\n")
    with pytest.raises(DatasetError, match="announces 2 APs, has 1"):
        P.read_wifi_blocks(tmp_path / "wifi.map")
    (tmp_path / "nodes.map").write_text("2\n0 0\n1\n5\n1 1\n1\n0\n")
    with pytest.raises(DatasetError, match="neighbour 5 outside"):
        P.read_route(tmp_path / "nodes.map")
    from indoor_loc.commands.import_data import parse_walks
    assert parse_walks("", [1, 2]) == [1, 2] and parse_walks("2, 1", [1, 2]) == [1, 2]
    with pytest.raises(ConfigError, match="no walk"):
        parse_walks("1,99", [1, 2])
    with pytest.raises(ConfigError, match="integers"):
        parse_walks("a", [1, 2])


def _read_back(bag: Path) -> dict[str, list]:
    """All messages per topic, deserialised by rosbags (an independent reader)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: dict[str, list] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, stamp, raw in reader.messages():
            out.setdefault(conn.topic, []).append((stamp, reader.deserialize(raw, conn.msgtype)))
    return out


def test_import_read_back_with_rosbags(ds, tmp_path, capsys):
    pytest.importorskip("indoor_loc.wifi.radiomap", reason="radio map I/O not available")
    from indoor_loc.commands import import_data as import_cli

    parser = argparse.ArgumentParser()
    import_cli.add_arguments(parser)
    args = parser.parse_args(["putmc", str(ds.root), str(tmp_path / "imp"), "--walks", "16,17", "--no-progress"])
    assert import_cli.main(args) == 0
    printed = capsys.readouterr().out
    out = tmp_path / "imp"
    assert sorted(p.name for p in out.glob("*.mcap")) == ["walk16.mcap", "walk17.mcap"]
    params = yaml.safe_load((out / "params.yaml").read_text())
    assert params["/**/imu_node"]["ros__parameters"] == {"heading_source": "orientation", "step_length_m": 0.65}
    assert params["/**/wifi_fix_node"]["ros__parameters"] == {
        "radiomap": str((out / "radiomap").resolve()), "method": "wknn", "fallback": "powed",
        "wknn": {"k": 3, "shared_threshold": 0.6, "shared_strict": True, "error_type": "rms"}}
    from indoor_loc.backend.putmc_events import PUTMC_GRAPH_PARAMS
    from indoor_loc.params import params_from_dict
    from indoor_loc.pipeline.backend_stage import BackendParams
    backend = params["/**/backend_node"]["ros__parameters"]
    assert backend == {"radiomap": str((out / "radiomap").resolve()), "offline_order": "sequential",
                       **PUTMC_GRAPH_PARAMS}
    bp = params_from_dict(BackendParams, backend)          # the node takes them as written
    assert bp.joint and bp.estimate_step_length and bp.robust_kernel == "huber" and bp.wifi_info == 0.28
    from indoor_loc.wifi.radiomap import load_radiomap
    rm, survey = load_radiomap(out / "radiomap"), ds.survey_map()
    assert rm.n_scans == 114 and rm.bssids == survey.bssids
    np.testing.assert_allclose(rm.positions, survey.positions)
    np.testing.assert_array_equal(rm.rssi_dbm, survey.rssi_dbm)
    report = (out / "import_report.md").read_text()
    assert "stale_samples" in report and "20 acc, 12 orient" in report and "stale_samples" in printed
    # importing again onto the same directory: refused (exit 2, files untouched) unless --overwrite
    from indoor_loc.cli import main as cli_main
    before = (out / "walk16.mcap").stat().st_mtime_ns
    assert cli_main(["import", "putmc", str(ds.root), str(out), "--walks", "16", "--no-progress"]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert (out / "walk16.mcap").stat().st_mtime_ns == before

    for n, stale_acc in ((16, 0), (17, 20)):
        raw = ds.walk(n, keep_stale=True)
        w = ds.walk(n)
        assert w.dropped["acc"] == stale_acc
        msgs = _read_back(out / f"walk{n:02d}.mcap")
        imu = msgs[f"/walk{n:02d}/imu/data"]
        assert len(imu) == raw.raw_counts["acc"] - stale_acc == len(w.acc_t)
        assert len(msgs[f"/walk{n:02d}/wifi/scan"]) == raw.raw_counts["wifi"] == 5
        (t_gt, gt), = msgs[f"/walk{n:02d}/ground_truth"]
        assert len(gt.poses) == 5 and gt.header.frame_id == "map"
        np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y] for p in gt.poses], w.scan_xy)
        assert [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in gt.poses] == w.scan_t.tolist()
        (_, route), = msgs[f"/walk{n:02d}/ground_truth/route"]
        lines = [m for m in route.markers if m.type == 5]
        assert len(lines) == 1 and len(lines[0].points) == 2 * len(ds.routes[n].links)
        # IMU: stamps = file stamps; causal orientation; yaw variance = headingAcc²; no gyro
        stamps = [s for s, _ in imu]
        assert stamps == w.acc_t.tolist()
        k = P.causal_index(w.acc_t, w.ori_t)
        qmap = P.to_map_quat(w.quat_xyzw)
        for i in (0, len(imu) // 2, len(imu) - 1):
            m = imu[i][1]
            assert m.angular_velocity_covariance[0] == -1.0
            np.testing.assert_allclose(m.linear_acceleration.x, w.acc[i, 0])
            if k[i] < 0:
                assert m.orientation_covariance[0] == -1.0
            else:
                o = m.orientation
                np.testing.assert_allclose([o.x, o.y, o.z, o.w], qmap[k[i]], atol=1e-12)
                assert m.orientation_covariance[8] == pytest.approx(w.heading_acc[k[i]] ** 2)
        scan = msgs[f"/walk{n:02d}/wifi/scan"][0][1]
        assert scan.status[0].name == "scan" and len(scan.status) - 1 == len(w.scans[0])
