"""VQF orientation (the ``vqf`` package's compiled core) online, sample by sample, with stamps.

Method: Laidig & Seel, "VQF: Highly Accurate IMU Orientation Estimation with Bias Estimation and
Magnetic Disturbance Rejection", Information Fusion 91, 2023 (doi:10.1016/j.inffus.2022.10.014):
gyroscope strapdown integration, accelerometer tilt correction in an almost-inertial frame with a
low-passed (τ_acc) gravity direction, rest and motion gyroscope-bias estimation, and a heading-only
magnetometer correction (τ_mag) with magnetic-disturbance rejection (field norm and dip against a
learnt reference). This module wraps ``vqf.VQF`` (C++), calling ``updateGyr``/``updateAcc`` per IMU
sample and ``updateMag`` per magnetometer sample at its own rate.

What the wrapper adds for data as it comes from phones and drivers:

- **Stamps, not a fixed rate.** VQF integrates ``ω·Ts`` with a fixed sampling time. Each gyroscope
  sample is passed as ``b + (ω − b)·dt/Ts`` (``b`` VQF's own bias estimate, ``dt`` from the stamps),
  so the integrated rotation is ``(ω − b)·dt`` exactly on jittery or irregular stamps; gaps longer
  than ``max_dt_s`` are not integrated. ``Ts`` (and the magnetometer's) only set the filters' time
  constants: given as rates, or measured from the first two samples of each stream.
- **Magnetometer at its own rate.** ``update_mag`` is called between IMU samples in stamp order
  (see :mod:`indoor_loc.imu.mag_sync`); when the magnetometer's rate is first measured the filter
  is rebuilt with it, carrying its whole state over.
- **Covariance.** VQF gives none; ROS consumers need one. The tilt standard deviation is
  ``tilt_std``; the heading's is ``mag_heading_std`` while the magnetometer corrects it, and grows
  linearly at ``heading_drift`` (rad/s) while it does not (disturbance rejected, magnetometer
  missing); without any magnetometer the heading is the 6-D one (its start is arbitrary:
  variance π²/3).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from indoor_loc.errors import InvalidInputError
from indoor_loc.params import field, require

_DEG = math.pi / 180.0
UNKNOWN_HEADING_VAR = math.pi ** 2 / 3.0


@dataclass(frozen=True)
class VqfParams:
    """Parameters of :class:`VqfFilter` (SI units, angles in rad); VQF's own defaults otherwise."""

    gyr_rate_hz: float = field(0.0, "nominal IMU rate, Hz (0 = from the first two stamps); sets VQF's Ts")
    mag_rate_hz: float = field(0.0, "nominal magnetometer rate, Hz (0 = from its first two stamps)")
    tau_acc_s: float = field(3.0, "VQF tauAcc: time constant of the accelerometer (tilt) correction, s")
    tau_mag_s: float = field(9.0, "VQF tauMag: time constant of the magnetometer (heading) correction, s")
    mag_dist_rejection: bool = field(True, "VQF magnetic disturbance rejection (field norm/dip gating)")
    rest_bias_est: bool = field(True, "VQF gyroscope-bias estimation at rest")
    motion_bias_est: bool = field(True, "VQF gyroscope-bias estimation in motion")
    max_dt_s: float = field(0.5, "larger IMU sample gaps are not integrated, s")
    tilt_std: float = field(2.0 * _DEG, "reported roll/pitch standard deviation, rad")
    mag_heading_std: float = field(4.0 * _DEG, "reported heading standard deviation while the "
                                               "magnetometer corrects it, rad")
    heading_drift: float = field(0.5 * _DEG, "growth of the heading standard deviation without a "
                                             "magnetometer correction, rad/s")

    def validate(self) -> None:
        owner = type(self).__name__
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool):
                continue
            require(isinstance(v, (int, float)) and math.isfinite(v), owner, f.name, "a finite number", v)
        for name in ("gyr_rate_hz", "mag_rate_hz"):
            require(getattr(self, name) >= 0, owner, name, ">= 0", getattr(self, name))
        for name in ("tau_acc_s", "tau_mag_s", "max_dt_s", "tilt_std", "mag_heading_std"):
            require(getattr(self, name) > 0, owner, name, "> 0", getattr(self, name))
        require(self.heading_drift >= 0, owner, "heading_drift", ">= 0", self.heading_drift)


