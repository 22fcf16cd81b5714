"""Adaptive error-state EKF for orientation (device→ENU) and gyroscope bias.

Method (the AEKF of Nowicki & Skrzypczyński 2019, Sec. 3, after their ref. [45]): the state is a unit quaternion ``q`` (device→ENU,
``v_enu = R(q) v_dev``) and the gyroscope bias ``b`` (rad/s, device frame). The filter is
multiplicative: its 6-D error state is ``δx = [δθ, δb]`` with ``q_true = exp(δθ) ⊗ q`` — δθ is a
small rotation about the **ENU** axes, so ``P[0:3, 0:3]`` is directly the orientation covariance
about east/north/up (≈ roll/pitch/yaw for a near-level device; ``P[2, 2]`` is the heading
variance) as ``sensor_msgs/Imu.orientation_covariance`` wants it (fixed axes).

- Prediction: ``q ← q ⊗ exp((ω − b) dt)``; ``δθ' = δθ − R(q) δb dt``, so
  ``F = [[I, −R dt], [0, I]]``, ``Q = diag(σ_g² dt I, σ_bw² dt I)``.
- Accelerometer (gravity direction): ``a_e = R(q) a/|a|`` ≈ ``e_z + e_z × δθ``, hence
  ``(a_e,y, −a_e,x)`` measures ``(δθ_x, δθ_y)``. Tilt only: the accelerometer never touches heading.
  Adaptation to the motion type: the noise is ``σ_a² + (|a|−g)² + s²`` (m/s²)², with ``s`` the
  short-term standard deviation of |a| (≈ 0.2 s window), divided by g² to give rad². Smooth motion
  keeps a small noise; high acceleration (|a|−g or s above ``acc_reject_m_s2``) skips the update.
- Magnetometer (heading only): ``m_e = R(q) m``; the heading of its horizontal projection
  ``atan2(m_e,x, m_e,y) − declination`` measures ``δθ_z`` (H = e_z). The inclination of the field
  is projected out and the gain on ``δθ_x, δθ_y`` is forced to zero (Joseph-form covariance, still
  exact for this sub-optimal gain), so a magnetic disturbance can never tilt the estimate. The
  noise is inflated by the field's norm and dip-angle anomalies relative to a reference learnt online
  (a slow moving average while the field agrees with it); beyond the tolerances the update is
  skipped, and a disturbance that persists ``mag_relearn_s`` is accepted as the new environment.
  Innovations beyond the ``mag_gate_nis`` gate inflate the noise (robust, no lock-out).
- Reported covariance: the per-sample magnetometer noise is treated as white, but a magnetometer
  heading also carries a slowly varying systematic error (calibration residuals, local field);
  ``mag_heading_sys_std²`` is added to the reported heading variance once a field was seen. On
  BROAD this makes the normalised heading error RMS 0.4–0.9 (without it: 1.5–3.6, over-confident).
- Rest: when the gyroscope and accelerometer are still for ``rest_min_s``, the measured rate is a
  direct measurement of the bias (zero-rate update), as in VQF's rest bias estimation.
- 6-D mode (no magnetometer): heading starts from the shortest-arc tilt (same convention as VQF's
  6-D output) with variance ``π²/3`` (unknown), then grows with gyro noise and bias uncertainty.

- Magnetometer at its own stamp (``Aekf.update_mag``, ``aekf_batch(..., mag_t_ns=...)``): the
  attitude is propagated from the last IMU stamp to the magnetometer's with the last gyroscope
  sample, updated there, and the next IMU sample continues from that stamp.

Structure as in VQF (Laidig & Seel, "VQF: Highly accurate IMU orientation estimation with bias
estimation and magnetic disturbance rejection", Information Fusion 2023): one function per sensor
step — :func:`_predict` (gyroscope), :func:`_update_acc`, :func:`_update_rest`, :func:`_update_mag` —
sharing :func:`_correct` for the error-state correction. Per-sample Python with plain floats (no 6×6
numpy temporaries; the covariance products are unrolled on the row-major list ``P``): ``aekf_batch``
and ``Aekf`` run the very same steps (:func:`_run`, :func:`_update_mag_at_stamp`), so online and batch
agree to the last bit. A plain matrix-form implementation in the tests checks the unrolled algebra.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike

from indoor_loc.errors import InvalidInputError
from indoor_loc.measurements import wrap_angle
from indoor_loc.params import field, require

_DEG = math.pi / 180.0


@dataclass(frozen=True)
class AekfParams:
    """Noise densities and adaptation thresholds of :class:`Aekf` (SI units, angles in rad)."""

    gyro_noise: float = field(0.002, "gyroscope angle random walk incl. model errors, rad/s/√Hz")
    gyro_scale_error: float = field(0.0, "relative gyro scale/misalignment error added to the angle "
                                         "noise as (k·|ω|)²·dt, 1")
    bias_init_std: float = field(0.5 * _DEG, "initial gyroscope bias standard deviation, rad/s")
    bias_walk: float = field(5e-5, "gyroscope bias random walk, rad/s/√s")
    gravity: float = field(9.81, "local gravity magnitude, m/s²")
    acc_noise: float = field(2.0, "accelerometer noise for the tilt update in smooth motion, m/s² "
                                  "per sample")
    acc_lp_tau_s: float = field(1.5, "time constant of the 2nd-order Butterworth low-pass applied to the "
                                     "accelerometer in the ENU frame before the tilt update (0 = raw); the "
                                     "Kalman gain smooths again, so this is half VQF's 3 s, s")
    acc_stat_tau_s: float = field(0.2, "time constant of the running mean/variance of |a|, s")
    acc_adapt_gain: float = field(0.05, "weight c of the motion terms in the tilt noise "
                                      "σ_a² + c·((|a|−g)² + var|a|), 1")
    acc_reject_m_s2: float = field(2.0, "skip the tilt update when ||a|−g| or the short-term std of |a| "
                                        "exceeds this (high-acceleration motion), m/s²")
    mag_noise: float = field(0.3, "magnetometer heading noise per sample in an undisturbed field, rad")
    mag_rate_noise_s: float = field(0.05, "heading noise growing with the rotation rate, rad per rad/s "
                                         "(≈ magnetometer/gyroscope timing mismatch), s")
    mag_anomaly_tau_s: float = field(0.0, "time constant smoothing the norm/dip anomalies before the "
                                          "tolerance test (0 = per sample), s")
    mag_heading_sys_std: float = field(1.5 * _DEG, "systematic heading error of the magnetometer "
                                       "reference (calibration residuals, local field); added to the "
                                       "reported heading variance once a field was seen, rad")
    mag_norm_tol: float = field(0.1, "tolerated relative field-norm anomaly |‖m‖/ref − 1|; beyond, "
                                     "the magnetometer update is skipped, 1")
    mag_dip_tol: float = field(3.0 * _DEG, "tolerated dip-angle anomaly; beyond, the update is skipped, rad")
    mag_ref_tau_s: float = field(30.0, "time constant of the online field-norm/dip reference, s")
    mag_relearn_s: float = field(30.0, "a disturbance lasting longer than this becomes the new "
                                       "reference (changed environment), s")
    mag_relearn_first_s: float = field(5.0, "the same for the start-up reference (one sample, dipped through a "
                                            "start-up tilt), until it is confirmed, s")
    mag_ref_confirm_s: float = field(20.0, "the reference is confirmed once the field has agreed with it this "
                                           "long, s")
    mag_gate_nis: float = field(9.0, "normalised innovation squared above which the magnetometer noise "
                                     "is inflated, 1")
    mag_declination: float = field(0.0, "magnetic declination (east of true north positive); 0 keeps "
                                         "ENU aligned with magnetic north, rad")
    rest_gyro: float = field(2.0 * _DEG, "rest detection: max |ω−b| and deviation from its low-pass, rad/s")
    rest_acc_m_s2: float = field(0.3, "rest detection: max deviation of a from its low-pass, m/s²")
    rest_min_s: float = field(1.5, "rest detection: minimum still duration before bias updates, s")
    rest_gyro_noise: float = field(0.01, "gyroscope white noise per sample for the zero-rate update, rad/s")
    max_dt_s: float = field(0.5, "larger sample gaps are not integrated (covariance still grows), s")

    def validate(self) -> None:
        owner = type(self).__name__
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            require(isinstance(v, (int, float)) and math.isfinite(v), owner, f.name, "a finite number", v)
        positive = ("gyro_noise", "bias_init_std", "gravity", "acc_noise", "acc_stat_tau_s",
                    "acc_reject_m_s2", "mag_noise", "mag_norm_tol", "mag_dip_tol", "mag_ref_tau_s",
                    "mag_relearn_s", "mag_relearn_first_s", "mag_ref_confirm_s",
                    "mag_gate_nis", "rest_gyro", "rest_acc_m_s2", "rest_gyro_noise",
                    "max_dt_s")
        for name in positive:
            v = getattr(self, name)
            require(v > 0, owner, name, "> 0", v)
        for name in ("bias_walk", "gyro_scale_error", "rest_min_s", "acc_lp_tau_s", "mag_rate_noise_s",
                     "mag_heading_sys_std",
                     "mag_anomaly_tau_s",
                     "acc_adapt_gain"):
            v = getattr(self, name)
            require(v >= 0, owner, name, ">= 0", v)
        require(abs(self.mag_declination) <= math.pi, owner, "mag_declination", "within [-π, π]",
                self.mag_declination)


@dataclass
class AekfState:
    """Everything :class:`Aekf` needs to resume (plain floats/lists; copy-safe via ``state()``).

    ``q`` (w, x, y, z) device→ENU; ``bias`` rad/s; ``P`` 6×6 row-major error covariance
    ([δθ_enu rad, δb rad/s]); the remaining fields are the adaptation memories."""

    initialised: bool = False
    stamp_ns: int = 0
    q: list[float] = dataclasses.field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])
    bias: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    P: list[float] = dataclasses.field(default_factory=lambda: [0.0] * 36)
    acc_mean: float = 0.0            # running mean of |a|, m/s²
    acc_var: float = 0.0             # running variance of |a|, (m/s²)²
    gyro_lp: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    acc_lp: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    enu_lp: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])       # m/s², ENU
    enu_lp_rate: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])  # m/s³, ENU
    rest_s: float = 0.0              # how long the device has been still, s
    mag_ref_ok: bool = False
    mag_norm_ref: float = 0.0        # reference field norm (input unit)
    mag_dip_ref: float = 0.0         # reference dip angle, rad (positive = field points up)
    mag_dist_s: float = 0.0          # how long the field has been disturbed, s
    mag_ok_s: float = 0.0            # how long the field has agreed with the reference, s
    mag_stamp_ns: int = 0            # stamp of the previous magnetometer sample used
    mag_norm_anomaly: float = 0.0    # smoothed ‖m‖/ref − 1
    mag_dip_anomaly: float = 0.0     # smoothed dip − ref, rad
    n_acc_skipped: int = 0
    n_mag_skipped: int = 0
    att_stamp_ns: int = 0            # time of the attitude (a magnetometer stamp after the last IMU one)
    imu_dt_s: float = 0.0            # the last IMU step, s
    gyro_last: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])  # rad/s, raw
    pending_mag: list[float] | None = None  # a magnetometer sample before initialisation

    def copy(self) -> "AekfState":
        return dataclasses.replace(self, q=list(self.q), bias=list(self.bias), P=list(self.P),
                                   gyro_lp=list(self.gyro_lp), acc_lp=list(self.acc_lp),
                                   enu_lp=list(self.enu_lp), enu_lp_rate=list(self.enu_lp_rate),
                                   gyro_last=list(self.gyro_last),
                                   pending_mag=None if self.pending_mag is None else list(self.pending_mag))


def _initialise(st: AekfState, c: "_Coef", a: list[float], m: Sequence[float] | None) -> None:
    """Tilt from the accelerometer (shortest arc a → e_z), heading from the magnetometer if any."""
    p = c.p
    ax, ay, az = a
    n = math.sqrt(ax * ax + ay * ay + az * az)
    if n < 1e-6:
        raise InvalidInputError("zero_acc", "cannot initialise the orientation from a zero accelerometer reading")
    ax, ay, az = ax / n, ay / n, az / n
    # shortest arc from (ax, ay, az) to (0, 0, 1): q = [1 + az, a × e_z] normalised
    w, x, y, z = 1.0 + az, ay, -ax, 0.0
    if w < 1e-9:  # upside down: 180° about x
        w, x, y, z = 0.0, 1.0, 0.0, 0.0
    qn = math.sqrt(w * w + x * x + y * y + z * z)
    q = [w / qn, x / qn, y / qn, z / qn]
    tilt_var = (p.acc_noise / p.gravity) ** 2
    yaw_var = math.pi ** 2 / 3.0  # uniform heading: unknown
    if m is not None:
        mx, my, mz = _rot(q, m)
        if math.hypot(mx, my) > 1e-9 * (abs(mz) + 1e-12):
            yaw = wrap_angle(math.atan2(mx, my) - p.mag_declination)  # field heading east of north
            # rotate about ENU z by +yaw so the field points north (+ declination)
            ch, sh = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
            q = [ch * q[0] - sh * q[3], ch * q[1] - sh * q[2], ch * q[2] + sh * q[1], ch * q[3] + sh * q[0]]
            yaw_var = p.mag_noise ** 2
            me = _rot(q, m)
            nm = math.sqrt(me[0] ** 2 + me[1] ** 2 + me[2] ** 2)
            st.mag_ref_ok = True
            st.mag_norm_ref = nm
            st.mag_dip_ref = math.asin(max(-1.0, min(1.0, me[2] / nm)))
    st.q = q
    st.bias = [0.0, 0.0, 0.0]
    P = [0.0] * 36
    P[0] = P[7] = tilt_var
    P[14] = yaw_var
    P[21] = P[28] = P[35] = p.bias_init_std ** 2
    st.P = P
    st.acc_mean = n
    st.acc_var = 0.0
    st.acc_lp = list(a)
    st.enu_lp = list(_rot(q, a))
    st.enu_lp_rate = [0.0, 0.0, 0.0]
    st.pending_mag = None
    st.initialised = True


def _rot(q: list[float], v: Sequence[float]) -> tuple[float, float, float]:
    w, x, y, z = q
    vx, vy, vz = v
    return ((1 - 2 * (y * y + z * z)) * vx + 2 * (x * y - w * z) * vy + 2 * (x * z + w * y) * vz,
            2 * (x * y + w * z) * vx + (1 - 2 * (x * x + z * z)) * vy + 2 * (y * z - w * x) * vz,
            2 * (x * z - w * y) * vx + 2 * (y * z + w * x) * vy + (1 - 2 * (x * x + y * y)) * vz)


class _Coef:
    """Constants derived once from :class:`AekfParams` (variances, gates, low-pass gains)."""

    __slots__ = ("p", "sg2", "ksf2", "sb2", "grav", "inv_g2", "sa2", "c_ad", "acc_rej2", "tau_a", "sm2", "k_mw2",
                 "sys2", "tau_an", "ntol", "dtol", "tau_m", "relearn", "relearn_first", "confirm", "gate",
                 "decl", "rest_g2", "rest_a2", "rest_min", "r_rest", "max_dt", "use_lp", "w_lp2", "d_lp")

    def __init__(self, p: AekfParams) -> None:
        self.p = p
        self.sg2 = p.gyro_noise ** 2
        self.ksf2 = p.gyro_scale_error ** 2
        self.sb2 = p.bias_walk ** 2
        self.grav = p.gravity
        self.inv_g2 = 1.0 / (p.gravity * p.gravity)
        self.sa2 = p.acc_noise ** 2
        self.c_ad = p.acc_adapt_gain
        self.acc_rej2 = p.acc_reject_m_s2 ** 2
        self.tau_a = p.acc_stat_tau_s
        self.sm2 = p.mag_noise ** 2
        self.k_mw2 = p.mag_rate_noise_s ** 2
        self.sys2 = p.mag_heading_sys_std ** 2
        self.tau_an = p.mag_anomaly_tau_s
        self.ntol = p.mag_norm_tol
        self.dtol = p.mag_dip_tol
        self.tau_m = p.mag_ref_tau_s
        self.relearn = p.mag_relearn_s
        self.relearn_first = p.mag_relearn_first_s
        self.confirm = p.mag_ref_confirm_s
        self.gate = p.mag_gate_nis
        self.decl = p.mag_declination
        self.rest_g2 = p.rest_gyro ** 2
        self.rest_a2 = p.rest_acc_m_s2 ** 2
        self.rest_min = p.rest_min_s
        self.r_rest = p.rest_gyro_noise ** 2
        self.max_dt = p.max_dt_s
        self.use_lp = p.acc_lp_tau_s > 0.0
        w_lp = math.sqrt(2.0) / p.acc_lp_tau_s if self.use_lp else 0.0  # Butterworth: ω = 2π f_c = √2/τ
        self.w_lp2, self.d_lp = w_lp * w_lp, math.sqrt(2.0) * w_lp       # ω², 2ζω with ζ = 1/√2


_sqrt, _sin, _cos = math.sqrt, math.sin, math.cos
Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]
Mat3 = tuple[float, float, float, float, float, float, float, float, float]


def _rotation(q: Quat) -> Mat3:
    """R(q) row-major, device → ENU."""
    qw, qx, qy, qz = q
    return (1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy),
            2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx),
            2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy))


def _predict(P: list[float], q: Quat, wx: float, wy: float, wz: float, dt: float, integrate: bool,
             qa: float, qb: float) -> tuple[Quat, Mat3]:
    """Gyroscope step (VQF's ``updateGyr``): ``q ← q ⊗ exp(ω dt)`` with the bias-corrected rate ω
    (skipped when ``integrate`` is false: a gap), ``P ← F P Fᵀ + diag(qa I, qb I)`` in place.
    Returns the new ``q`` and its rotation matrix."""
    qw, qx, qy, qz = q
    if integrate:
        ang = _sqrt(wx * wx + wy * wy + wz * wz) * dt
        if ang > 1e-12:
            h = 0.5 * ang
            s = _sin(h) * dt / ang
            dw, dx_, dy_, dz_ = _cos(h), wx * s, wy * s, wz * s
        else:
            dw, dx_, dy_, dz_ = 1.0, 0.5 * wx * dt, 0.5 * wy * dt, 0.5 * wz * dt
        qw, qx, qy, qz = (qw * dw - qx * dx_ - qy * dy_ - qz * dz_,
                          qw * dx_ + qx * dw + qy * dz_ - qz * dy_,
                          qw * dy_ - qx * dz_ + qy * dw + qz * dx_,
                          qw * dz_ + qx * dy_ - qy * dx_ + qz * dw)
        qn = 1.0 / _sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw * qn, qx * qn, qy * qn, qz * qn
    # R(q) as in _rotation, inline (once per sample)
    r00 = 1 - 2 * (qy * qy + qz * qz); r01 = 2 * (qx * qy - qw * qz); r02 = 2 * (qx * qz + qw * qy)
    r10 = 2 * (qx * qy + qw * qz); r11 = 1 - 2 * (qx * qx + qz * qz); r12 = 2 * (qy * qz - qw * qx)
    r20 = 2 * (qx * qz - qw * qy); r21 = 2 * (qy * qz + qw * qx); r22 = 1 - 2 * (qx * qx + qy * qy)
    # P ← F P Fᵀ + Q with F = [[I, M], [0, I]], M = −R dt
    m00, m01, m02 = -r00 * dt, -r01 * dt, -r02 * dt
    m10, m11, m12 = -r10 * dt, -r11 * dt, -r12 * dt
    m20, m21, m22 = -r20 * dt, -r21 * dt, -r22 * dt
    # unrolled; rows 0..2 += M · rows 3..5, then cols 0..2 += cols 3..5 · Mᵀ (P stays symmetric:
    # only the upper triangle of the angle block is computed, the lower-left block is mirrored)
    P[0] += m00 * P[18] + m01 * P[24] + m02 * P[30]
    P[1] += m00 * P[19] + m01 * P[25] + m02 * P[31]
    P[2] += m00 * P[20] + m01 * P[26] + m02 * P[32]
    P[3] += m00 * P[21] + m01 * P[27] + m02 * P[33]
    P[4] += m00 * P[22] + m01 * P[28] + m02 * P[34]
    P[5] += m00 * P[23] + m01 * P[29] + m02 * P[35]
    P[6] += m10 * P[18] + m11 * P[24] + m12 * P[30]
    P[7] += m10 * P[19] + m11 * P[25] + m12 * P[31]
    P[8] += m10 * P[20] + m11 * P[26] + m12 * P[32]
    P[9] += m10 * P[21] + m11 * P[27] + m12 * P[33]
    P[10] += m10 * P[22] + m11 * P[28] + m12 * P[34]
    P[11] += m10 * P[23] + m11 * P[29] + m12 * P[35]
    P[12] += m20 * P[18] + m21 * P[24] + m22 * P[30]
    P[13] += m20 * P[19] + m21 * P[25] + m22 * P[31]
    P[14] += m20 * P[20] + m21 * P[26] + m22 * P[32]
    P[15] += m20 * P[21] + m21 * P[27] + m22 * P[33]
    P[16] += m20 * P[22] + m21 * P[28] + m22 * P[34]
    P[17] += m20 * P[23] + m21 * P[29] + m22 * P[35]
    P[0] += P[3] * m00 + P[4] * m01 + P[5] * m02
    P[1] = P[6] = P[1] + P[3] * m10 + P[4] * m11 + P[5] * m12
    P[2] = P[12] = P[2] + P[3] * m20 + P[4] * m21 + P[5] * m22
    P[7] += P[9] * m10 + P[10] * m11 + P[11] * m12
    P[8] = P[13] = P[8] + P[9] * m20 + P[10] * m21 + P[11] * m22
    P[14] += P[15] * m20 + P[16] * m21 + P[17] * m22
    P[18], P[19], P[20], P[24], P[25] = P[3], P[9], P[15], P[4], P[10]
    P[26], P[30], P[31], P[32] = P[16], P[5], P[11], P[17]
    P[0] += qa; P[7] += qa; P[14] += qa
    P[21] += qb; P[28] += qb; P[35] += qb
    return (qw, qx, qy, qz), (r00, r01, r02, r10, r11, r12, r20, r21, r22)


def _correct(q: Quat, b: Vec3, y: Vec3, v: Vec3, dx: tuple[float, ...]) -> tuple[Quat, Vec3, Vec3, Vec3]:
    """Apply an error-state correction: ``q ← exp(δθ) ⊗ q`` (first order, normalised), ``b += δb``;
    the buffered ENU vectors (low-passed specific force ``y`` and its rate ``v``) follow the corrected
    frame, ``y ← exp(δθ) y``. ``dx`` = (δθ_enu, δb)."""
    ex, ey, ez, dbx, dby, dbz = dx
    qw, qx, qy, qz = q
    hx, hy, hz = 0.5 * ex, 0.5 * ey, 0.5 * ez
    qw, qx, qy, qz = (qw - hx * qx - hy * qy - hz * qz,
                      qx + hx * qw + hy * qz - hz * qy,
                      qy - hx * qz + hy * qw + hz * qx,
                      qz + hx * qy - hy * qx + hz * qw)
    qn = 1.0 / _sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    ylx, yly, ylz = y
    vlx, vly, vlz = v
    return ((qw * qn, qx * qn, qy * qn, qz * qn), (b[0] + dbx, b[1] + dby, b[2] + dbz),
            (ylx + ey * ylz - ez * yly, yly + ez * ylx - ex * ylz, ylz + ex * yly - ey * ylx),
            (vlx + ey * vlz - ez * vly, vly + ez * vlx - ex * vlz, vlz + ex * vly - ey * vlx))


def _update_acc(P: list[float], c: _Coef, R: Mat3, y: Vec3, v: Vec3, ax: float, ay: float, az: float,
                an: float, acc_var: float, dt: float) -> tuple[Vec3, Vec3, tuple[float, ...] | None]:
    """Accelerometer step (VQF's ``updateAcc``): the specific force is rotated to ENU and low-passed
    there (linear accelerations average out, gravity stays); its direction measures the tilt error
    ``(δθx, δθy)`` with the motion-adaptive noise. Updates ``P`` in place; returns the new low-pass
    state ``(y, v)`` and the correction ``δx`` (6), or None when the update is skipped."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
    uex = r00 * ax + r01 * ay + r02 * az
    uey = r10 * ax + r11 * ay + r12 * az
    uez = r20 * ax + r21 * ay + r22 * az
    if c.use_lp:
        ylx, yly, ylz = y
        vlx, vly, vlz = v
        hdt = dt if dt < c.max_dt else c.max_dt
        w_lp2, d_lp = c.w_lp2, c.d_lp
        vlx += hdt * (w_lp2 * (uex - ylx) - d_lp * vlx); ylx += hdt * vlx
        vly += hdt * (w_lp2 * (uey - yly) - d_lp * vly); yly += hdt * vly
        vlz += hdt * (w_lp2 * (uez - ylz) - d_lp * vlz); ylz += hdt * vlz
        y, v = (ylx, yly, ylz), (vlx, vly, vlz)
    else:
        ylx, yly, ylz = y = (uex, uey, uez)
    yn = _sqrt(ylx * ylx + yly * yly + ylz * ylz)
    dev = an - c.grav
    dlp = yn - c.grav
    rej2 = c.acc_rej2
    if not (yn > 1e-6 and dlp * dlp <= rej2 and (c.use_lp or (dev * dev <= rej2 and acc_var <= rej2))):
        return y, v, None
    ra = (c.sa2 + c.c_ad * (dev * dev + acc_var)) * c.inv_g2
    inv_yn = 1.0 / yn
    z0, z1 = yly * inv_yn, -ylx * inv_yn    # measures (δθx, δθy)
    s00, s01, s11 = P[0] + ra, P[1], P[7] + ra
    det = s00 * s11 - s01 * s01
    i00, i01, i11 = s11 / det, -s01 / det, s00 / det
    # unrolled: U = P Hᵀ (columns 0, 1), V = U S⁻¹, P ← P − V Uᵀ (upper triangle, mirrored)
    u00, u01, u02, u03, u04, u05 = P[0], P[6], P[12], P[18], P[24], P[30]
    u10, u11, u12, u13, u14, u15 = P[1], P[7], P[13], P[19], P[25], P[31]
    v00 = u00 * i00 + u10 * i01; v10 = u00 * i01 + u10 * i11
    v01 = u01 * i00 + u11 * i01; v11 = u01 * i01 + u11 * i11
    v02 = u02 * i00 + u12 * i01; v12 = u02 * i01 + u12 * i11
    v03 = u03 * i00 + u13 * i01; v13 = u03 * i01 + u13 * i11
    v04 = u04 * i00 + u14 * i01; v14 = u04 * i01 + u14 * i11
    v05 = u05 * i00 + u15 * i01; v15 = u05 * i01 + u15 * i11
    P[0] -= v00 * u00 + v10 * u10
    P[1] = P[6] = P[1] - (v00 * u01 + v10 * u11)
    P[2] = P[12] = P[2] - (v00 * u02 + v10 * u12)
    P[3] = P[18] = P[3] - (v00 * u03 + v10 * u13)
    P[4] = P[24] = P[4] - (v00 * u04 + v10 * u14)
    P[5] = P[30] = P[5] - (v00 * u05 + v10 * u15)
    P[7] -= v01 * u01 + v11 * u11
    P[8] = P[13] = P[8] - (v01 * u02 + v11 * u12)
    P[9] = P[19] = P[9] - (v01 * u03 + v11 * u13)
    P[10] = P[25] = P[10] - (v01 * u04 + v11 * u14)
    P[11] = P[31] = P[11] - (v01 * u05 + v11 * u15)
    P[14] -= v02 * u02 + v12 * u12
    P[15] = P[20] = P[15] - (v02 * u03 + v12 * u13)
    P[16] = P[26] = P[16] - (v02 * u04 + v12 * u14)
    P[17] = P[32] = P[17] - (v02 * u05 + v12 * u15)
    P[21] -= v03 * u03 + v13 * u13
    P[22] = P[27] = P[22] - (v03 * u04 + v13 * u14)
    P[23] = P[33] = P[23] - (v03 * u05 + v13 * u15)
    P[28] -= v04 * u04 + v14 * u14
    P[29] = P[34] = P[29] - (v04 * u05 + v14 * u15)
    P[35] -= v05 * u05 + v15 * u15
    return y, v, (v00 * z0 + v10 * z1, v01 * z0 + v11 * z1, v02 * z0 + v12 * z1,
                  v03 * z0 + v13 * z1, v04 * z0 + v14 * z1, v05 * z0 + v15 * z1)


def _update_rest(P: list[float], r_rest: float, wx: float, wy: float, wz: float) -> tuple[float, ...]:
    """Zero-rate update at rest: the measured rate minus the bias, ``ω_m − b``, measures ``δb``
    (noise ``r_rest`` rad²/s²). Updates ``P`` in place; returns the correction ``δx`` (6)."""
    c00 = P[21] + r_rest; c01 = P[22]; c02 = P[23]
    c11 = P[28] + r_rest; c12 = P[29]; c22 = P[35] + r_rest
    k00 = c11 * c22 - c12 * c12; k01 = c02 * c12 - c01 * c22; k02 = c01 * c12 - c02 * c11
    k11 = c00 * c22 - c02 * c02; k12 = c01 * c02 - c00 * c12; k22 = c00 * c11 - c01 * c01
    det = c00 * k00 + c01 * k01 + c02 * k02
    k00 /= det; k01 /= det; k02 /= det; k11 /= det; k12 /= det; k22 /= det
    # U = P Hᵀ (columns 3..5), V = U S⁻¹, P ← P − V Uᵀ: the lower triangle from rows of U and V
    U = [(P[i * 6 + 3], P[i * 6 + 4], P[i * 6 + 5]) for i in range(6)]
    V = [(u0 * k00 + u1 * k01 + u2 * k02, u0 * k01 + u1 * k11 + u2 * k12, u0 * k02 + u1 * k12 + u2 * k22)
         for u0, u1, u2 in U]
    for i in range(6):
        va, vb, vc = V[i]
        for j in range(i, 6):
            uj = U[j]
            P[i * 6 + j] = P[j * 6 + i] = P[i * 6 + j] - (va * uj[0] + vb * uj[1] + vc * uj[2])
    return tuple(va * wx + vb * wy + vc * wz for va, vb, vc in V)


def _update_mag(st: AekfState, c: _Coef, P: list[float], q: Quat, m: Sequence[float], tk: int, dt: float,
                wn2: float) -> tuple[float, ...] | None:
    """Magnetometer step (VQF's ``updateMag``), heading only, at stamp ``tk``: the field's norm and
    dip are checked against the online reference (smoothed anomalies, relearning of a lasting
    change), then the heading of its horizontal projection updates ``δθz`` and the bias with no gain
    on the tilt (Joseph form). Updates ``P`` and the reference memories of ``st`` in place; returns the
    correction ``δx`` (6) or None when the sample is not used. ``dt`` is the IMU step (for the
    first sample) and ``wn2`` the squared rotation rate (timing-mismatch noise)."""
    mx, my, mz = m
    mn = math.sqrt(mx * mx + my * my + mz * mz)
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation(q)
    mex = r00 * mx + r01 * my + r02 * mz
    mey = r10 * mx + r11 * my + r12 * mz
    mez = r20 * mx + r21 * my + r22 * mz
    if not (mn > 0.0 and math.sqrt(mex * mex + mey * mey) > 1e-3 * mn):
        return None
    dip = math.asin(max(-1.0, min(1.0, mez / mn)))
    if not st.mag_ref_ok:
        st.mag_ref_ok = True
        st.mag_norm_ref, st.mag_dip_ref = mn, dip
    # the magnetometer's own clock: its timers and low-passes advance by the time since the
    # previous magnetometer sample, not by the IMU's dt (a 50 Hz magnetometer beside a
    # 200 Hz gyroscope would otherwise age 4x too slowly)
    dtm = (tk - st.mag_stamp_ns) * 1e-9 if st.mag_stamp_ns else dt
    dtm = min(dtm, c.max_dt)
    st.mag_stamp_ns = tk
    # anomalies, smoothed over mag_anomaly_tau_s (sensor noise alone should not trip them)
    gam = dtm / (c.tau_an + dtm) if dtm > 0.0 else float(c.tau_an == 0.0)   # dtm 0: right after start-up
    st.mag_norm_anomaly += gam * (mn / st.mag_norm_ref - 1.0 - st.mag_norm_anomaly)
    st.mag_dip_anomaly += gam * (dip - st.mag_dip_ref - st.mag_dip_anomaly)
    rn, rd = st.mag_norm_anomaly / c.ntol, st.mag_dip_anomaly / c.dtol
    anomaly = rn * rn + rd * rd
    if rn * rn <= 1.0 and rd * rd <= 1.0:
        beta = dtm / (c.tau_m + dtm)
        st.mag_dip_ref += beta * (dip - st.mag_dip_ref)
        st.mag_norm_ref += beta * (mn - st.mag_norm_ref)
        st.mag_dist_s = 0.0
        st.mag_ok_s += dtm
    else:
        st.mag_dist_s += dtm
        # persistent: a new environment, not a disturbance. The first reference comes from
        # one sample at start-up, dipped through a tilt that may be wrong while moving:
        # until the field has agreed with it for mag_ref_confirm_s, relearn after the shorter
        # mag_relearn_first_s
        if st.mag_dist_s > (c.relearn if st.mag_ok_s >= c.confirm else c.relearn_first):
            st.mag_norm_ref, st.mag_dip_ref = mn, dip
            st.mag_dist_s = 0.0
            st.mag_norm_anomaly = st.mag_dip_anomaly = 0.0
        return None
    rm = c.sm2 * (1.0 + 4.0 * anomaly) + c.k_mw2 * wn2
    zy = (math.atan2(mex, mey) - c.decl + math.pi) % (2.0 * math.pi) - math.pi
    s = P[14] + rm
    nis = zy * zy / s
    if nis > c.gate:
        rm += s * (nis / c.gate - 1.0)
        s = P[14] + rm
    # gain only on heading and bias (no tilt gain): k0 = k1 = 0
    p20, p21, p22, p23, p24, p25 = P[12], P[13], P[14], P[15], P[16], P[17]
    is_ = 1.0 / s
    k2, k3, k4, k5 = p22 * is_, p23 * is_, p24 * is_, p25 * is_
    # Joseph form P − K p2ᵀ − p2 Kᵀ + (P22 + R) K Kᵀ (valid for any gain), unrolled
    P[2] = P[12] = P[2] - (p20 * k2)
    P[3] = P[18] = P[3] - (p20 * k3)
    P[4] = P[24] = P[4] - (p20 * k4)
    P[5] = P[30] = P[5] - (p20 * k5)
    P[8] = P[13] = P[8] - (p21 * k2)
    P[9] = P[19] = P[9] - (p21 * k3)
    P[10] = P[25] = P[10] - (p21 * k4)
    P[11] = P[31] = P[11] - (p21 * k5)
    P[14] -= k2 * p22 + p22 * k2 - s * k2 * k2
    P[15] = P[20] = P[15] - (k2 * p23 + p22 * k3 - s * k2 * k3)
    P[16] = P[26] = P[16] - (k2 * p24 + p22 * k4 - s * k2 * k4)
    P[17] = P[32] = P[17] - (k2 * p25 + p22 * k5 - s * k2 * k5)
    P[21] -= k3 * p23 + p23 * k3 - s * k3 * k3
    P[22] = P[27] = P[22] - (k3 * p24 + p23 * k4 - s * k3 * k4)
    P[23] = P[33] = P[23] - (k3 * p25 + p23 * k5 - s * k3 * k5)
    P[28] -= k4 * p24 + p24 * k4 - s * k4 * k4
    P[29] = P[34] = P[29] - (k4 * p25 + p24 * k5 - s * k4 * k5)
    P[35] -= k5 * p25 + p25 * k5 - s * k5 * k5
    return 0.0, 0.0, k2 * zy, k3 * zy, k4 * zy, k5 * zy


def _out_cov(P: list[float], st: AekfState, c: _Coef) -> tuple[float, ...]:
    return (P[0], P[1], P[2], P[6], P[7], P[8], P[12], P[13], P[14] + (c.sys2 if st.mag_ref_ok else 0.0))


def _check(tk: int, v: Sequence[float], what: str) -> None:
    if not (math.isfinite(v[0]) and math.isfinite(v[1]) and math.isfinite(v[2])):
        raise InvalidInputError("nan", f"non-finite {what} sample at stamp {tk} ns")


def _run(st: AekfState, c: _Coef, t: list[int], g: list[list[float]], a: list[list[float]],
         m: Sequence[Sequence[float] | None] | None, out_q: list[Sequence[float]] | None,
         out_cov: list[Sequence[float]] | None) -> None:
    """Process IMU samples ``t[k]`` (int ns), ``g[k]``, ``a[k]`` and magnetometer samples ``m[k]`` at
    the same stamps (lists of 3 floats; ``m`` None or an entry None for none) in place on ``st``:
    per sample the gyroscope, accelerometer, rest and magnetometer steps. Appends (w,x,y,z) to
    ``out_q`` and the 9 entries of P[0:3,0:3] to ``out_cov`` per sample when given."""
    sqrt, isfinite = math.sqrt, math.isfinite
    max_dt, tau_a, rest_g2, rest_a2, rest_min = c.max_dt, c.tau_a, c.rest_g2, c.rest_a2, c.rest_min
    q: Quat = tuple(st.q)  # type: ignore[assignment]
    b: Vec3 = tuple(st.bias)  # type: ignore[assignment]
    P = list(st.P)
    acc_mean, acc_var = st.acc_mean, st.acc_var
    glx, gly, glz = st.gyro_lp
    alx, aly, alz = st.acc_lp
    y: Vec3 = tuple(st.enu_lp)  # type: ignore[assignment]
    v: Vec3 = tuple(st.enu_lp_rate)  # type: ignore[assignment]
    rest_s = st.rest_s
    t_prev, t_att = st.stamp_ns, st.att_stamp_ns
    n_acc_skip, n_mag_skip = st.n_acc_skipped, st.n_mag_skipped
    dt = st.imu_dt_s
    for k in range(len(t)):
        tk = t[k]
        gx, gy, gz = g[k]
        ax, ay, az = a[k]
        mk = None if m is None else m[k]
        if not (isfinite(gx) and isfinite(gy) and isfinite(gz) and isfinite(ax) and isfinite(ay)
                and isfinite(az)):
            raise InvalidInputError("nan", f"non-finite gyroscope/accelerometer sample at stamp {tk} ns")
        if mk is not None:
            _check(tk, mk, "magnetometer")
        if not st.initialised:
            _initialise(st, c, [ax, ay, az], mk if mk is not None else st.pending_mag)
            q = tuple(st.q)  # type: ignore[assignment]
            b = tuple(st.bias)  # type: ignore[assignment]
            P = list(st.P)
            acc_mean, acc_var = st.acc_mean, st.acc_var
            alx, aly, alz = st.acc_lp
            y, v = tuple(st.enu_lp), tuple(st.enu_lp_rate)  # type: ignore[assignment]
            glx, gly, glz = gx, gy, gz
            t_prev = t_att = tk
            if out_q is not None:
                out_q.append(q)
            if out_cov is not None:
                out_cov.append(_out_cov(P, st, c))
            continue
        if tk <= t_prev:
            raise InvalidInputError("non_monotonic_stamp", f"stamps must increase: {tk} ns after {t_prev} ns")
        dt = (tk - t_prev) * 1e-9
        # a magnetometer sample at its own stamp may have advanced the attitude part-way already
        dt_att = (tk - t_att) * 1e-9
        t_prev = t_att = tk

        # ---------------- gyroscope ----------------
        wx, wy, wz = gx - b[0], gy - b[1], gz - b[2]
        wn2 = wx * wx + wy * wy + wz * wz
        q, R = _predict(P, q, wx, wy, wz, dt_att, dt <= max_dt, (c.sg2 + c.ksf2 * wn2) * dt_att,
                        c.sb2 * dt_att)

        # ---------------- motion statistics, rest detection ----------------
        an = sqrt(ax * ax + ay * ay + az * az)
        alpha = dt / (tau_a + dt)
        d = an - acc_mean
        acc_mean += alpha * d
        acc_var += alpha * (d * d - acc_var)
        glx += alpha * (gx - glx); gly += alpha * (gy - gly); glz += alpha * (gz - glz)
        alx += alpha * (ax - alx); aly += alpha * (ay - aly); alz += alpha * (az - alz)
        still = wn2 < rest_g2
        if still:
            ex_, ey_, ez_ = gx - glx, gy - gly, gz - glz
            still = ex_ * ex_ + ey_ * ey_ + ez_ * ez_ < rest_g2
            if still:
                ex_, ey_, ez_ = ax - alx, ay - aly, az - alz
                still = ex_ * ex_ + ey_ * ey_ + ez_ * ez_ < rest_a2
        rest_s = rest_s + dt if still else 0.0

        # ---------------- accelerometer: tilt ----------------
        y, v, dx = _update_acc(P, c, R, y, v, ax, ay, az, an, acc_var, dt)
        if dx is None:
            n_acc_skip += 1
        else:
            q, b, y, v = _correct(q, b, y, v, dx)

        # ---------------- rest: zero-rate bias update ----------------
        if rest_s >= rest_min and rest_s > 0.0:
            q, b, y, v = _correct(q, b, y, v, _update_rest(P, c.r_rest, wx, wy, wz))

        # ---------------- magnetometer: heading ----------------
        if mk is not None:
            dx = _update_mag(st, c, P, q, mk, tk, dt, wn2)
            if dx is None:
                n_mag_skip += 1
            else:
                q, b, y, v = _correct(q, b, y, v, dx)

        if out_q is not None:
            out_q.append(q)
        if out_cov is not None:
            out_cov.append(_out_cov(P, st, c))
    # ---- locals back into the state ----
    st.q = list(q)
    st.bias = list(b)
    st.P = P
    st.acc_mean, st.acc_var = acc_mean, acc_var
    st.gyro_lp = [glx, gly, glz]
    st.acc_lp = [alx, aly, alz]
    st.enu_lp = list(y)
    st.enu_lp_rate = list(v)
    st.rest_s = rest_s
    st.stamp_ns, st.att_stamp_ns = t_prev, t_att
    st.n_acc_skipped, st.n_mag_skipped = n_acc_skip, n_mag_skip
    st.imu_dt_s = dt
    if t and st.initialised:
        st.gyro_last = list(g[-1])


def _update_mag_at_stamp(st: AekfState, c: _Coef, tm: int, m: list[float]) -> None:
    """A magnetometer sample at its own stamp ``tm``: the attitude is propagated from the last IMU
    stamp to ``tm`` with the last gyroscope sample (zero-order hold), the magnetometer step runs
    there, and the next IMU sample continues from ``tm``. Before the first IMU sample it is kept for
    the initial heading. Raises InvalidInputError for a non-finite sample or a stamp before the
    filter's time (the state is then unchanged)."""
    _check(tm, m, "magnetometer")
    if not st.initialised:
        st.pending_mag = list(m)
        return
    if tm < st.att_stamp_ns:
        raise InvalidInputError("non_monotonic_stamp",
                                f"magnetometer stamp {tm} ns is before the filter's time {st.att_stamp_ns} ns")
    P = list(st.P)
    q: Quat = tuple(st.q)  # type: ignore[assignment]
    b: Vec3 = tuple(st.bias)  # type: ignore[assignment]
    wx, wy, wz = st.gyro_last[0] - b[0], st.gyro_last[1] - b[1], st.gyro_last[2] - b[2]
    wn2 = wx * wx + wy * wy + wz * wz
    dt = (tm - st.att_stamp_ns) * 1e-9
    if dt > 0.0:
        q, _ = _predict(P, q, wx, wy, wz, dt, (tm - st.stamp_ns) * 1e-9 <= c.max_dt,
                        (c.sg2 + c.ksf2 * wn2) * dt, c.sb2 * dt)
        st.att_stamp_ns = tm
    dx = _update_mag(st, c, P, q, m, tm, st.imu_dt_s, wn2)
    if dx is None:
        st.n_mag_skipped += 1
    else:
        q, b, y, v = _correct(q, b, tuple(st.enu_lp), tuple(st.enu_lp_rate), dx)  # type: ignore[arg-type]
        st.enu_lp, st.enu_lp_rate = list(y), list(v)
    st.q, st.bias, st.P = list(q), list(b), P


class Aekf:
    """Online adaptive EKF. ``update()`` one sample at a time; ``state()``/``set_state()`` to save
    and resume (100 + 100 samples == 200 samples)."""

    def __init__(self, params: AekfParams | None = None) -> None:
        self.params = params if params is not None else AekfParams()
        self.params.validate()
        self._c = _Coef(self.params)
        self._st = AekfState()

    def update(self, stamp_ns: int, gyro: Sequence[float] | np.ndarray, acc: Sequence[float] | np.ndarray,
               mag: Sequence[float] | np.ndarray | None = None) -> None:
        """One sample: ``gyro`` (3,) rad/s, ``acc`` (3,) m/s² (specific force, +g up at rest),
        ``mag`` (3,) any unit or None. dt comes from the stamps (irregular is fine); the first call
        initialises from acc [+ mag]. Raises InvalidInputError (a ValueError) on non-finite input or
        stamps that do not increase (the state is then unchanged)."""
        g = [float(v) for v in gyro]
        a = [float(v) for v in acc]
        mm = None if mag is None else [[float(v) for v in mag]]
        if len(g) != 3 or len(a) != 3 or (mm is not None and len(mm[0]) != 3):
            raise InvalidInputError("shape", "gyro, acc and mag must have 3 components")
        # _run checks a sample before touching the state, so a rejected sample leaves it unchanged
        _run(self._st, self._c, [int(stamp_ns)], [g], [a], mm, None, None)

    def update_imu(self, stamp_ns: int, gyro: Sequence[float] | np.ndarray, acc: Sequence[float] | np.ndarray) -> None:
        """One IMU sample (gyroscope, accelerometer and rest steps); magnetometer samples come
        separately through :meth:`update_mag`."""
        self.update(stamp_ns, gyro, acc, None)

    def update_imu_run(self, stamps_ns: list[int], gyro: np.ndarray, acc: np.ndarray
                       ) -> tuple[list[Sequence[float]], list[Sequence[float]]]:
        """:meth:`update_imu` for each of a run of samples at once: the same steps (:func:`_run`) on
        the same floats, so the state is that of the sample-by-sample calls. ``gyro``, ``acc`` (N, 3).
        Returns per sample the quaternion (w, x, y, z) and the 9 entries of :attr:`orientation_cov`
        (row-major) after it. Raises InvalidInputError as :meth:`update_imu` would for the first bad
        sample, the state then unchanged (the caller checks a run first and takes none of it)."""
        out_q: list[Sequence[float]] = []
        out_c: list[Sequence[float]] = []
        _run(self._st, self._c, list(stamps_ns), np.asarray(gyro, dtype=float).tolist(),
             np.asarray(acc, dtype=float).tolist(), None, out_q, out_c)
        return out_q, out_c

    def update_mag(self, stamp_ns: int, mag: Sequence[float] | np.ndarray) -> None:
        """One magnetometer sample at its own stamp, applied there: the attitude is propagated to
        ``stamp_ns`` with the last gyroscope sample, updated, and the next IMU sample continues from
        it. Samples must come in stamp order with the IMU samples (``stamp_ns`` not before the last
        IMU stamp; :class:`indoor_loc.imu.mag_sync.MagSync` merges the two streams so)."""
        m = [float(v) for v in mag]
        if len(m) != 3:
            raise InvalidInputError("shape", f"malformed magnetometer sample at stamp {stamp_ns} ns")
        _update_mag_at_stamp(self._st, self._c, int(stamp_ns), m)

    @property
    def initialised(self) -> bool:
        return self._st.initialised

    @property
    def quat_wxyz(self) -> np.ndarray:
        """Unit quaternion (w, x, y, z), device→ENU, shape (4,)."""
        return np.array(self._st.q)

    @property
    def orientation_cov(self) -> np.ndarray:
        """(3, 3) rad²: covariance of the rotation error about ENU x, y, z (≈ roll, pitch, yaw for a
        near-level device; [2, 2] is the heading variance, which grows without a magnetometer and
        includes ``mag_heading_sys_std²`` with one)."""
        cov = np.array(self._st.P).reshape(6, 6)[:3, :3].copy()
        if self._st.mag_ref_ok:
            cov[2, 2] += self.params.mag_heading_sys_std ** 2
        return cov

    @property
    def covariance(self) -> np.ndarray:
        """Full (6, 6) error covariance [δθ_enu rad, δb rad/s]."""
        return np.array(self._st.P).reshape(6, 6)

    @property
    def gyro_bias(self) -> np.ndarray:
        """Estimated gyroscope bias, rad/s, device frame, shape (3,)."""
        return np.array(self._st.bias)

    @property
    def heading(self) -> float:
        """Yaw (rad, counter-clockwise from east) of the device x axis."""
        qw, qx, qy, qz = self._st.q
        return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))

    def state(self) -> AekfState:
        return self._st.copy()

    def set_state(self, state: AekfState) -> None:
        self._st = state.copy()


