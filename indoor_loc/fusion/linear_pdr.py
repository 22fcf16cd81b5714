"""Linear PDR Kalman filter and Rauch–Tung–Striebel smoother (Raitoharju et al. 2015, Sec. 4; docs/references.md).

State ``x = [r1, r2, v1, v2]``: position (m, map frame) and *footstep vector* (m per step). One
prediction covers ``steps`` footsteps during which the heading changed by ``dtheta`` (eq. 53)::

    r_t = r_{t-1} + steps * v_{t-1}
    v_t = R(dtheta) v_{t-1} + dv,          dv ~ N(0, sigma_dv^2 I)

which is linear in the state, so the Kalman filter is exact for it; no initial heading is needed
(the step vector starts at 0 with 1 m^2 per axis and WiFi fixes make it observable).

Process noise (eqs. 54, 58): the paper equates ``sigma_dv^2 = sigma_dtheta^2 s^2 = sigma_ds^2``.
Here both the heading-change and the step-length-change variances are added isotropically per
footstep, ``sigma_dv^2 = steps * (sigma_dtheta^2 s^2 + sigma_ds^2)`` (plus a tiny floor keeping the
prediction covariance invertible for the smoother). WiFi fixes (``Fix.xy``, ``Fix.cov``) are
linear position measurements ``z = [I 0] x + e`` (eq. 32), gated by the squared Mahalanobis
distance of the innovation (chi-square test with 2 degrees of freedom) and applied with the
Joseph-form covariance update.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np
from scipy.stats import chi2

from indoor_loc.params import field, require
from indoor_loc.errors import InvalidInputError
from indoor_loc.measurements import Fix

H_POS = np.hstack([np.eye(2), np.zeros((2, 2))])  # (2, 4) position measurement matrix


@dataclass(frozen=True)
class LinearPdrParams:
    """Parameters of the Raitoharju et al. 2015 linear PDR model and its WiFi update."""
    step_length_m: float = field(0.7, "nominal footstep length s (m), scales the heading noise")
    sigma_dtheta_rad: float = field(0.1, "heading-change noise per footstep (rad)")
    sigma_ds_m: float = field(0.07, "step-vector length change noise per footstep (m)")
    q_floor_m2: float = field(1e-6, "process-noise floor on the step vector per prediction (m^2)")
    init_pos_var_m2: float = field(100.0, "initial position variance per axis when no position is given (m^2)")
    init_step_var_m2: float = field(1.0, "initial step-vector variance per axis; mean 0 (m^2)")
    gate: bool = field(True, "reject WiFi fixes whose innovation fails the chi-square test")
    gate_prob: float = field(0.999, "chi-square (2 dof) probability of the innovation gate")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.step_length_m > 0, n, "step_length_m", "> 0", self.step_length_m)
        require(self.sigma_dtheta_rad >= 0, n, "sigma_dtheta_rad", ">= 0", self.sigma_dtheta_rad)
        require(self.sigma_ds_m >= 0, n, "sigma_ds_m", ">= 0", self.sigma_ds_m)
        require(self.q_floor_m2 > 0, n, "q_floor_m2", "> 0", self.q_floor_m2)
        require(self.init_pos_var_m2 > 0, n, "init_pos_var_m2", "> 0", self.init_pos_var_m2)
        require(self.init_step_var_m2 > 0, n, "init_step_var_m2", "> 0", self.init_step_var_m2)
        require(0.0 < self.gate_prob < 1.0, n, "gate_prob", "in (0, 1)", self.gate_prob)

    @property
    def gate_threshold(self) -> float:
        """Squared-Mahalanobis gate for a 2-D innovation (``chi2.ppf(gate_prob, 2)``)."""
        return float(chi2.ppf(self.gate_prob, 2)) if self.gate else np.inf


@dataclass
class KfState:
    """Gaussian state: mean ``x`` (n,), covariance ``P`` (n, n), time of validity in ns."""
    x: np.ndarray
    P: np.ndarray
    stamp_ns: int = 0
    n_updates: int = 0
    n_rejected: int = 0
    last_nis: float = float("nan")

    def copy(self) -> "KfState":
        return replace(self, x=self.x.copy(), P=self.P.copy())


# ----------------------------------------------------------------------------------------------
# Model pieces (pure functions)
# ----------------------------------------------------------------------------------------------
def transition_matrix(steps: float, dtheta: float) -> np.ndarray:
    """F_t of eq. 53 generalised to ``steps`` footsteps (4, 4)."""
    c, s = np.cos(dtheta), np.sin(dtheta)
    return np.array([[1.0, 0.0, steps, 0.0],
                     [0.0, 1.0, 0.0, steps],
                     [0.0, 0.0, c, -s],
                     [0.0, 0.0, s, c]])


def process_noise(p: LinearPdrParams, steps: float) -> np.ndarray:
    """Q_t of eq. 54 (4, 4): ``steps * (sigma_dtheta^2 s^2 + sigma_ds^2)`` on the step vector."""
    q = abs(steps) * (p.sigma_dtheta_rad ** 2 * p.step_length_m ** 2 + p.sigma_ds_m ** 2) + p.q_floor_m2
    return np.diag([0.0, 0.0, q, q])


def joseph_update(x: np.ndarray, Pm: np.ndarray, z: np.ndarray, R: np.ndarray, H: np.ndarray,
                  gate_threshold: float = np.inf) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """Linear KF update with chi-square gating and the Joseph form ``(I-KH)P(I-KH)^T + K R K^T``.

    Returns (x+, P+, nis, accepted); when rejected x, P come back unchanged.
    """
    y = z - H @ x
    S = H @ Pm @ H.T + R
    S = 0.5 * (S + S.T)
    Sinv_y = np.linalg.solve(S, y)
    nis = float(y @ Sinv_y)
    if not nis <= gate_threshold:
        return x, Pm, nis, False
    K = np.linalg.solve(S, H @ Pm).T  # P H^T S^-1, S symmetric
    ImKH = np.eye(len(x)) - K @ H
    Pn = ImKH @ Pm @ ImKH.T + K @ R @ K.T
    return x + K @ y, 0.5 * (Pn + Pn.T), nis, True


def mahalanobis_sq(points: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distances of ``points`` (N, 2) from N(mean (2,), cov (2, 2)) -> (N,)."""
    d = np.atleast_2d(np.asarray(points, float)) - mean
    L = np.linalg.cholesky(0.5 * (cov + cov.T))
    u = np.linalg.solve(L, d.T)
    return np.einsum("ij,ij->j", u, u)


