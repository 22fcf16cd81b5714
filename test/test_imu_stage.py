"""ImuStage: stepometer + heading -> pdr/odom (+ imu/data), failure paths of the message contract."""
from __future__ import annotations

import math

import numpy as np
import pytest

from indoor_loc.errors import ConfigError
from indoor_loc.measurements import pdr_intervals
from msg_adapters.imu import imu_from_msg, imu_to_msg, mag_to_msg
from msg_adapters.odom import odom_from_msg
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.imu_stage import ImuStage, ImuStageParams

G = 9.81
CADENCE = 1.8


def make_stage(ns="/alice", **over) -> ImuStage:
    return ImuStage(params_from_dict(ImuStageParams, over), namespace=ns)


def walk(rng, duration_s=25.0, rate_hz=100.0, yaw_rate=0.0):
    """Stamps (ns), acc (N,3) m/s² of a level walk (|a| oscillating at the cadence) and gyro (N,3)."""
    n = int(duration_s * rate_hz)
    t = np.arange(n) / rate_hz + rng.uniform(-0.001, 0.001, n)
    az = G + 2.0 * np.sin(2 * np.pi * CADENCE * t) + 0.4 * np.sin(np.pi * CADENCE * t) + 0.05 * rng.standard_normal(n)
    acc = np.c_[0.05 * rng.standard_normal(n), 0.05 * rng.standard_normal(n), az]
    gyro = np.c_[np.zeros(n), np.zeros(n), np.full(n, yaw_rate)] + 0.002 * rng.standard_normal((n, 3))
    return (10**9 + np.round(t * 1e9)).astype(np.int64), acc, gyro, t


def feed(stage, stamps, acc, gyro=None, mag_every=0, quats=None):
    outs = []
    for i, ns in enumerate(stamps):
        ns = int(ns)
        outs += stage.process("imu/data_raw", imu_to_msg(ns, "alice/imu_link", acc[i], None if gyro is None else gyro[i]), ns)
        if mag_every and i % mag_every == 0:
            outs += stage.process("imu/mag", mag_to_msg(ns, "alice/imu_link", [2e-5, 0.0, -4e-5]), ns)
        if quats is not None and i % 2 == 0:
            outs += stage.process("imu/data", imu_to_msg(ns, "alice/imu_link", [0, 0, 0], None, quats[i],
                                                         np.diag([0.01, 0.01, 0.04])), ns)
    return outs + stage.finish()


def odoms(outs):
    return [odom_from_msg(m) for topic, m in outs if topic == "pdr/odom"]


def test_aekf_heading_with_mag(rng):
    stamps, acc, gyro, t = walk(rng, yaw_rate=0.0)
    st = make_stage(heading_source="aekf")
    outs = feed(st, stamps, acc, gyro, mag_every=2)
    od = odoms(outs)
    imu = [imu_from_msg(m) for topic, m in outs if topic == "imu/data"]
    assert len(imu) == len(stamps)
    assert all(abs(np.linalg.norm(s.quat_xyzw) - 1) < 1e-6 for s in imu)
    expected_steps = CADENCE * t[-1]
    assert st.stepometer.total_steps == pytest.approx(expected_steps, rel=0.01)
    xy = np.array([[0.0, 0.0]] + [[o.x, o.y] for o in od])
    yaw = np.array([od[0].yaw] + [o.yaw for o in od])
    steps = pdr_intervals(np.arange(len(xy)), xy, yaw, step_length_m=0.65).steps
    assert steps.sum() == pytest.approx(st.stepometer.total_steps, rel=1e-6)
    assert od[-1].frame_id == "alice/odom" and od[-1].child_frame_id == "alice/base_link"
    assert od[-1].cov[2, 2] < 0.1                      # magnetometer: heading known
    diag = st.extra_diagnostics()
    assert diag["heading_source"] == "aekf" and int(diag["mag_used"]) > 0 and diag["walking"] == "true"
    assert float(diag["rate_hz"]) == pytest.approx(100.0, rel=0.01)


