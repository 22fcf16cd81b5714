"""Step confidence in ``pdr/odom``: twist.covariance[0] round trip, and the stage publishing it."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.errors import InvalidMessageError
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.imu_stage import ImuStage, ImuStageParams
from msg_adapters.imu import imu_to_msg
from msg_adapters.odom import odom_from_msg, odom_to_msg
from test_stepometer import aperiodic_motion, gait


def test_speed_variance_round_trip_and_rejects_negative():
    msg = odom_to_msg(5, "u/odom", "u/base_link", 1.0, 2.0, 0.3, np.eye(3) * 0.1, 1.2, 0.05, speed_var=0.04)
    assert msg.twist.covariance[0] == 0.04 and sum(abs(v) for v in msg.twist.covariance) == 0.04
    assert odom_from_msg(msg).speed_var == 0.04
    assert odom_from_msg(odom_to_msg(5, "a", "b", 0, 0, 0, np.zeros((3, 3)), 0, 0)).speed_var == 0.0
    with pytest.raises(InvalidMessageError):
        odom_to_msg(5, "a", "b", 0, 0, 0, np.zeros((3, 3)), 0, 0, speed_var=-1.0)


def test_stage_publishes_low_confidence_as_speed_variance(rng):
    """Walking, then handling the phone: the handling hops carry a speed variance beyond the step-length
    term alone, and their along-track position variance grows although no steps are counted."""
    rate = 100.0
    stamps = 10**9 + np.round(np.arange(int(30 * rate)) * 1e9 / rate).astype(np.int64)
    acc = gait(rng, stamps, cadence_hz=1.8)
    late = stamps >= stamps[0] + 15 * 10**9
    acc[late] = aperiodic_motion(rng, stamps[late], std=1.5)
    stage = ImuStage(params_from_dict(ImuStageParams, {}), namespace="/u")
    odoms = []
    for t, a in zip(stamps, acc):
        odoms += [odom_from_msg(m) for topic, m in stage.process("imu/data_raw", imu_to_msg(int(t), "imu", a), int(t))
                  if topic == "pdr/odom"]
    odoms += [odom_from_msg(m) for topic, m in stage.finish() if topic == "pdr/odom"]
    assert sum(stage.diag.rejected.values()) == 0
    walking = [o for o in odoms if 3e9 < o.stamp_ns - stamps[0] < 12e9]
    handling = [o for o in odoms if o.stamp_ns - stamps[0] > 19e9]
    rel = stage.pdr.params.step_length_rel_std
    assert all(o.speed_var == pytest.approx((rel * o.speed) ** 2) for o in walking)
    unsure = [o for o in handling if o.speed_var > (rel * o.speed) ** 2 + 1e-12]
    assert len(unsure) > 0.5 * len(handling)
    tr = [np.trace(o.cov[:2, :2]) for o in handling]
    assert tr[-1] > tr[0]
    assert float(stage.extra_diagnostics()["step_confidence"]) < 1.0