def aekf_batch(t_ns: ArrayLike, gyro: ArrayLike, acc: ArrayLike, mag: ArrayLike | None = None,
               params: AekfParams | None = None, state: AekfState | None = None,
               mag_t_ns: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Run the filter over whole arrays: ``t_ns`` (N,) int ns, ``gyro`` (N, 3) rad/s, ``acc`` (N, 3)
    m/s², ``mag`` (N, 3) at the IMU stamps or None (rows of NaN = no magnetometer sample) — or, with
    ``mag_t_ns`` (M,) given, ``mag`` (M, 3) at its own stamps, merged in stamp order as
    :func:`indoor_loc.imu.mag_sync.merge_events` does (the same result as :class:`Aekf` fed in that
    order). Returns ``quat`` (N, 4) w x y z device→ENU and ``cov`` (N, 3, 3) rad² after each IMU
    sample (see :attr:`Aekf.orientation_cov`). ``state`` (optional) is resumed and advanced in place."""
    params = params if params is not None else AekfParams()
    params.validate()
    t = np.asarray(t_ns).astype(np.int64)
    g = np.asarray(gyro, dtype=float)
    a = np.asarray(acc, dtype=float)
    n = len(t)
    if g.shape != (n, 3) or a.shape != (n, 3):
        raise InvalidInputError("shape", f"expected gyro/acc of shape ({n}, 3), got {g.shape} and {a.shape}")
    st = state if state is not None else AekfState()
    out_q: list[Sequence[float]] = []
    out_c: list[Sequence[float]] = []
    c = _Coef(params)
    if mag_t_ns is not None:
        _batch_own_stamps(st, c, t, g, a, mag, mag_t_ns, out_q, out_c)
        return np.array(out_q).reshape(n, 4), np.array(out_c).reshape(n, 3, 3)
    mlist = None
    if mag is not None:
        mg = np.asarray(mag, dtype=float)
        if mg.shape != (n, 3):
            raise InvalidInputError("shape", f"expected mag of shape ({n}, 3), got {mg.shape}")
        ok = np.isfinite(mg).all(axis=1)
        mlist = mg.tolist()
        if not ok.all():
            for i in np.flatnonzero(~ok):
                mlist[i] = None
    _run(st, c, t.tolist(), g.tolist(), a.tolist(), mlist, out_q, out_c)
    return np.array(out_q).reshape(n, 4), np.array(out_c).reshape(n, 3, 3)


def _batch_own_stamps(st: AekfState, c: _Coef, t: np.ndarray, g: np.ndarray, a: np.ndarray, mag: ArrayLike | None,
                      mag_t_ns: ArrayLike, out_q: list[Sequence[float]], out_c: list[Sequence[float]]) -> None:
    """:func:`aekf_batch` with the magnetometer at its own stamps: runs of IMU samples between
    magnetometer samples go through :func:`_run` at once, each magnetometer sample at its stamp."""
    from indoor_loc.imu.mag_sync import IMU, merge_events

    mt = np.asarray(mag_t_ns).astype(np.int64)
    mg = np.asarray(mag if mag is not None else np.empty((0, 3)), dtype=float)
    if mg.shape != (len(mt), 3):
        raise InvalidInputError("shape", f"expected mag of shape ({len(mt)}, 3), got {mg.shape}")
    tl, gl, al, ml = t.tolist(), g.tolist(), a.tolist(), mg.tolist()
    start = 0                                   # first IMU sample not yet run
    for kind, i in merge_events(t, mt):
        if kind == IMU:
            continue
        end = int(np.searchsorted(t, mt[i], side="right"))   # the IMU samples up to its stamp go first
        if end > start:
            _run(st, c, tl[start:end], gl[start:end], al[start:end], None, out_q, out_c)
            start = end
        _update_mag_at_stamp(st, c, int(mt[i]), ml[i])
    if start < len(tl):
        _run(st, c, tl[start:], gl[start:], al[start:], None, out_q, out_c)