def test_missing_magnetometer_6d_heading_uncertainty_grows(rng):
    stamps, acc, gyro, _ = walk(rng, yaw_rate=0.1)
    st = make_stage(heading_source="aekf")
    od = odoms(feed(st, stamps, acc, gyro))
    assert st.extra_diagnostics()["mag_used"] == "0"
    assert od[-1].cov[2, 2] > od[0].cov[2, 2]
    assert np.trace(od[-1].cov[:2, :2]) > np.trace(od[1].cov[:2, :2])
    # the gyro turns the heading at 0.1 rad/s
    turned = np.unwrap([o.yaw for o in od])
    assert (turned[-1] - turned[0]) == pytest.approx(0.1 * (od[-1].stamp_ns - od[0].stamp_ns) * 1e-9, rel=0.1)


def test_accelerometer_only_heading_unknown(rng):
    stamps, acc, _, t = walk(rng)
    st = make_stage()
    od = odoms(feed(st, stamps, acc, None))
    assert all(o.cov[2, 2] == 1e6 for o in od)
    dist = math.hypot(od[-1].x, od[-1].y)
    assert dist == pytest.approx(0.65 * CADENCE * t[-1], rel=0.01)
    assert st.extra_diagnostics()["heading_source"] == "none"


def test_orientation_topic_gives_heading(rng):
    stamps, acc, _, t = walk(rng)
    yaw = math.pi / 2
    q = np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
    quats = np.tile(q, (len(stamps), 1))
    st = make_stage(heading_source="orientation")
    assert [p.topic for p in st.outputs()] == ["pdr/odom"]
    od = odoms(feed(st, stamps, acc, None, quats=quats))
    assert abs(od[-1].x) < 1e-6 and od[-1].y == pytest.approx(0.65 * CADENCE * t[-1], rel=0.01)
    assert od[-1].cov[2, 2] == pytest.approx(0.04)
    assert st.extra_diagnostics()["acc_source"] == "imu/data_raw"


def test_auto_ignores_own_echo_and_switches_to_external_orientation(rng):
    stamps, acc, gyro, _ = walk(rng, duration_s=8.0)
    st = make_stage(heading_source="auto")
    outs = []
    for i in range(300):
        ns = int(stamps[i])
        got = st.process("imu/data_raw", imu_to_msg(ns, "imu", acc[i], gyro[i]), ns)
        outs += got
        for topic, msg in got:                     # DDS delivers our own imu/data back to us
            if topic == "imu/data":
                st.process("imu/data", msg, ns)
    assert st.heading_mode == "vqf"                # auto: the better filter on walking phones
    ns = int(stamps[300]) + 1
    st.process("imu/data", imu_to_msg(ns, "imu", [0, 0, 0], None, [0, 0, 0, 1], np.eye(3) * 0.01), ns)
    assert st.heading_mode == "orientation"
    assert sum(st.diag.rejected.values()) == 0


def test_nan_and_backwards_stamps_are_rejected_without_state_change(rng):
    stamps, acc, gyro, _ = walk(rng, duration_s=6.0)
    st = make_stage(heading_source="aekf")
    feed_part = [st.process("imu/data_raw", imu_to_msg(int(s), "imu", a, g), int(s))
                 for s, a, g in zip(stamps[:400], acc[:400], gyro[:400])]
    assert feed_part
    step_state, aekf_q = st.stepometer.state(), st.filter.quat_wxyz.copy()
    bad = imu_to_msg(int(stamps[400]), "imu", acc[400], gyro[400])
    bad.linear_acceleration.x = float("nan")
    assert st.process("imu/data_raw", bad, 0) == []
    inf_gyro = imu_to_msg(int(stamps[400]), "imu", acc[400], gyro[400])
    inf_gyro.angular_velocity.z = float("inf")
    assert st.process("imu/data_raw", inf_gyro, 0) == []
    # 3.9 s back: held as a possible jump back (more than time.jump_s); the source then goes on in
    # step, so it was a straggler: rejected (stale_stamp) once the next one is taken
    assert st.process("imu/data_raw", imu_to_msg(int(stamps[10]), "imu", acc[10], gyro[10]), 0) == []
    assert st.process("imu/data_raw", imu_to_msg(int(stamps[399]), "imu", acc[399], gyro[399]), 0) == []
    assert st.diag.rejected["nan"] == 2 and st.diag.rejected["non_monotonic_stamp"] == 1
    assert st.stepometer.state().buffer == step_state.buffer
    np.testing.assert_array_equal(st.filter.quat_wxyz, aekf_q)
    bad_mag = mag_to_msg(int(stamps[400]), "imu", [1e-5, 0, 0])
    bad_mag.magnetic_field.y = float("nan")
    st.process("imu/mag", bad_mag, 0)
    assert st.diag.rejected["nan"] == 3
    # still works afterwards (the held straggler counted now)
    assert st.process("imu/data_raw", imu_to_msg(int(stamps[400]), "imu", acc[400], gyro[400]), 0)
    assert st.diag.rejected["stale_stamp"] == 1 and st.diag.time_jumps == 0