def _check_fix(fix: Fix) -> tuple[np.ndarray, np.ndarray]:
    z = np.asarray(fix.xy, float).reshape(2)
    R = np.asarray(fix.cov, float).reshape(2, 2)
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(R))):
        raise InvalidInputError("nan", f"fix: expected finite xy and cov, got xy={z}, cov={R.tolist()}")
    return z, R


# ----------------------------------------------------------------------------------------------
# Online filter
# ----------------------------------------------------------------------------------------------
class PositionFilter:
    """What the PDR filters share: a state whose first two components are the position, read
    access (``x``, ``P``, ``position`` (2,), ``position_cov`` (2, 2)), the gated linear WiFi
    position update and the innovation / Mahalanobis tests on it."""
    state: KfState
    params: Any    # a Params object with ``gate_threshold``

    @property
    def x(self) -> np.ndarray:
        return self.state.x

    @property
    def P(self) -> np.ndarray:
        return self.state.P

    @property
    def position(self) -> np.ndarray:
        return self.state.x[:2].copy()

    @property
    def position_cov(self) -> np.ndarray:
        return self.state.P[:2, :2].copy()


    def update(self, fix: Fix) -> bool:
        """Apply a WiFi fix as a linear position measurement (gated, Joseph form). Returns True if
        it passed the gate (fixes with ``ok=False`` are ignored and return False)."""
        if not fix.ok:
            return False
        z, R = _check_fix(fix)
        st = self.state
        st.x, st.P, st.last_nis, ok = joseph_update(st.x, st.P, z, R, H_POS, self.params.gate_threshold)
        if ok:
            st.n_updates += 1
        else:
            st.n_rejected += 1
        return ok

    def nis(self, fix: Fix) -> float:
        """Normalised innovation squared of a fix against the current prediction (no update)."""
        z, R = _check_fix(fix)
        return float(mahalanobis_sq(z[None], self.state.x[:2], self.state.P[:2, :2] + R)[0])

    def mahalanobis(self, points: np.ndarray) -> np.ndarray:
        """Squared Mahalanobis distance of candidate positions (N, 2) from the position estimate
        (Raitoharju et al. 2015, Sec. 5.2, integrity monitoring of a particle filter: ``(c_i - x)^T P^-1 (c_i - x)``) -> (N,)."""
        return mahalanobis_sq(points, self.state.x[:2], self.state.P[:2, :2])