@dataclass
class VqfFilterState:
    """Resumable state: VQF's own state dict and its sampling times, plus the wrapper's memory."""

    vqf_state: dict[str, Any] | None = None
    gyr_ts: float = 0.0
    mag_ts: float = 0.0
    mag_ts_measured: bool = False
    stamp_ns: int | None = None
    first_imu: tuple[Any, ...] | None = None          # (t_ns, gyr, acc) waiting for the IMU rate
    mag_stamp_ns: int | None = None
    mag_seen: bool = False
    last_mag_ok_ns: int | None = None       # last magnetometer sample VQF accepted (not rejected)
    n_mag: int = 0
    n_mag_rejected: int = 0
    q: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0)         # last output, w x y z

    def copy(self) -> "VqfFilterState":
        import copy
        return copy.deepcopy(self)


def _ts_from_rate(rate_hz: float) -> float:
    return 1.0 / rate_hz if rate_hz > 0 else 0.0


class VqfFilter:
    """Online VQF with stamps. ``update_imu(t, gyr, acc)`` per IMU sample, ``update_mag(t, mag)`` per
    magnetometer sample, in stamp order; ``state()``/``set_state()`` to save and resume."""

    def __init__(self, params: VqfParams | None = None) -> None:
        self.params = params if params is not None else VqfParams()
        self.params.validate()
        self._st = VqfFilterState()
        self._vqf: Any = None                   # the vqf package's VQF object (untyped extension)
        self._q = np.array([1.0, 0.0, 0.0, 0.0])

    # -- construction ---------------------------------------------------------------------------------
    def _make(self, gyr_ts: float, mag_ts: float, state: dict[str, Any] | None) -> Any:
        from vqf import VQF

        p = self.params
        v = VQF(gyr_ts, gyr_ts, mag_ts, tauAcc=p.tau_acc_s, tauMag=p.tau_mag_s,
                magDistRejectionEnabled=p.mag_dist_rejection, restBiasEstEnabled=p.rest_bias_est,
                motionBiasEstEnabled=p.motion_bias_est)
        if state is not None:
            v.state = state
        return v

    def _ensure(self) -> None:
        """Rebuild the C++ object from the saved state (after ``set_state``)."""
        st = self._st
        if self._vqf is None and st.vqf_state is not None:
            self._vqf = self._make(st.gyr_ts, st.mag_ts, st.vqf_state)

    # -- updates --------------------------------------------------------------------------------------
    @property
    def initialised(self) -> bool:
        return self._st.vqf_state is not None or self._vqf is not None

    def update_imu(self, t_ns: int, gyr: ArrayLike, acc: ArrayLike) -> None:
        """One IMU sample: ``gyr`` (3,) rad/s, ``acc`` (3,) m/s². Raises InvalidInputError on non-finite
        input or a stamp that does not increase (state unchanged)."""
        g = np.asarray(gyr, dtype=float).reshape(3)
        a = np.asarray(acc, dtype=float).reshape(3)
        if not (np.isfinite(g).all() and np.isfinite(a).all()):
            raise InvalidInputError("nan", f"non-finite gyroscope/accelerometer sample at stamp {t_ns} ns")
        st = self._st
        if st.stamp_ns is not None and t_ns <= st.stamp_ns:
            raise InvalidInputError("non_monotonic_stamp", f"stamps must increase: {t_ns} ns after {st.stamp_ns} ns")
        self._ensure()
        if self._vqf is None:
            ts = _ts_from_rate(self.params.gyr_rate_hz)
            if ts == 0.0:
                if st.first_imu is None:               # wait for a second stamp to know the rate
                    st.first_imu = (t_ns, g, a)
                    st.stamp_ns = t_ns
                    return
                ts = (t_ns - st.first_imu[0]) * 1e-9
                if ts > self.params.max_dt_s:
                    st.first_imu = (t_ns, g, a)
                    st.stamp_ns = t_ns
                    return
            st.gyr_ts = ts
            st.mag_ts = _ts_from_rate(self.params.mag_rate_hz) or ts
            st.mag_ts_measured = self.params.mag_rate_hz > 0
            self._vqf = self._make(st.gyr_ts, st.mag_ts, None)
            if st.first_imu is not None:
                t0, g0, a0 = st.first_imu
                st.first_imu = None
                self._vqf.updateGyr(np.ascontiguousarray(g0))
                self._vqf.updateAcc(np.ascontiguousarray(a0))
                st.stamp_ns = t0
            else:                                      # first sample with a known rate
                self._vqf.updateGyr(np.ascontiguousarray(g))
                self._vqf.updateAcc(np.ascontiguousarray(a))
                st.stamp_ns = t_ns
                self._q = np.asarray(self._vqf.getQuat9D() if st.mag_seen else self._vqf.getQuat6D())
                st.vqf_state = None
                return
        assert st.stamp_ns is not None           # set with the first sample
        dt = (t_ns - st.stamp_ns) * 1e-9
        v = self._vqf
        if dt <= self.params.max_dt_s:
            b = np.asarray(v.getBiasEstimate()[0])
            gs = b + (g - b) * (dt / st.gyr_ts)
        else:
            gs = np.asarray(v.getBiasEstimate()[0])     # gap: no rotation integrated
        v.updateGyr(np.ascontiguousarray(gs))
        v.updateAcc(np.ascontiguousarray(a))
        st.stamp_ns = t_ns
        self._q = np.asarray(v.getQuat9D() if st.mag_seen else v.getQuat6D())
        st.vqf_state = None

    def update_mag(self, t_ns: int, mag: ArrayLike) -> None:
        """One magnetometer sample (3,), any unit, at its own stamp (after the IMU samples up to it).
        Ignored before the first IMU sample. Raises InvalidInputError on non-finite input."""
        m = np.asarray(mag, dtype=float).reshape(3)
        if not np.isfinite(m).all():
            raise InvalidInputError("nan", f"non-finite magnetometer sample at stamp {t_ns} ns")
        st = self._st
        if st.mag_stamp_ns is not None and t_ns <= st.mag_stamp_ns:
            raise InvalidInputError("non_monotonic_stamp",
                                    f"magnetometer stamps must increase: {t_ns} ns after {st.mag_stamp_ns} ns")
        self._ensure()
        prev = st.mag_stamp_ns
        st.mag_stamp_ns = t_ns
        if self._vqf is None:
            return
        if not st.mag_ts_measured and prev is not None:
            dtm = (t_ns - prev) * 1e-9
            if 0.0 < dtm <= self.params.max_dt_s:
                st.mag_ts = dtm
                st.mag_ts_measured = True
                self._vqf = self._make(st.gyr_ts, st.mag_ts, self._vqf.state)
        v = self._vqf
        v.updateMag(np.ascontiguousarray(m))
        st.mag_seen = True
        st.n_mag += 1
        if v.getMagDistDetected():
            st.n_mag_rejected += 1
        else:
            st.last_mag_ok_ns = t_ns
        self._q = np.asarray(v.getQuat9D())
        st.vqf_state = None

    # -- outputs --------------------------------------------------------------------------------------
    @property
    def quat_wxyz(self) -> np.ndarray:
        """Unit quaternion (w, x, y, z), device→ENU (magnetic north with a magnetometer), (4,)."""
        return self._q.copy()

    @property
    def orientation_cov(self) -> np.ndarray:
        """(3, 3) rad² about ENU x, y, z (see the module docstring: a model, VQF has no covariance)."""
        p, st = self.params, self._st
        if not st.mag_seen:
            yaw_var = UNKNOWN_HEADING_VAR
        else:
            since = 0.0 if st.last_mag_ok_ns is None or st.stamp_ns is None else \
                max(0.0, (st.stamp_ns - st.last_mag_ok_ns) * 1e-9)
            yaw_var = min((p.mag_heading_std + p.heading_drift * since) ** 2, UNKNOWN_HEADING_VAR)
        return np.diag([p.tilt_std ** 2, p.tilt_std ** 2, yaw_var])

    @property
    def gyro_bias(self) -> np.ndarray:
        self._ensure()
        return np.zeros(3) if self._vqf is None else np.asarray(self._vqf.getBiasEstimate()[0])

    @property
    def mag_disturbed(self) -> bool:
        self._ensure()
        return bool(self._vqf is not None and self._vqf.getMagDistDetected())

    @property
    def n_mag_rejected(self) -> int:
        return self._st.n_mag_rejected

    def state(self) -> VqfFilterState:
        st = self._st.copy()
        if self._vqf is not None:
            st.vqf_state = self._vqf.state
        st.q = tuple(float(x) for x in self._q)
        return st

    def set_state(self, state: VqfFilterState) -> None:
        st = state.copy()
        self._q = np.array(st.q, dtype=float)
        self._st = st
        self._vqf = None
        self._ensure()
        self._st.vqf_state = None


