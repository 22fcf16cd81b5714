"""indoor_loc.measurements: the one pdr/odom decoder (online == batch, against the producer), wrap_angle."""
from __future__ import annotations

import math

import numpy as np
import pytest

from indoor_loc.errors import InvalidInputError, InvalidMessageError
from indoor_loc.imu.pdr import PdrParams, pdr_batch
from indoor_loc.measurements import PdrIntervalDecoder, pdr_intervals, wrap_angle
from msg_adapters.odom import PdrOdomReader, odom_to_msg, pdr_intervals_from_msgs


def _walk(rng: np.random.Generator, n: int = 60, rel_std: float = 0.1):
    t0 = np.arange(n, dtype=np.int64) * 400_000_000 + 1_000_000_000
    steps = rng.uniform(0.0, 2.0, n)
    yaw = np.cumsum(rng.normal(0.0, 0.6, n))          # crosses +-pi many times
    var = rng.uniform(1e-4, 0.05, n)
    params = PdrParams(step_length_m=0.7, step_length_rel_std=rel_std)
    return t0, steps, wrap_angle(yaw), var, pdr_batch(t0, t0 + 320_000_000, steps, wrap_angle(yaw), var, params)


def test_wrap_angle_float_and_array_agree_to_the_bit(rng):
    a = rng.uniform(-50, 50, 1000)
    out = wrap_angle(a)
    assert out.shape == a.shape and np.all(out >= -math.pi) and np.all(out < math.pi)
    assert [wrap_angle(float(v)) for v in a] == out.tolist()
    assert wrap_angle(math.pi) == -math.pi and wrap_angle(0.0) == 0.0


def test_decoder_recovers_the_producers_steps_heading_change_and_along_track_variance(rng):
    t0, steps, yaw, var, poses = _walk(rng)
    dec = PdrIntervalDecoder(0.7)
    out = [dec.update(p.stamp_ns, p.x, p.y, p.yaw, p.cov) for p in poses]
    assert out[0] is None and all(iv is not None for iv in out[1:])
    ivs = [iv for iv in out if iv is not None]
    np.testing.assert_allclose([iv.steps for iv in ivs], steps[1:], atol=1e-9)
    np.testing.assert_allclose([iv.distance_m for iv in ivs], 0.7 * steps[1:], atol=1e-9)
    np.testing.assert_allclose([iv.dtheta for iv in ivs], wrap_angle(np.diff(yaw)), atol=1e-9)
    # the producer adds (rel_std * d)^2 along the track
    np.testing.assert_allclose([iv.distance_var for iv in ivs], (0.1 * 0.7 * steps[1:]) ** 2, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose([iv.dtheta_var for iv in ivs], var[1:] + var[:-1], rtol=1e-12)
    assert [iv.t_start_ns for iv in ivs] == [p.stamp_ns for p in poses[:-1]]


def test_online_equals_batch(rng):
    *_, poses = _walk(rng, n=80)
    dec = PdrIntervalDecoder(0.7)
    online = [iv for p in poses if (iv := dec.update(p.stamp_ns, p.x, p.y, p.yaw, p.cov)) is not None]
    batch = pdr_intervals(np.array([p.stamp_ns for p in poses]), np.array([(p.x, p.y) for p in poses]),
                          np.array([p.yaw for p in poses]), np.array([p.cov for p in poses]), step_length_m=0.7)
    assert len(batch) == len(online) == len(poses) - 1
    for i, iv in enumerate(online):
        np.testing.assert_allclose(tuple(batch.row(i)), tuple(iv), rtol=1e-12, atol=1e-12)


def test_messages_decode_like_the_core(rng):
    *_, poses = _walk(rng, n=20)
    msgs = [odom_to_msg(p.stamp_ns, "alice/odom", "alice/base_link", p.x, p.y, p.yaw, p.cov, p.speed, p.yaw_rate)
            for p in poses]
    reader = PdrOdomReader(0.7)
    online = [reader.read(m)[1] for m in msgs]
    batch = pdr_intervals_from_msgs(msgs, 0.7)
    assert online[0] is None
    np.testing.assert_allclose([iv.steps for iv in online[1:]], batch.steps, rtol=1e-12)
    np.testing.assert_allclose([iv.dtheta for iv in online[1:]], batch.dtheta, rtol=1e-12, atol=1e-15)


def test_time_going_backwards_is_refused_and_changes_nothing():
    dec = PdrIntervalDecoder(0.65)
    dec.update(10, 0.0, 0.0, 0.0, np.zeros((3, 3)))
    with pytest.raises(InvalidInputError, match="non_monotonic_stamp"):
        dec.update(10, 1.0, 0.0, 0.0, np.zeros((3, 3)))
    iv = dec.update(20, 0.65, 0.0, 0.0, np.zeros((3, 3)))
    assert iv is not None and iv.steps == pytest.approx(1.0) and iv.t_start_ns == 10
    reader = PdrOdomReader(0.65)
    reader.read(odom_to_msg(5, "o", "b", 0.0, 0.0, 0.0, np.zeros((3, 3)), 0.0, 0.0))
    with pytest.raises(InvalidMessageError, match="non_monotonic_stamp"):
        reader.read(odom_to_msg(5, "o", "b", 1.0, 0.0, 0.0, np.zeros((3, 3)), 0.0, 0.0))
    assert reader.last_stamp_ns == 5


@pytest.mark.parametrize("kwargs, match", [
    (dict(stamps_ns=[0, 1], xy=[[0, 0]], yaw=[0, 0]), "shape"),
    (dict(stamps_ns=[0, 0], xy=[[0, 0], [1, 0]], yaw=[0, 0]), "non_monotonic_stamp"),
    (dict(stamps_ns=[0, 1], xy=[[0, 0], [1, 0]], yaw=[0, 0], cov=np.zeros((2, 2))), "shape"),
])
def test_batch_refuses_bad_arrays(kwargs, match):
    with pytest.raises(InvalidInputError, match=match):
        pdr_intervals(**kwargs, step_length_m=0.65)


def test_step_length_must_be_positive():
    with pytest.raises(InvalidInputError, match="step_length_m > 0"):
        PdrIntervalDecoder(0.0)
