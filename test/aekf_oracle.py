"""A plain matrix-form implementation of the AEKF (numpy 6×6, no unrolling), written from the
filter's description in :mod:`indoor_loc.imu.aekf` — slow and obviously correct, the oracle the
unrolled per-sample loop is tested against."""
from __future__ import annotations

import math

import numpy as np

from indoor_loc.imu.aekf import AekfParams


def _rotmat(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class AekfOracle:
    def __init__(self, p: AekfParams | None = None):
        self.p = p or AekfParams()
        self.init = False

    def _initialise(self, a, m):
        p = self.p
        an = a / np.linalg.norm(a)
        q = np.array([1.0 + an[2], an[1], -an[0], 0.0])          # shortest arc a → e_z
        if q[0] < 1e-9:
            q = np.array([0.0, 1.0, 0.0, 0.0])
        q /= np.linalg.norm(q)
        yaw_var = math.pi ** 2 / 3.0
        self.ref_ok = False
        self.norm_ref = self.dip_ref = 0.0
        if m is not None:
            me = _rotmat(q) @ m
            if math.hypot(me[0], me[1]) > 1e-9 * (abs(me[2]) + 1e-12):
                yaw = _wrap(math.atan2(me[0], me[1]) - p.mag_declination)
                q = _qmul(np.array([math.cos(0.5 * yaw), 0, 0, math.sin(0.5 * yaw)]), q)
                yaw_var = p.mag_noise ** 2
                me = _rotmat(q) @ m
                self.ref_ok = True
                self.norm_ref = np.linalg.norm(me)
                self.dip_ref = math.asin(max(-1.0, min(1.0, me[2] / self.norm_ref)))
        self.q, self.b = q, np.zeros(3)
        tilt_var = (p.acc_noise / p.gravity) ** 2
        self.P = np.diag([tilt_var, tilt_var, yaw_var] + [p.bias_init_std ** 2] * 3)
        self.acc_mean, self.acc_var = float(np.linalg.norm(a)), 0.0
        self.acc_lp = a.copy()
        self.y = _rotmat(q) @ a
        self.v = np.zeros(3)
        self.rest_s = 0.0
        self.en = self.ed = 0.0
        self.dist_s = 0.0
        self.ok_s = 0.0
        self.mag_t = 0
        self.init = True

    def _correct(self, dx):
        e = dx[:3]
        self.b = self.b + dx[3:]
        self.q = _qmul(np.array([1.0, *(0.5 * e)]), self.q)
        self.q /= np.linalg.norm(self.q)
        self.y = self.y + np.cross(e, self.y)
        self.v = self.v + np.cross(e, self.v)

    def _propagate(self, w, dt, integrate):
        p = self.p
        wn2 = float(w @ w)
        if integrate:
            ang = math.sqrt(wn2) * dt
            dq = (np.array([math.cos(ang / 2), *(w * math.sin(ang / 2) / math.sqrt(wn2))])
                  if ang > 1e-12 else np.array([1.0, *(0.5 * w * dt)]))
            self.q = _qmul(self.q, dq)
            self.q /= np.linalg.norm(self.q)
        F = np.eye(6)
        F[:3, 3:] = -_rotmat(self.q) * dt
        Q = np.diag([(p.gyro_noise ** 2 + p.gyro_scale_error ** 2 * wn2) * dt] * 3 + [p.bias_walk ** 2 * dt] * 3)
        self.P = F @ self.P @ F.T + Q

    def mag_at(self, t, m):
        """A magnetometer sample at its own stamp: propagate from the attitude's time to ``t`` with the
        last gyroscope sample, then the magnetometer update."""
        m = np.asarray(m, float)
        if not self.init:
            self.pending = m
            return
        w = self.g_last - self.b
        dt = (t - self.t_att) * 1e-9
        if dt > 0:
            self._propagate(w, dt, (t - self.t) * 1e-9 <= self.p.max_dt_s)
            self.t_att = t
        self._mag(t, m, float(w @ w), self.imu_dt)

    def step(self, t, g, a, m):
        p = self.p
        g, a = np.asarray(g, float), np.asarray(a, float)
        m = None if m is None else np.asarray(m, float)
        if not self.init:
            self._initialise(a, m if m is not None else getattr(self, "pending", None))
            self.t = self.t_att = t
            self.gyro_lp = g.copy()
            self.g_last, self.imu_dt = g.copy(), 0.0
            return self.out()
        dt = (t - self.t) * 1e-9
        dt_att = (t - self.t_att) * 1e-9
        self.t = self.t_att = t
        self.g_last, self.imu_dt = g.copy(), dt
        # prediction
        w = g - self.b
        wn2 = float(w @ w)
        self._propagate(w, dt_att, dt <= p.max_dt_s)
        R = _rotmat(self.q)
        # motion statistics and rest detection
        an = float(np.linalg.norm(a))
        alpha = dt / (p.acc_stat_tau_s + dt)
        d = an - self.acc_mean
        self.acc_mean += alpha * d
        self.acc_var += alpha * (d * d - self.acc_var)
        self.gyro_lp = self.gyro_lp + alpha * (g - self.gyro_lp)
        self.acc_lp = self.acc_lp + alpha * (a - self.acc_lp)
        still = (wn2 < p.rest_gyro ** 2 and np.sum((g - self.gyro_lp) ** 2) < p.rest_gyro ** 2
                 and np.sum((a - self.acc_lp) ** 2) < p.rest_acc_m_s2 ** 2)
        self.rest_s = self.rest_s + dt if still else 0.0
        # accelerometer: tilt
        ue = R @ a
        use_lp = p.acc_lp_tau_s > 0
        if use_lp:
            wl = math.sqrt(2.0) / p.acc_lp_tau_s
            h = min(dt, p.max_dt_s)
            self.v = self.v + h * (wl * wl * (ue - self.y) - math.sqrt(2.0) * wl * self.v)
            self.y = self.y + h * self.v
        else:
            self.y = ue
        yn = float(np.linalg.norm(self.y))
        dev, dlp = an - p.gravity, yn - p.gravity
        rej2 = p.acc_reject_m_s2 ** 2
        if yn > 1e-6 and dlp ** 2 <= rej2 and (use_lp or (dev ** 2 <= rej2 and self.acc_var <= rej2)):
            ra = (p.acc_noise ** 2 + p.acc_adapt_gain * (dev ** 2 + self.acc_var)) / p.gravity ** 2
            z = np.array([self.y[1], -self.y[0]]) / yn
            H = np.zeros((2, 6))
            H[0, 0] = H[1, 1] = 1.0
            S = H @ self.P @ H.T + ra * np.eye(2)
            K = self.P @ H.T @ np.linalg.inv(S)
            self.P = self.P - K @ H @ self.P
            self._correct(K @ z)
        # rest: zero-rate update of the bias
        if self.rest_s >= p.rest_min_s and self.rest_s > 0.0:
            H = np.hstack([np.zeros((3, 3)), np.eye(3)])
            S = H @ self.P @ H.T + p.rest_gyro_noise ** 2 * np.eye(3)
            K = self.P @ H.T @ np.linalg.inv(S)
            self.P = self.P - K @ H @ self.P
            self._correct(K @ w)
        # magnetometer: heading only
        if m is not None:
            self._mag(t, m, wn2, dt)
        return self.out()

    def _mag(self, t, m, wn2, dt):
        p = self.p
        mn = float(np.linalg.norm(m))
        me = _rotmat(self.q) @ m
        use = mn > 0.0 and math.hypot(me[0], me[1]) > 1e-3 * mn
        anomaly = 0.0
        if use:
            dip = math.asin(max(-1.0, min(1.0, me[2] / mn)))
            if not self.ref_ok:
                self.ref_ok, self.norm_ref, self.dip_ref = True, mn, dip
            dtm = min((t - self.mag_t) * 1e-9 if self.mag_t else dt, p.max_dt_s)
            self.mag_t = t
            gam = dtm / (p.mag_anomaly_tau_s + dtm) if dtm > 0 else float(p.mag_anomaly_tau_s == 0)
            self.en += gam * (mn / self.norm_ref - 1.0 - self.en)
            self.ed += gam * (dip - self.dip_ref - self.ed)
            rn, rd = self.en / p.mag_norm_tol, self.ed / p.mag_dip_tol
            anomaly = rn * rn + rd * rd
            if rn * rn <= 1.0 and rd * rd <= 1.0:
                beta = dtm / (p.mag_ref_tau_s + dtm)
                ed = dip - self.dip_ref
                self.norm_ref += beta * (mn - self.norm_ref)
                self.dip_ref += beta * ed
                self.dist_s = 0.0
                self.ok_s += dtm
            else:
                use = False
                self.dist_s += dtm
                if self.dist_s > (p.mag_relearn_s if self.ok_s >= p.mag_ref_confirm_s else p.mag_relearn_first_s):
                    self.norm_ref, self.dip_ref = mn, dip
                    self.dist_s = 0.0
                    self.en = self.ed = 0.0
        if use:
            rm = p.mag_noise ** 2 * (1.0 + 4.0 * anomaly) + p.mag_rate_noise_s ** 2 * wn2
            zy = _wrap(math.atan2(me[0], me[1]) - p.mag_declination)
            s = self.P[2, 2] + rm
            if zy * zy / s > p.mag_gate_nis:
                rm += s * (zy * zy / s / p.mag_gate_nis - 1.0)
                s = self.P[2, 2] + rm
            K = np.zeros(6)
            K[2:] = self.P[2, 2:] / s                        # no gain on tilt
            H = np.zeros(6)
            H[2] = 1.0
            A = np.eye(6) - np.outer(K, H)
            self.P = A @ self.P @ A.T + rm * np.outer(K, K)   # Joseph form (any gain)
            self._correct(K * zy)

    def out(self):
        cov = self.P[:3, :3].copy()
        if self.ref_ok:
            cov[2, 2] += self.p.mag_heading_sys_std ** 2
        return self.q.copy(), cov
