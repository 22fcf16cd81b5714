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

Per-sample Python with plain floats (no 6×6 numpy temporaries): ``aekf_batch`` and
``Aekf.update`` run the very same loop (:func:`_run`), so online and batch agree to the last bit.
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
    acc_lp_tau_s: float = field(3.0, "time constant of the 2nd-order Butterworth low-pass applied to the "
                                     "accelerometer in the ENU frame before the tilt update (0 = raw), s")
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

    def copy(self) -> "AekfState":
        return dataclasses.replace(self, q=list(self.q), bias=list(self.bias), P=list(self.P),
                                   gyro_lp=list(self.gyro_lp), acc_lp=list(self.acc_lp),
                                   enu_lp=list(self.enu_lp), enu_lp_rate=list(self.enu_lp_rate))


def _initialise(st: AekfState, p: AekfParams, a: list[float], m: list[float] | None) -> None:
    """Tilt from the accelerometer (shortest arc a → e_z), heading from the magnetometer if any."""
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
            c, s = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
            q = [c * q[0] - s * q[3], c * q[1] - s * q[2], c * q[2] + s * q[1], c * q[3] + s * q[0]]
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
    st.initialised = True


def _rot(q: list[float], v: list[float]) -> tuple[float, float, float]:
    w, x, y, z = q
    vx, vy, vz = v
    return ((1 - 2 * (y * y + z * z)) * vx + 2 * (x * y - w * z) * vy + 2 * (x * z + w * y) * vz,
            2 * (x * y + w * z) * vx + (1 - 2 * (x * x + z * z)) * vy + 2 * (y * z - w * x) * vz,
            2 * (x * z - w * y) * vx + 2 * (y * z + w * x) * vy + (1 - 2 * (x * x + y * y)) * vz)


