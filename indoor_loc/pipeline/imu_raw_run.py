"""The column path of ``imu_node`` for runs of ``imu/data_raw`` (a phone's or robot's IMU with a gyroscope,
no magnetometer): the steady state of a multi-user ``imu_node``, where the IMU path costs most of the CPU
per user (docs/scaling.md).

:meth:`ImuStage._raw_sample` takes one sample at a time: the time policy, the stepometer's scalar path,
the magnetometer merge, VQF, the heading history, one ``imu/data`` packed per sample. A run the node took
from one user's subscription (decoded in bulk, :func:`indoor_loc.bag.bulk.imu_samples`) goes here in
cuts that end on the sample completing a stepometer window: VQF runs its compiled core over the cut
(:func:`indoor_loc.imu.vqf_filter.update_imu_run`, the same arithmetic), yaw and headings column-wise,
the stepometer's grid in one vectorised step (:meth:`Stepometer.extend_steady`), the cut's ``imu/data``
packed together (:func:`msg_adapters.imu_cdr.imu_cdr_run`) — the same values, state, outputs and order
as one sample at a time (``test/test_imu_raw_run.py``).

The AEKF (``heading_source: aekf``, the simulator's) takes the same path: its per-sample steps over the
cut in one call (:meth:`indoor_loc.imu.aekf.Aekf.update_imu_run`, the same function on the same floats),
its covariance per sample (it grows between tilt updates) packed with each ``imu/data``
(:func:`msg_adapters.imu_cdr.imu_cdr_run_covs`).

Taken only when every sample of the run would take the plain way one by one (:func:`run_ok`): the
stepometer fed by ``imu/data_raw`` and running steadily, the filter running (VQF not waiting for its
rate, the AEKF initialised), no magnetometer ever seen (nothing held in the merge), every sample with a
gyroscope, stamps increasing and passing the time policy. Anything else (start-up, a gap, a
magnetometer, a sample the adapter rejects) goes one sample at a time as before.
"""
from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from indoor_loc.imu.aekf import Aekf
from indoor_loc.imu.vqf_filter import VqfFilter, update_imu_run
from indoor_loc.pipeline.time_policy import Order
from msg_adapters.imu import imu_to_msg
from msg_adapters.imu_cdr import imu_cdr, imu_cdr_run, imu_cdr_run_covs

if TYPE_CHECKING:
    from indoor_loc.pipeline.imu_stage import ImuStage

TOPIC = "imu/data_raw"
#: runs at least this long have their stepometer windows analysed together first (offline runs)
PREFETCH_MIN = 100


def run_ok(stage: "ImuStage", items: Any, recv_ns: list[int]) -> bool:
    """Whether :meth:`ImuStage._raw_sample` would take every item of the run the plain way (module doc)."""
    arrays = getattr(items, "arrays", None)
    if arrays is None or len(items) < 2 or stage.map_odom is not None:
        return False
    f = stage.filter
    if stage._acc_topic != TOPIC or stage._external_orientation:
        return False
    if isinstance(f, Aekf):
        a = f._st
        if not a.initialised or a.pending_mag is not None or a.mag_ref_ok or a.att_stamp_ns != a.stamp_ns:
            return False
        filter_ns = a.stamp_ns
    elif isinstance(f, VqfFilter):
        if not f.initialised or f._st.first_imu is not None or f._st.stamp_ns is None or f._st.mag_seen:
            return False
        filter_ns = f._st.stamp_ns
    else:
        return False
    ms = stage.mag_sync._st
    if ms.seen_mag or ms.imu or ms.mag or not all(items._gyro_on):
        return False
    t = items.stamps
    last = stage._last_raw_ns
    if last is None or t[0] <= last or t[0] <= filter_ns or any(b <= a for a, b in zip(t, t[1:])):
        return False
    return stage.time.passes_run("", TOPIC, t, list(recv_ns), Order.STRICT)