class LinearPdrKf(PositionFilter):
    """Online Raitoharju et al. 2015 linear PDR Kalman filter. ``predict(steps, dtheta)`` per PDR increment,
    ``update(fix)`` per WiFi fix; ``state`` can be saved (``state.copy()``) and restored."""

    def __init__(self, params: LinearPdrParams | None = None, *, xy0: np.ndarray | None = None,
                 pos_cov0: np.ndarray | None = None, stamp_ns: int = 0,
                 heading: tuple[float, float] | None = None) -> None:
        self.params = params or LinearPdrParams()
        self.params.validate()
        self.state = initial_state(self.params, xy0=xy0, pos_cov0=pos_cov0, stamp_ns=stamp_ns, heading=heading)
        self.last_F = np.eye(4)


    def predict(self, steps: float, dtheta: float, *, stamp_ns: int | None = None) -> None:
        """Propagate ``steps`` footsteps (may be fractional, >= 0) with heading change ``dtheta`` rad."""
        if not (np.isfinite(steps) and np.isfinite(dtheta)) or steps < 0:
            raise InvalidInputError("bad_pdr", f"LinearPdrKf.predict: expected finite steps >= 0 and dtheta, "
                                                  f"got {steps}, {dtheta}")
        F = transition_matrix(steps, dtheta)
        self.last_F = F
        st = self.state
        st.x = F @ st.x
        Pn = F @ st.P @ F.T + process_noise(self.params, steps)
        st.P = 0.5 * (Pn + Pn.T)
        if stamp_ns is not None:
            st.stamp_ns = int(stamp_ns)

    def predict_matrix(self, F: np.ndarray, Q: np.ndarray, *, stamp_ns: int | None = None) -> None:
        """Propagate with a given transition ``F`` (4, 4) and process noise ``Q`` (4, 4) (a robot's
        odometry increment, :func:`indoor_loc.fusion.odom_kf.odom_transition`)."""
        self.last_F = F
        st = self.state
        st.x = F @ st.x
        Pn = F @ st.P @ F.T + Q
        st.P = 0.5 * (Pn + Pn.T)
        if stamp_ns is not None:
            st.stamp_ns = int(stamp_ns)


def initial_state(p: LinearPdrParams, *, xy0: np.ndarray | None = None, pos_cov0: np.ndarray | None = None,
                  stamp_ns: int = 0, heading: tuple[float, float] | None = None) -> KfState:
    """Initial state: position ``xy0`` (default 0 with ``init_pos_var_m2``), step vector 0 with
    ``init_step_var_m2`` per axis (no initial heading) — or, with ``heading = (ψ, σψ)`` (rad, map
    frame: the odometry's yaw when it is known to be map-aligned), the step vector
    ``s (cos ψ, sin ψ)`` with variance ``(s σψ)²`` across it and ``sigma_ds_m² + (0.2 s)²`` along it
    (first order in σψ; ``s`` = ``step_length_m``)."""
    x = np.zeros(4)
    Pm = np.diag([p.init_pos_var_m2, p.init_pos_var_m2, p.init_step_var_m2, p.init_step_var_m2])
    if xy0 is not None:
        x[:2] = np.asarray(xy0, float).reshape(2)
    if pos_cov0 is not None:
        Pm[:2, :2] = np.asarray(pos_cov0, float).reshape(2, 2)
    if heading is not None:
        psi, sd = float(heading[0]), float(heading[1])
        if not (np.isfinite(psi) and np.isfinite(sd) and sd > 0):
            raise InvalidInputError("bad_heading", f"initial heading: expected finite yaw and std > 0, got {heading}")
        s = p.step_length_m
        u = np.array([math.cos(psi), math.sin(psi)])
        n = np.array([-u[1], u[0]])
        x[2:4] = s * u
        Pm[2:4, 2:4] = (p.sigma_ds_m ** 2 + (0.2 * s) ** 2) * np.outer(u, u) + (s * sd) ** 2 * np.outer(n, n)
    return KfState(x=x, P=Pm, stamp_ns=int(stamp_ns))


# ----------------------------------------------------------------------------------------------
# Batch filter and RTS smoother
# ----------------------------------------------------------------------------------------------
@dataclass
class KfTrack:
    """Result of a batch run over T epochs (each epoch: predict, then update if a fix is present).

    x_pred, P_pred: (T, n), (T, n, n) predictions; x_filt, P_filt: filtered; F: (T, n, n) the
    transition (or linearisation) used at each epoch; accepted: (T,) bool fix applied;
    nis: (T,) innovation NIS (NaN without a fix).
    """
    x_pred: np.ndarray
    P_pred: np.ndarray
    x_filt: np.ndarray
    P_filt: np.ndarray
    F: np.ndarray
    accepted: np.ndarray
    nis: np.ndarray