def _run(st: AekfState, p: AekfParams, t: list[int], g: list[list[float]], a: list[list[float]],
         m: list[list[float]] | None, out_q: list[Sequence[float]] | None,
         out_cov: list[Sequence[float]] | None) -> None:
    """Process samples ``t[k]`` (int ns), ``g[k]``, ``a[k]``, ``m[k]`` (lists of 3 floats; ``m`` None
    or an entry None for no magnetometer) in place on ``st``. Appends (w,x,y,z) to ``out_q`` and
    the 9 entries of P[0:3,0:3] to ``out_cov`` per sample when given."""
    # ---- coefficients (derived once per call) ----
    sg2 = p.gyro_noise ** 2
    ksf2 = p.gyro_scale_error ** 2
    sb2 = p.bias_walk ** 2
    grav = p.gravity
    inv_g2 = 1.0 / (grav * grav)
    sa2 = p.acc_noise ** 2
    c_ad = p.acc_adapt_gain
    acc_rej = p.acc_reject_m_s2
    acc_rej2 = acc_rej * acc_rej
    tau_a = p.acc_stat_tau_s
    sm2 = p.mag_noise ** 2
    k_mw2 = p.mag_rate_noise_s ** 2
    sys2 = p.mag_heading_sys_std ** 2
    tau_an = p.mag_anomaly_tau_s
    ntol = p.mag_norm_tol
    dtol = p.mag_dip_tol
    tau_m = p.mag_ref_tau_s
    relearn = p.mag_relearn_s
    relearn_first = p.mag_relearn_first_s
    confirm = p.mag_ref_confirm_s
    gate = p.mag_gate_nis
    decl = p.mag_declination
    rest_g2 = p.rest_gyro ** 2
    rest_a2 = p.rest_acc_m_s2 ** 2
    rest_min = p.rest_min_s
    r_rest = p.rest_gyro_noise ** 2
    max_dt = p.max_dt_s
    use_lp = p.acc_lp_tau_s > 0.0
    w_lp = math.sqrt(2.0) / p.acc_lp_tau_s if use_lp else 0.0  # Butterworth: ω = 2π f_c = √2/τ
    w_lp2, d_lp = w_lp * w_lp, math.sqrt(2.0) * w_lp            # ω², 2ζω with ζ = 1/√2
    isfinite = math.isfinite
    sqrt = math.sqrt
    # ---- state into locals ----
    qw, qx, qy, qz = st.q
    bx, by, bz = st.bias
    P = list(st.P)
    acc_mean, acc_var = st.acc_mean, st.acc_var
    glx, gly, glz = st.gyro_lp
    alx, aly, alz = st.acc_lp
    ylx, yly, ylz = st.enu_lp
    vlx, vly, vlz = st.enu_lp_rate
    rest_s = st.rest_s
    en_lp, ed_lp = st.mag_norm_anomaly, st.mag_dip_anomaly
    t_prev = st.stamp_ns
    n_acc_skip, n_mag_skip = st.n_acc_skipped, st.n_mag_skipped

    for k in range(len(t)):
        tk = t[k]
        gx, gy, gz = g[k]
        ax, ay, az = a[k]
        mk = None if m is None else m[k]
        if not (isfinite(gx) and isfinite(gy) and isfinite(gz) and isfinite(ax) and isfinite(ay)
                and isfinite(az)):
            raise InvalidInputError("nan", f"non-finite gyroscope/accelerometer sample at stamp {tk} ns")
        if mk is not None and not (isfinite(mk[0]) and isfinite(mk[1]) and isfinite(mk[2])):
            raise InvalidInputError("nan", f"non-finite magnetometer sample at stamp {tk} ns")
        if not st.initialised:
            _initialise(st, p, [ax, ay, az], mk)
            qw, qx, qy, qz = st.q
            bx, by, bz = st.bias
            P = list(st.P)
            acc_mean, acc_var = st.acc_mean, st.acc_var
            alx, aly, alz = st.acc_lp
            ylx, yly, ylz = st.enu_lp
            vlx, vly, vlz = st.enu_lp_rate
            glx, gly, glz = gx, gy, gz
            t_prev = tk
            if out_q is not None:
                out_q.append((qw, qx, qy, qz))
            if out_cov is not None:
                out_cov.append((P[0], P[1], P[2], P[6], P[7], P[8], P[12], P[13],
                            P[14] + (sys2 if st.mag_ref_ok else 0.0)))
            continue
        if tk <= t_prev:
            raise InvalidInputError("non_monotonic_stamp", f"stamps must increase: {tk} ns after {t_prev} ns")
        dt = (tk - t_prev) * 1e-9
        t_prev = tk

        # ---------------- prediction ----------------
        wx, wy, wz = gx - bx, gy - by, gz - bz
        wn2 = wx * wx + wy * wy + wz * wz
        if dt <= max_dt:
            ang = sqrt(wn2) * dt
            if ang > 1e-12:
                h = 0.5 * ang
                s = math.sin(h) * dt / ang
                dw, dx_, dy_, dz_ = math.cos(h), wx * s, wy * s, wz * s
            else:
                dw, dx_, dy_, dz_ = 1.0, 0.5 * wx * dt, 0.5 * wy * dt, 0.5 * wz * dt
            qw, qx, qy, qz = (qw * dw - qx * dx_ - qy * dy_ - qz * dz_,
                              qw * dx_ + qx * dw + qy * dz_ - qz * dy_,
                              qw * dy_ - qx * dz_ + qy * dw + qz * dx_,
                              qw * dz_ + qx * dy_ - qy * dx_ + qz * dw)
            qn = 1.0 / sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            qw, qx, qy, qz = qw * qn, qx * qn, qy * qn, qz * qn
        # rotation matrix R(q), device → ENU
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
        qa = (sg2 + ksf2 * wn2) * dt
        qb = sb2 * dt
        P[0] += qa; P[7] += qa; P[14] += qa
        P[21] += qb; P[28] += qb; P[35] += qb

        # ---------------- motion statistics ----------------
        an = sqrt(ax * ax + ay * ay + az * az)
        alpha = dt / (tau_a + dt)
        d = an - acc_mean
        acc_mean += alpha * d
        acc_var += alpha * (d * d - acc_var)
        # rest detection (low-passes with the same time constant)
        glx += alpha * (gx - glx); gly += alpha * (gy - gly); glz += alpha * (gz - glz)
        alx += alpha * (ax - alx); aly += alpha * (ay - aly); alz += alpha * (az - alz)
        still = (wn2 < rest_g2
                 and (gx - glx) ** 2 + (gy - gly) ** 2 + (gz - glz) ** 2 < rest_g2
                 and (ax - alx) ** 2 + (ay - aly) ** 2 + (az - alz) ** 2 < rest_a2)
        rest_s = rest_s + dt if still else 0.0

        # ---------------- accelerometer: tilt ----------------
        # specific force in ENU, low-passed there (linear accelerations average out, gravity stays)
        uex = r00 * ax + r01 * ay + r02 * az
        uey = r10 * ax + r11 * ay + r12 * az
        uez = r20 * ax + r21 * ay + r22 * az
        if use_lp:
            hdt = min(dt, max_dt)
            vlx += hdt * (w_lp2 * (uex - ylx) - d_lp * vlx); ylx += hdt * vlx
            vly += hdt * (w_lp2 * (uey - yly) - d_lp * vly); yly += hdt * vly
            vlz += hdt * (w_lp2 * (uez - ylz) - d_lp * vlz); ylz += hdt * vlz
        else:
            ylx, yly, ylz = uex, uey, uez
        yn = sqrt(ylx * ylx + yly * yly + ylz * ylz)
        dev = an - grav
        dlp = yn - grav
        if yn > 1e-6 and dlp * dlp <= acc_rej2 and (use_lp or (dev * dev <= acc_rej2 and acc_var <= acc_rej2)):
            ra = (sa2 + c_ad * (dev * dev + acc_var)) * inv_g2
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
            ex = v00 * z0 + v10 * z1
            ey = v01 * z0 + v11 * z1
            ez = v02 * z0 + v12 * z1
            bx += v03 * z0 + v13 * z1
            by += v04 * z0 + v14 * z1
            bz += v05 * z0 + v15 * z1
            # q ← exp(δθ) ⊗ q (first order, then normalise)
            hx, hy, hz = 0.5 * ex, 0.5 * ey, 0.5 * ez
            qw, qx, qy, qz = (qw - hx * qx - hy * qy - hz * qz,
                              qx + hx * qw + hy * qz - hz * qy,
                              qy - hx * qz + hy * qw + hz * qx,
                              qz + hx * qy - hy * qx + hz * qw)
            qn = 1.0 / sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            qw, qx, qy, qz = qw * qn, qx * qn, qy * qn, qz * qn
            # the buffered ENU vectors follow the corrected frame: y ← exp(δθ) y
            ylx, yly, ylz = (ylx + ey * ylz - ez * yly, yly + ez * ylx - ex * ylz, ylz + ex * yly - ey * ylx)
            vlx, vly, vlz = (vlx + ey * vlz - ez * vly, vly + ez * vlx - ex * vlz, vlz + ex * vly - ey * vlx)
        else:
            n_acc_skip += 1

        # ---------------- rest: zero-rate bias update ----------------
        if rest_s >= rest_min and rest_min >= 0.0 and rest_s > 0.0:
            c00 = P[21] + r_rest; c01 = P[22]; c02 = P[23]
            c11 = P[28] + r_rest; c12 = P[29]; c22 = P[35] + r_rest
            k00 = c11 * c22 - c12 * c12; k01 = c02 * c12 - c01 * c22; k02 = c01 * c12 - c02 * c11
            k11 = c00 * c22 - c02 * c02; k12 = c01 * c02 - c00 * c12; k22 = c00 * c11 - c01 * c01
            det = c00 * k00 + c01 * k01 + c02 * k02
            k00 /= det; k01 /= det; k02 /= det; k11 /= det; k12 /= det; k22 /= det
            z0, z1, z2 = wx, wy, wz                  # ω_m − b measures δb
            # unrolled: U = P Hᵀ (columns 3..5), V = U S⁻¹, P ← P − V Uᵀ (upper triangle, mirrored)
            u30, u40, u50 = P[3], P[4], P[5]
            u31, u41, u51 = P[9], P[10], P[11]
            u32, u42, u52 = P[15], P[16], P[17]
            u33, u43, u53 = P[21], P[22], P[23]
            u34, u44, u54 = P[27], P[28], P[29]
            u35, u45, u55 = P[33], P[34], P[35]
            va0 = u30 * k00 + u40 * k01 + u50 * k02
            vb0 = u30 * k01 + u40 * k11 + u50 * k12
            vc0 = u30 * k02 + u40 * k12 + u50 * k22
            va1 = u31 * k00 + u41 * k01 + u51 * k02
            vb1 = u31 * k01 + u41 * k11 + u51 * k12
            vc1 = u31 * k02 + u41 * k12 + u51 * k22
            va2 = u32 * k00 + u42 * k01 + u52 * k02
            vb2 = u32 * k01 + u42 * k11 + u52 * k12
            vc2 = u32 * k02 + u42 * k12 + u52 * k22
            va3 = u33 * k00 + u43 * k01 + u53 * k02
            vb3 = u33 * k01 + u43 * k11 + u53 * k12
            vc3 = u33 * k02 + u43 * k12 + u53 * k22
            va4 = u34 * k00 + u44 * k01 + u54 * k02
            vb4 = u34 * k01 + u44 * k11 + u54 * k12
            vc4 = u34 * k02 + u44 * k12 + u54 * k22
            va5 = u35 * k00 + u45 * k01 + u55 * k02
            vb5 = u35 * k01 + u45 * k11 + u55 * k12
            vc5 = u35 * k02 + u45 * k12 + u55 * k22
            P[0] -= va0 * u30 + vb0 * u40 + vc0 * u50
            P[1] = P[6] = P[1] - (va0 * u31 + vb0 * u41 + vc0 * u51)
            P[2] = P[12] = P[2] - (va0 * u32 + vb0 * u42 + vc0 * u52)
            P[3] = P[18] = P[3] - (va0 * u33 + vb0 * u43 + vc0 * u53)
            P[4] = P[24] = P[4] - (va0 * u34 + vb0 * u44 + vc0 * u54)
            P[5] = P[30] = P[5] - (va0 * u35 + vb0 * u45 + vc0 * u55)
            P[7] -= va1 * u31 + vb1 * u41 + vc1 * u51
            P[8] = P[13] = P[8] - (va1 * u32 + vb1 * u42 + vc1 * u52)
            P[9] = P[19] = P[9] - (va1 * u33 + vb1 * u43 + vc1 * u53)
            P[10] = P[25] = P[10] - (va1 * u34 + vb1 * u44 + vc1 * u54)
            P[11] = P[31] = P[11] - (va1 * u35 + vb1 * u45 + vc1 * u55)
            P[14] -= va2 * u32 + vb2 * u42 + vc2 * u52
            P[15] = P[20] = P[15] - (va2 * u33 + vb2 * u43 + vc2 * u53)
            P[16] = P[26] = P[16] - (va2 * u34 + vb2 * u44 + vc2 * u54)
            P[17] = P[32] = P[17] - (va2 * u35 + vb2 * u45 + vc2 * u55)
            P[21] -= va3 * u33 + vb3 * u43 + vc3 * u53
            P[22] = P[27] = P[22] - (va3 * u34 + vb3 * u44 + vc3 * u54)
            P[23] = P[33] = P[23] - (va3 * u35 + vb3 * u45 + vc3 * u55)
            P[28] -= va4 * u34 + vb4 * u44 + vc4 * u54
            P[29] = P[34] = P[29] - (va4 * u35 + vb4 * u45 + vc4 * u55)
            P[35] -= va5 * u35 + vb5 * u45 + vc5 * u55
            ex = va0 * z0 + vb0 * z1 + vc0 * z2
            ey = va1 * z0 + vb1 * z1 + vc1 * z2
            ez = va2 * z0 + vb2 * z1 + vc2 * z2
            bx += va3 * z0 + vb3 * z1 + vc3 * z2
            by += va4 * z0 + vb4 * z1 + vc4 * z2
            bz += va5 * z0 + vb5 * z1 + vc5 * z2
            hx, hy, hz = 0.5 * ex, 0.5 * ey, 0.5 * ez
            qw, qx, qy, qz = (qw - hx * qx - hy * qy - hz * qz,
                              qx + hx * qw + hy * qz - hz * qy,
                              qy - hx * qz + hy * qw + hz * qx,
                              qz + hx * qy - hy * qx + hz * qw)
            qn = 1.0 / sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            qw, qx, qy, qz = qw * qn, qx * qn, qy * qn, qz * qn
            # the buffered ENU vectors follow the corrected frame: y ← exp(δθ) y
            ylx, yly, ylz = (ylx + ey * ylz - ez * yly, yly + ez * ylx - ex * ylz, ylz + ex * yly - ey * ylx)
            vlx, vly, vlz = (vlx + ey * vlz - ez * vly, vly + ez * vlx - ex * vlz, vlz + ex * vly - ey * vlx)

        # ---------------- magnetometer: heading only ----------------
        if mk is not None:
            mx, my, mz = mk
            mn = sqrt(mx * mx + my * my + mz * mz)
            r00 = 1 - 2 * (qy * qy + qz * qz); r01 = 2 * (qx * qy - qw * qz); r02 = 2 * (qx * qz + qw * qy)
            r10 = 2 * (qx * qy + qw * qz); r11 = 1 - 2 * (qx * qx + qz * qz); r12 = 2 * (qy * qz - qw * qx)
            r20 = 2 * (qx * qz - qw * qy); r21 = 2 * (qy * qz + qw * qx); r22 = 1 - 2 * (qx * qx + qy * qy)
            mex = r00 * mx + r01 * my + r02 * mz
            mey = r10 * mx + r11 * my + r12 * mz
            mez = r20 * mx + r21 * my + r22 * mz
            mh = sqrt(mex * mex + mey * mey)
            use = mn > 0.0 and mh > 1e-3 * mn
            if use:
                dip = math.asin(max(-1.0, min(1.0, mez / mn)))
                if not st.mag_ref_ok:
                    st.mag_ref_ok = True
                    st.mag_norm_ref, st.mag_dip_ref = mn, dip
                # the magnetometer's own clock: its timers and low-passes advance by the time since the
                # previous magnetometer sample, not by the IMU's dt (a 50 Hz magnetometer beside a
                # 200 Hz gyroscope would otherwise age 4x too slowly)
                dtm = (tk - st.mag_stamp_ns) * 1e-9 if st.mag_stamp_ns else dt
                dtm = min(dtm, max_dt)
                st.mag_stamp_ns = tk
                # anomalies, smoothed over mag_anomaly_tau_s (sensor noise alone should not trip them)
                gam = dtm / (tau_an + dtm)
                en_lp += gam * (mn / st.mag_norm_ref - 1.0 - en_lp)
                ed_lp += gam * (dip - st.mag_dip_ref - ed_lp)
                ed = dip - st.mag_dip_ref
                rn, rd = en_lp / ntol, ed_lp / dtol
                anomaly = rn * rn + rd * rd
                if rn * rn <= 1.0 and rd * rd <= 1.0:
                    beta = dtm / (tau_m + dtm)
                    st.mag_norm_ref += beta * (mn - st.mag_norm_ref)
                    st.mag_dip_ref += beta * ed
                    st.mag_dist_s = 0.0
                    st.mag_ok_s += dtm
                else:
                    use = False
                    st.mag_dist_s += dtm
                    # persistent: a new environment, not a disturbance. The first reference comes from
                    # one sample at start-up, dipped through a tilt that may be wrong while moving:
                    # until the field has agreed with it for mag_ref_confirm_s, relearn after the shorter
                    # mag_relearn_first_s
                    if st.mag_dist_s > (relearn if st.mag_ok_s >= confirm else relearn_first):
                        st.mag_norm_ref, st.mag_dip_ref = mn, dip
                        st.mag_dist_s = 0.0
                        en_lp = ed_lp = 0.0
            if use:
                rm = sm2 * (1.0 + 4.0 * anomaly) + k_mw2 * wn2
                zy = (math.atan2(mex, mey) - decl + math.pi) % (2.0 * math.pi) - math.pi
                s = P[14] + rm
                nis = zy * zy / s
                if nis > gate:
                    rm += s * (nis / gate - 1.0)
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
                ez = k2 * zy
                bx += k3 * zy
                by += k4 * zy
                bz += k5 * zy
                hz = 0.5 * ez
                qw, qx, qy, qz = qw - hz * qz, qx - hz * qy, qy + hz * qx, qz + hz * qw
                qn = 1.0 / sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
                qw, qx, qy, qz = qw * qn, qx * qn, qy * qn, qz * qn
                ylx, yly = ylx - ez * yly, yly + ez * ylx
                vlx, vly = vlx - ez * vly, vly + ez * vlx
            else:
                n_mag_skip += 1

        if out_q is not None:
            out_q.append((qw, qx, qy, qz))
        if out_cov is not None:
            out_cov.append((P[0], P[1], P[2], P[6], P[7], P[8], P[12], P[13],
                            P[14] + (sys2 if st.mag_ref_ok else 0.0)))

    # ---- locals back into the state ----
    st.q = [qw, qx, qy, qz]
    st.bias = [bx, by, bz]
    st.P = P
    st.acc_mean, st.acc_var = acc_mean, acc_var
    st.gyro_lp = [glx, gly, glz]
    st.acc_lp = [alx, aly, alz]
    st.enu_lp = [ylx, yly, ylz]
    st.enu_lp_rate = [vlx, vly, vlz]
    st.rest_s = rest_s
    st.mag_norm_anomaly, st.mag_dip_anomaly = en_lp, ed_lp
    st.stamp_ns = t_prev
    st.n_acc_skipped, st.n_mag_skipped = n_acc_skip, n_mag_skip


