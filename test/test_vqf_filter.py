"""VqfFilter (VQF's compiled core with stamps) and the stage's heading inputs: online = batch with the
magnetometer at its own rate and late, save/restore, jittery stamps, hard-iron bias, disturbance."""
from __future__ import annotations

import math

import numpy as np
import pytest

from heading_synth import FIELD_ENU_UT, arrival_order, turning_device
from indoor_loc.errors import ConfigError
from indoor_loc.imu.mag_sync import IMU, MagSync
from indoor_loc.imu.quaternion import qconj, qmul, quat_yaw
from indoor_loc.imu.vqf_filter import VqfFilter, VqfParams, vqf_batch
from msg_adapters.imu import imu_from_msg, imu_to_msg, mag_to_msg
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.imu_stage import ImuStage, ImuStageParams


def _angle_deg(qa, qb):
    e = qmul(qa, qconj(qb))
    return np.degrees(2.0 * np.arccos(np.clip(np.abs(e[..., 0]), 0.0, 1.0)))


def test_tracks_a_turning_device_with_magnetometer_at_its_own_rate(rng):
    d = turning_device(rng, duration_s=40.0)
    q = vqf_batch(d["t"], d["gyr"], d["acc"], d["mt"], d["mag"])
    err = _angle_deg(q, d["q"])
    assert np.all(np.isfinite(q)) and np.allclose(np.linalg.norm(q, axis=1), 1.0)
    assert np.percentile(err[len(err) // 2:], 95) < 2.0


def test_jittery_stamps_integrate_the_true_angle(rng):
    """6-D, no noise: ±40 % stamp jitter and a dropped stretch — the heading turned equals ∫ω dt."""
    n = 4000
    dt = 0.005 * (1.0 + rng.uniform(-0.4, 0.4, n - 1))
    dt[2000] = 0.2                                              # a 0.2 s gap (still integrated)
    t = np.round(1e9 * np.concatenate([[1.0], 1.0 + np.cumsum(dt)])).astype(np.int64)
    gyr = np.tile([0.0, 0.0, 0.5], (n, 1))
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    q = vqf_batch(t, gyr, acc, params=VqfParams(rest_bias_est=False, motion_bias_est=False))
    turned = np.unwrap(quat_yaw(q))
    expected = 0.5 * (t - t[1]) * 1e-9                         # from the second sample (rate known)
    np.testing.assert_allclose(turned[1:] - turned[1], expected[1:], atol=1e-6)


def test_online_with_late_magnetometer_equals_batch_and_save_restore(rng):
    d = turning_device(rng, duration_s=10.0)
    ref = vqf_batch(d["t"], d["gyr"], d["acc"], d["mt"], d["mag"])
    delays = rng.integers(0, 60_000_000, len(d["mt"]))
    delays[0] = 0
    f, sync = VqfFilter(), MagSync(0.1)
    got = {}
    order = arrival_order(d["t"], d["mt"], delays)
    for n, (kind, i) in enumerate(order):
        if n == len(order) // 2:                                # save, rebuild, restore half-way
            saved_f, saved_s = f.state(), sync.state()
            f, sync = VqfFilter(), MagSync(0.1)
            f.set_state(saved_f)
            sync.set_state(saved_s)
        evs = sync.push_imu(int(d["t"][i]), i) if kind == "imu" else sync.push_mag(int(d["mt"][i]), i)
        for k, stamp, j in evs + ([] if n < len(order) - 1 else sync.flush()):
            if k == IMU:
                f.update_imu(stamp, d["gyr"][j], d["acc"][j])
                got[j] = f.quat_wxyz
            else:
                f.update_mag(stamp, d["mag"][j])
    assert sync.n_late == 0
    np.testing.assert_array_equal(np.array([got[i] for i in range(len(d["t"]))]), ref)


def test_bad_input_and_params():
    f = VqfFilter()
    f.update_imu(1_000_000, [0, 0, 0], [0, 0, 9.81])
    with pytest.raises(ValueError, match="non-finite"):
        f.update_imu(2_000_000, [math.nan, 0, 0], [0, 0, 9.81])
    with pytest.raises(ValueError, match="stamps must increase"):
        f.update_imu(1_000_000, [0, 0, 0], [0, 0, 9.81])
    with pytest.raises(ValueError, match="non-finite"):
        f.update_mag(3_000_000, [0, math.inf, 0])
    with pytest.raises(ConfigError, match="tau_acc_s"):
        params_from_dict(VqfParams, {"tau_acc_s": 0.0})


# -- the stage ---------------------------------------------------------------------------------------
def _stage(**over):
    return ImuStage(params_from_dict(ImuStageParams, over), namespace="/alice")


def _drive(stage, d, order, mag_offset_ut=(0.0, 0.0, 0.0)):
    out = {}
    for kind, i in order:
        if kind == "imu":
            ns = int(d["t"][i])
            outs = stage.process("imu/data_raw", imu_to_msg(ns, "imu", d["acc"][i], d["gyr"][i]), ns)
        else:
            ns = int(d["mt"][i])
            outs = stage.process("imu/mag", mag_to_msg(ns, "imu", (d["mag"][i] + mag_offset_ut) * 1e-6), ns)
        for topic, msg in outs:
            if topic == "imu/data":
                s = imu_from_msg(msg)
                out[s.stamp_ns] = s.quat_xyzw[[3, 0, 1, 2]]
    for topic, msg in stage.finish():
        if topic == "imu/data":
            s = imu_from_msg(msg)
            out[s.stamp_ns] = s.quat_xyzw[[3, 0, 1, 2]]
    return out


@pytest.mark.parametrize("source", ["vqf", "aekf"])
def test_stage_late_magnetometer_gives_the_in_order_result(source, rng):
    d = turning_device(rng, duration_s=8.0)
    in_order = _drive(_stage(heading_source=source), d, arrival_order(d["t"], d["mt"], 0))
    delays = rng.integers(0, 80_000_000, len(d["mt"]))
    delays[0] = 0
    st = _stage(heading_source=source)
    late = _drive(st, d, arrival_order(d["t"], d["mt"], delays))
    assert sorted(late) == sorted(in_order) and len(late) >= len(d["t"]) - 1   # VQF: rate from 2 stamps
    for k in in_order:
        np.testing.assert_array_equal(late[k], in_order[k])
    diag = st.extra_diagnostics()
    assert diag["mag_late"] == "0" and int(diag["mag_used"]) == len(d["mt"])


def test_stage_counts_a_magnetometer_later_than_the_bound(rng):
    d = turning_device(rng, duration_s=4.0)
    delays = np.zeros(len(d["mt"]), dtype=np.int64)
    delays[50] = 500_000_000
    st = _stage(heading_source="vqf", mag_max_delay_s=0.1)
    _drive(st, d, arrival_order(d["t"], d["mt"], delays))
    assert int(st.extra_diagnostics()["mag_late"]) > 0
    assert st.diag.rejected["mag_late"] == int(st.extra_diagnostics()["mag_late"])


@pytest.mark.parametrize("source", ["vqf", "aekf"])
def test_stage_hard_iron_bias_parameter(source, rng):
    """An uncalibrated magnetometer (a constant offset of 30 µT) with mag_bias_* set to that offset
    gives the calibrated result; without it the heading is wrong."""
    d = turning_device(rng, duration_s=20.0)
    order = arrival_order(d["t"], d["mt"], 0)
    bias_ut = np.array([25.0, -12.0, 8.0])
    clean = _drive(_stage(heading_source=source), d, order)
    corrected = _drive(_stage(heading_source=source, mag_bias_x=bias_ut[0] * 1e-6, mag_bias_y=bias_ut[1] * 1e-6,
                              mag_bias_z=bias_ut[2] * 1e-6), d, order, bias_ut)
    raw = _drive(_stage(heading_source=source), d, order, bias_ut)
    ks = sorted(clean)
    a = np.array([clean[k] for k in ks])
    np.testing.assert_allclose(np.array([corrected[k] for k in ks]), a, atol=1e-9)
    err_raw = _angle_deg(np.array([raw[k] for k in ks]), d["q"][-len(ks):])
    err_ok = _angle_deg(a, d["q"][-len(ks):])
    assert np.median(err_ok[len(ks) // 2:]) < 2.0 < np.median(err_raw[len(ks) // 2:])


def test_stage_auto_runs_vqf_and_config_errors():
    assert _stage().filter_name == "vqf"
    assert _stage(heading_source="aekf").filter_name == "aekf"
    with pytest.raises(ConfigError, match="mag_max_delay_s"):
        _stage(mag_max_delay_s=-1.0)
    with pytest.raises(ConfigError, match="mag_bias_x"):
        _stage(mag_bias_x=math.nan)


def test_field_constant_is_a_plausible_earth_field():
    assert 25.0 < np.linalg.norm(FIELD_ENU_UT) < 65.0


@pytest.mark.parametrize("source", ["aekf"])
def test_disturbance_that_comes_and_goes_is_rejected_and_recovered_from(source, rng):
    """A steel door for 8 s while turning: the field swings 60° and grows 50 % (known answer: the
    true orientation). The AEKF's heading holds through it and is right again after it. (VQF with
    its default parameters lets this one pull its heading about 21° by the end of the 8 s, so it is
    not held to this bar.)"""
    d = turning_device(rng, duration_s=50.0, yaw_rate=0.1)
    mag = d["mag"].copy()
    ts = (d["mt"] - d["mt"][0]) * 1e-9
    on = (ts > 25.0) & (ts < 33.0)
    c, s = math.cos(1.05), math.sin(1.05)
    mag[on] = 1.5 * mag[on] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    d["mag"] = mag
    got = _drive(_stage(heading_source=source), d, arrival_order(d["t"], d["mt"], 0))
    ks = np.array(sorted(got))
    q = np.array([got[k] for k in ks])
    idx = np.searchsorted(d["t"], ks)
    yaw_err = np.degrees(np.abs(np.angle(np.exp(1j * (quat_yaw(q) - quat_yaw(d["q"][idx]))))))
    t_s = (ks - d["t"][0]) * 1e-9
    during = (t_s > 25.0) & (t_s < 33.0)
    assert np.max(yaw_err[(t_s > 15.0) & (t_s < 25.0)]) < 2.0          # settled before
    assert np.max(yaw_err[during]) < 5.0                               # rejected (60° unrejected)
    assert np.max(yaw_err[t_s > 40.0]) < 2.0                           # recovered after