def process_raw_run(stage: "ImuStage", items: Any, recv_ns: list[int]) -> list[tuple[int, str, Any]]:
    """A run :func:`run_ok` allowed: outputs ``[(recv_ns, topic, message)]`` as ``Stage.process_batch``
    gives them; counters, time policy and diagnostics as one sample at a time."""
    arrays = items.arrays
    n = len(items)
    stamps: list[int] = items.stamps
    acc = arrays.linear_acceleration
    gyro = arrays.angular_velocity
    diag = stage.diag
    stats = diag.received[TOPIC]
    t0 = time.perf_counter()
    diag.now_ns = recv_ns[-1]
    f = stage.filter
    offset = stage.params.heading_offset_rad
    step = stage.stepometer
    if n >= PREFETCH_MIN:
        step.prefetch(np.asarray(stamps, dtype=np.int64), acc)   # a long run (offline): windows analysed together
    out: list[tuple[int, str, Any]] = []
    try:
        # the filter does not read the stepometer: the whole run first (the same arithmetic per sample)
        if isinstance(f, Aekf):
            q_rows, covs = f.update_imu_run(stamps, gyro, acc)
            quats = np.array(q_rows)
            var_zs = [c[8] for c in covs]       # the per-sample path's float(orientation_cov[2, 2])
            data = _imu_data(stage, stamps, arrays.frame_id, acc, gyro, quats[:, [1, 2, 3, 0]], covs)
        else:
            assert isinstance(f, VqfFilter)
            cov = f.orientation_cov             # VQF without a magnetometer: the same for every sample
            var_zs = [float(cov[2, 2])] * n
            quats = update_imu_run(f, stamps, gyro, acc)
            data = _imu_data(stage, stamps, arrays.frame_id, acc, gyro, quats[:, [1, 2, 3, 0]], cov)
        add_heading, add, update = step.add_heading, stage.headings.add, step.update
        published = stage.time.published
        acc_rows = acc.tolist()
        for k, (t, (w, x, y, z)) in enumerate(zip(stamps, quats.tolist())):
            hops = update(t, acc_rows[k])       # before this sample's heading, as _raw_sample
            yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))    # yaw_xyzw
            add(t, yaw + offset, var_zs[k])
            add_heading(t, yaw)
            msg = data[k]
            if msg is not None:
                published("", "imu/data", t)   # its echo recognised (time_policy.py: echoes)
                out.append((recv_ns[k], "imu/data", msg))
            if hops:
                for o_topic, o_msg in stage._hops(hops):
                    out.append((recv_ns[k], o_topic, o_msg))
        stage._last_raw_ns = stamps[-1]
        ms = stage.mag_sync._st
        ms.last_imu_in_ns = ms.last_released_imu_ns = stamps[-1]
    except Exception as err:  # noqa: BLE001 - as process(): counted, the run goes on
        stage._reject("internal_error", f"{TOPIC} (batch of {n}): {type(err).__name__}: {err}")
    for _, o_topic, _ in out:
        diag.published[o_topic] += 1
    stage.time.accepted("", TOPIC, stamps[-1])
    stats.count += n
    stats.first_ns = recv_ns[0] if stats.first_ns is None else stats.first_ns
    stats.last_ns = recv_ns[-1]
    diag.process_s.append((time.perf_counter() - t0) / n)       # one entry per run: its mean
    return out


def _imu_data(stage: "ImuStage", stamps: list[int], frame: str, acc: np.ndarray, gyro: np.ndarray,
              q_xyzw: np.ndarray, cov: np.ndarray | list) -> list[Any]:
    """The run's ``imu/data`` messages (None for one the encoder refuses, counted as it would be);
    ``cov`` (3, 3) for every sample, or a list of each sample's 9 entries."""
    per_sample = isinstance(cov, list)
    if stage.raw_outputs:
        packed = imu_cdr_run_covs(stamps, frame, acc, gyro, q_xyzw, cov) if isinstance(cov, list) else \
            imu_cdr_run(stamps, frame, acc, gyro, q_xyzw, cov)
        if packed is not None:
            return packed
    encode = imu_cdr if stage.raw_outputs else imu_to_msg
    msgs: list[Any] = []
    for k, s in enumerate(stamps):
        try:
            c = np.array(cov[k]).reshape(3, 3) if per_sample else cov
            msgs.append(encode(s, frame, acc[k], gyro[k], q_xyzw[k], c))
        except Exception as err:  # noqa: BLE001 - as _judged counts a sample's error
            stage._reject(getattr(err, "reason", "internal_error"), f"{TOPIC}: {err}")
            msgs.append(None)
    return msgs