class Aekf:
    """Online adaptive EKF. ``update()`` one sample at a time; ``state()``/``set_state()`` to save
    and resume (100 + 100 samples == 200 samples)."""

    def __init__(self, params: AekfParams | None = None) -> None:
        self.params = params if params is not None else AekfParams()
        self.params.validate()
        self._st = AekfState()
        self._pending_mag: list[float] | None = None

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
        _run(self._st, self.params, [int(stamp_ns)], [g], [a], mm, None, None)

    def update_imu(self, stamp_ns: int, gyro: Sequence[float] | np.ndarray, acc: Sequence[float] | np.ndarray) -> None:
        """One IMU sample; a magnetometer sample given by :meth:`update_mag` since the previous IMU
        sample is applied with it (each magnetometer sample once)."""
        mag, self._pending_mag = self._pending_mag, None
        self.update(stamp_ns, gyro, acc, mag)

    def update_mag(self, stamp_ns: int, mag: Sequence[float] | np.ndarray) -> None:
        """One magnetometer sample at its own stamp, applied with the next IMU sample."""
        m = [float(v) for v in mag]
        if len(m) != 3 or not all(math.isfinite(v) for v in m):
            raise InvalidInputError("nan", f"non-finite or malformed magnetometer sample at stamp {stamp_ns} ns")
        self._pending_mag = m

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
               params: AekfParams | None = None,
               state: AekfState | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Run the filter over whole arrays: ``t_ns`` (N,) int ns, ``gyro`` (N, 3) rad/s, ``acc`` (N, 3)
    m/s², ``mag`` (N, 3) or None (rows of NaN = no magnetometer sample). Returns ``quat`` (N, 4)
    w x y z device→ENU and ``cov`` (N, 3, 3) rad² (see :attr:`Aekf.orientation_cov`). ``state``
    (optional) is resumed and advanced in place."""
    params = params if params is not None else AekfParams()
    params.validate()
    t = np.asarray(t_ns).astype(np.int64)
    g = np.asarray(gyro, dtype=float)
    a = np.asarray(acc, dtype=float)
    n = len(t)
    if g.shape != (n, 3) or a.shape != (n, 3):
        raise InvalidInputError("shape", f"expected gyro/acc of shape ({n}, 3), got {g.shape} and {a.shape}")
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
    st = state if state is not None else AekfState()
    out_q: list[Sequence[float]] = []
    out_c: list[Sequence[float]] = []
    _run(st, params, t.tolist(), g.tolist(), a.tolist(), mlist, out_q, out_c)
    return np.array(out_q).reshape(n, 4), np.array(out_c).reshape(n, 3, 3)