@pytest.mark.parametrize("rate_hz", [50.0, 400.0])
def test_rates(rate_hz, rng):
    stamps, acc, _, t = walk(rng, duration_s=20.0, rate_hz=rate_hz)
    st = make_stage(heading_source="orientation")
    feed(st, stamps, acc)
    assert st.stepometer.total_steps == pytest.approx(CADENCE * t[-1], rel=0.01)


def test_frames_and_config_errors():
    st = make_stage(ns="", odom_frame="odom_custom")
    assert st.odom_frame == "odom_custom" and st.base_frame == "base_link"
    with pytest.raises(ConfigError, match="heading_source"):
        params_from_dict(ImuStageParams, {"heading_source": "compass"})
    with pytest.raises(ConfigError, match="window_s"):
        params_from_dict(ImuStageParams, {"stepometer": {"window_s": -1.0}})
    with pytest.raises(ConfigError, match="unknown"):
        params_from_dict(ImuStageParams, {"step_lenght_m": 0.7})


def test_config_file_holds_every_parameter_with_defaults():
    from pathlib import Path

    import dataclasses

    from indoor_loc.params import load_params_file, params_for_node
    path = Path(__file__).resolve().parents[1] / "config" / "imu_node.yaml"
    values = params_for_node(load_params_file(path), "imu_node", "/alice")
    names = {f.name for f in dataclasses.fields(ImuStageParams)}
    assert set(values) <= names
    # every stage and stepometer key is in the file; AEKF keys (mirrored from AekfParams) may lag
    assert {n for n in names if not n.startswith("aekf_")} <= set(values)
    assert params_from_dict(ImuStageParams, values) == ImuStageParams()
    for line in path.read_text().splitlines():
        if line.startswith("    ") and ":" in line and not line.strip().startswith("#"):
            assert "#" in line, line


def test_offline_run_writes_pdr_odom(tmp_path, rng):
    """`indoor-loc run BAG --nodes imu`: the same stage replays a bag into pdr/odom under the user's namespace."""
    from indoor_loc.bag import BagWriter, read_bag
    from indoor_loc.pipeline.offline import run_offline
    stamps, acc, gyro, t = walk(rng, duration_s=15.0)
    bag = tmp_path / "walk01.mcap"
    with BagWriter(bag) as w:
        for i, ns in enumerate(stamps):
            w.write("/walk01/imu/data_raw", imu_to_msg(int(ns), "walk01/imu_link", acc[i], gyro[i]), int(ns))
    out = tmp_path / "out.mcap"
    run_offline([bag], out, nodes=["imu"], progress=False)
    od = [odom_from_msg(m.msg) for m in read_bag([out], topics=["/walk01/pdr/odom"])]
    assert od and od[-1].frame_id == "walk01/odom"
    dist = sum(math.hypot(b.x - a.x, b.y - a.y) for a, b in zip(od, od[1:])) + math.hypot(od[0].x, od[0].y)
    assert dist == pytest.approx(0.65 * CADENCE * t[-1], rel=0.02)
    assert [m for m in read_bag([out], topics=["/walk01/imu/data"])]