def vqf_batch(t_ns: ArrayLike, gyr: ArrayLike, acc: ArrayLike, mag_t_ns: ArrayLike | None = None,
              mag: ArrayLike | None = None, params: VqfParams | None = None) -> np.ndarray:
    """:class:`VqfFilter` over whole arrays, the magnetometer merged by stamp as online
    (:func:`indoor_loc.imu.mag_sync.merge_events`). Returns (N, 4) w x y z after each IMU sample."""
    from indoor_loc.imu.mag_sync import IMU, merge_events

    f = VqfFilter(params)
    t = np.asarray(t_ns, dtype=np.int64)
    g = np.asarray(gyr, dtype=float)
    a = np.asarray(acc, dtype=float)
    out = np.empty((len(t), 4))
    mt = None if mag_t_ns is None else np.asarray(mag_t_ns, dtype=np.int64)
    mg = None if mag is None else np.asarray(mag, dtype=float)
    for kind, i in merge_events(t, mt):
        if kind == IMU:
            f.update_imu(int(t[i]), g[i], a[i])
            out[i] = f.quat_wxyz
        else:
            assert mt is not None and mg is not None
            f.update_mag(int(mt[i]), mg[i])
    return out


def update_imu_run(f: VqfFilter, stamps_ns: list[int], gyr: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """:meth:`VqfFilter.update_imu` for each of a run of samples of a running filter (initialised, no
    sample waiting for the rate), with the same floating-point operations in the same order, so the
    state and quaternions are those of the sample-by-sample calls; the checks those calls make
    (finite values, increasing stamps after the last one) are the caller's, made on the whole run
    before (:func:`indoor_loc.bag.bulk.imu_samples` and the run's stamps). Returns the quaternion
    (w, x, y, z) after each sample, (N, 4)."""
    f._ensure()
    v = f._vqf
    st = f._st
    assert v is not None and st.stamp_ns is not None and st.first_imu is None
    ts, max_dt = st.gyr_ts, f.params.max_dt_s
    quat = v.getQuat9D if st.mag_seen else v.getQuat6D
    bias = v.getBiasEstimate
    upd_g, upd_a = v.updateGyr, v.updateAcc
    contig = np.ascontiguousarray
    g_all = np.asarray(gyr, dtype=float)
    a_all = contig(acc, dtype=float)
    out = np.empty((len(stamps_ns), 4))
    prev = st.stamp_ns
    for i, t_ns in enumerate(stamps_ns):
        dt = (t_ns - prev) * 1e-9
        b = np.asarray(bias()[0])
        gs = b + (g_all[i] - b) * (dt / ts) if dt <= max_dt else b
        upd_g(contig(gs))
        upd_a(a_all[i])
        prev = t_ns
        out[i] = quat()
    st.stamp_ns = prev
    f._q = out[-1].copy()
    st.vqf_state = None
    return out