def fixes_to_arrays(fixes: Sequence[Fix | None]) -> tuple[np.ndarray, np.ndarray]:
    """Per-epoch fixes (None or ok=False = no fix) -> z (T, 2) NaN where none, R (T, 2, 2)."""
    T = len(fixes)
    z = np.full((T, 2), np.nan)
    R = np.tile(np.eye(2), (T, 1, 1))
    for t, f in enumerate(fixes):
        if f is not None and f.ok:
            z[t], R[t] = _check_fix(f)
    return z, R


def filter_batch(params: LinearPdrParams, steps: np.ndarray, dtheta: np.ndarray, z: np.ndarray,
                 R: np.ndarray, *, xy0: np.ndarray | None = None, pos_cov0: np.ndarray | None = None,
                 x0: np.ndarray | None = None, P0: np.ndarray | None = None,
                 F: np.ndarray | None = None, Q: np.ndarray | None = None) -> KfTrack:
    """Linear KF over T epochs: steps (T,), dtheta (T,) rad, z (T, 2) m (NaN = no fix), R (T, 2, 2) m^2.

    The prior is the initial state from ``xy0``/``pos_cov0``, or the full state ``x0`` (4,) and
    ``P0`` (4, 4) when given (a window of a longer run starting from its filtered state). ``F`` and
    ``Q`` (T, 4, 4), when given, are each epoch's transition and process noise instead of the footstep
    model's (a robot's odometry increments)."""
    params.validate()
    steps = np.asarray(steps, float)
    dtheta = np.asarray(dtheta, float)
    z = np.asarray(z, float)
    R = np.asarray(R, float)
    T = len(steps)
    if not (dtheta.shape == (T,) and z.shape == (T, 2) and R.shape == (T, 2, 2)):
        raise InvalidInputError("shape", f"filter_batch: expected steps (T,), dtheta (T,), z (T,2), R (T,2,2), got "
                          f"{steps.shape}, {dtheta.shape}, {z.shape}, {R.shape}")
    st = initial_state(params, xy0=xy0, pos_cov0=pos_cov0)
    x, Pm = st.x, st.P
    if x0 is not None and P0 is not None:
        x, Pm = np.asarray(x0, float).reshape(4).copy(), np.asarray(P0, float).reshape(4, 4).copy()
    out = KfTrack(np.zeros((T, 4)), np.zeros((T, 4, 4)), np.zeros((T, 4)), np.zeros((T, 4, 4)),
                  np.zeros((T, 4, 4)), np.zeros(T, bool), np.full(T, np.nan))
    thr = params.gate_threshold
    for t in range(T):
        Ft = transition_matrix(steps[t], dtheta[t]) if F is None else F[t]
        x = Ft @ x
        Pm = Ft @ Pm @ Ft.T + (process_noise(params, steps[t]) if Q is None else Q[t])
        Pm = 0.5 * (Pm + Pm.T)
        out.F[t], out.x_pred[t], out.P_pred[t] = Ft, x, Pm
        if np.all(np.isfinite(z[t])):
            x, Pm, out.nis[t], out.accepted[t] = joseph_update(x, Pm, z[t], R[t], H_POS, thr)
        out.x_filt[t], out.P_filt[t] = x, Pm
    return out


def rts_smooth(track: KfTrack) -> tuple[np.ndarray, np.ndarray]:
    """Rauch–Tung–Striebel smoother (eqs. 23–25) over a :class:`KfTrack`.

    ``C_t = P_t|t F_{t+1}^T P_{t+1|t}^-1``; ``x_t|T = x_t|t + C_t (x_{t+1|T} - x_{t+1|t})``;
    ``P_t|T = P_t|t + C_t (P_{t+1|T} - P_{t+1|t}) C_t^T``. Returns means (T, n), covs (T, n, n).
    """
    xs = track.x_filt.copy()
    Ps = track.P_filt.copy()
    for t in range(len(xs) - 2, -1, -1):
        C = np.linalg.solve(track.P_pred[t + 1], track.F[t + 1] @ track.P_filt[t]).T
        xs[t] = track.x_filt[t] + C @ (xs[t + 1] - track.x_pred[t + 1])
        Pn = track.P_filt[t] + C @ (Ps[t + 1] - track.P_pred[t + 1]) @ C.T
        Ps[t] = 0.5 * (Pn + Pn.T)
    return xs, Ps
