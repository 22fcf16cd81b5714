"""Traditional nonlinear PDR models with EKF and UKF, for comparison with the linear model (Raitoharju et al. 2015).

State ``x = [r1, r2, theta, s]`` (eq. 47): position (m), heading (rad, ENU, not wrapped — there
are no angle measurements) and footstep length (m). One prediction covers ``steps`` footsteps::

    r_t     = r_{t-1} + steps * s_{t-1} [cos theta_{t-1}, sin theta_{t-1}]
    theta_t = theta_{t-1} + dtheta + e_theta,   e_theta ~ N(0, steps * sigma_dtheta^2)
    s_t     = s_{t-1} + e_s,                    e_s ~ N(0, steps * sigma_ds^2)

EKF: eqs. 48–50 (linearised F); UKF: eqs. 14–22 with the state propagated through the model
(noise is additive here, so the augmented state of eqs. 51–52 reduces to adding Q). WiFi fixes are
the same linear position measurements as in :mod:`indoor_loc.fusion.linear_pdr`, so both filters
share the gated Joseph-form update. Same interface as :class:`LinearPdrKf` (``predict``,
``update``, ``mahalanobis``, ``state``); :func:`run_filter` gives a batch :class:`KfTrack` with the
(statistically) linearised transitions so :func:`rts_smooth` applies to both.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from indoor_loc.params import field, require
from indoor_loc.errors import InvalidInputError
from indoor_loc.fusion.linear_pdr import (KfState, KfTrack, LinearPdrKf, PositionFilter)
from indoor_loc.measurements import Fix



@dataclass(frozen=True)
class NonlinearPdrParams:
    """Parameters of the nonlinear [r, theta, s] PDR model (eq. 47) for EKF and UKF."""
    step_length_m: float = field(0.7, "initial footstep length mean (m)")
    init_step_var_m2: float = field(0.01, "initial footstep length variance (m^2)")
    init_heading_rad: float = field(0.0, "initial heading mean (rad, ENU)")
    init_heading_var_rad2: float = field(1.0, "initial heading variance (rad^2); keep < (pi/2)^2 or the UKF's "
                                              "sigma points wrap around and hide the uncertainty")
    init_pos_var_m2: float = field(100.0, "initial position variance per axis when no position is given (m^2)")
    sigma_dtheta_rad: float = field(0.1, "heading-change noise per footstep (rad)")
    sigma_ds_m: float = field(0.02, "footstep-length random walk per footstep (m)")
    q_floor: float = field(1e-8, "process-noise floor on theta (rad^2) and s (m^2) per prediction")
    gate: bool = field(True, "reject WiFi fixes whose innovation fails the chi-square test")
    gate_prob: float = field(0.999, "chi-square (2 dof) probability of the innovation gate")
    ukf_alpha: float = field(1.0, "UKF spread alpha (eq. 17)")
    ukf_beta: float = field(2.0, "UKF beta (eq. 21); 2 is optimal for Gaussians")
    ukf_kappa: float = field(-1.0, "UKF kappa (eq. 17); 3 - d = -1 matches Gaussian fourth moments for d = 4")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.step_length_m > 0, n, "step_length_m", "> 0", self.step_length_m)
        for name in ("init_step_var_m2", "init_heading_var_rad2", "init_pos_var_m2", "q_floor", "ukf_alpha"):
            require(getattr(self, name) > 0, n, name, "> 0", getattr(self, name))
        for name in ("sigma_dtheta_rad", "sigma_ds_m", "ukf_beta"):
            require(getattr(self, name) >= 0, n, name, ">= 0", getattr(self, name))
        require(0.0 < self.gate_prob < 1.0, n, "gate_prob", "in (0, 1)", self.gate_prob)
        require(self.ukf_alpha ** 2 * (4 + self.ukf_kappa) > 0, n, "ukf_kappa", "alpha^2 (4 + kappa) > 0",
                  self.ukf_kappa)

    @property
    def gate_threshold(self) -> float:
        return float(chi2.ppf(self.gate_prob, 2)) if self.gate else np.inf


def transition(x: np.ndarray, steps: float, dtheta: float) -> np.ndarray:
    """Mean transition of eq. 47 for states ``x`` (..., 4)."""
    x = np.asarray(x, float)
    out = x.copy()
    out[..., 0] = x[..., 0] + steps * x[..., 3] * np.cos(x[..., 2])
    out[..., 1] = x[..., 1] + steps * x[..., 3] * np.sin(x[..., 2])
    out[..., 2] = x[..., 2] + dtheta
    return out


def transition_jacobian(x: np.ndarray, steps: float) -> np.ndarray:
    """Linearised transition of eq. 49 at ``x`` (4,) -> (4, 4)."""
    c, s = np.cos(x[2]), np.sin(x[2])
    return np.array([[1.0, 0.0, -steps * x[3] * s, steps * c],
                     [0.0, 1.0, steps * x[3] * c, steps * s],
                     [0.0, 0.0, 1.0, 0.0],
                     [0.0, 0.0, 0.0, 1.0]])


def process_noise(p: NonlinearPdrParams, steps: float) -> np.ndarray:
    """Additive process noise of eq. 50 for ``steps`` footsteps (4, 4)."""
    n = abs(steps)
    return np.diag([0.0, 0.0, n * p.sigma_dtheta_rad ** 2 + p.q_floor, n * p.sigma_ds_m ** 2 + p.q_floor])


class _NonlinearPdrFilter(PositionFilter):
    """Shared state handling of the EKF and the UKF (the update is linear for both)."""

    def __init__(self, params: NonlinearPdrParams | None = None, *, xy0: np.ndarray | None = None,
                 pos_cov0: np.ndarray | None = None, stamp_ns: int = 0) -> None:
        self.params = params or NonlinearPdrParams()
        self.params.validate()
        p = self.params
        x = np.array([0.0, 0.0, p.init_heading_rad, p.step_length_m])
        Pm = np.diag([p.init_pos_var_m2, p.init_pos_var_m2, p.init_heading_var_rad2, p.init_step_var_m2])
        if xy0 is not None:
            x[:2] = np.asarray(xy0, float).reshape(2)
        if pos_cov0 is not None:
            Pm[:2, :2] = np.asarray(pos_cov0, float).reshape(2, 2)
        self.state = KfState(x=x, P=Pm, stamp_ns=int(stamp_ns))
        self.last_F = np.eye(4)

    def _check(self, steps: float, dtheta: float) -> None:
        if not (np.isfinite(steps) and np.isfinite(dtheta)) or steps < 0:
            raise InvalidInputError("bad_pdr", f"{type(self).__name__}.predict: expected finite steps >= 0 "
                                      f"and dtheta, got {steps}, {dtheta}")

    def predict(self, steps: float, dtheta: float, *, stamp_ns: int | None = None) -> None:
        raise NotImplementedError


class PdrEkf(_NonlinearPdrFilter):
    """EKF on the nonlinear [r, theta, s] model (eqs. 48–50)."""

    def predict(self, steps: float, dtheta: float, *, stamp_ns: int | None = None) -> None:
        self._check(steps, dtheta)
        st = self.state
        F = transition_jacobian(st.x, steps)
        st.x = transition(st.x, steps, dtheta)
        Pn = F @ st.P @ F.T + process_noise(self.params, steps)
        st.P = 0.5 * (Pn + Pn.T)
        self.last_F = F
        if stamp_ns is not None:
            st.stamp_ns = int(stamp_ns)


class PdrUkf(_NonlinearPdrFilter):
    """UKF on the nonlinear [r, theta, s] model (sigma points eqs. 14–17, weights eqs. 20–22)."""

    def _weights(self, d: int) -> tuple[float, np.ndarray, np.ndarray]:
        p = self.params
        xi = p.ukf_alpha ** 2 * (d + p.ukf_kappa) - d
        wm = np.full(2 * d + 1, 1.0 / (2 * (d + xi)))
        wc = wm.copy()
        wm[0] = xi / (d + xi)
        wc[0] = xi / (d + xi) + (1.0 - p.ukf_alpha ** 2 + p.ukf_beta)
        return xi, wm, wc

    def predict(self, steps: float, dtheta: float, *, stamp_ns: int | None = None) -> None:
        self._check(steps, dtheta)
        st = self.state
        d = 4
        xi, wm, wc = self._weights(d)
        L = np.linalg.cholesky((d + xi) * st.P)
        chi = np.vstack([st.x, st.x + L.T, st.x - L.T])  # (2d+1, 4): columns of L as offsets
        y = transition(chi, steps, dtheta)
        xm = wm @ y
        dy = y - xm
        dx = chi - st.x
        Pn = (wc[:, None] * dy).T @ dy + process_noise(self.params, steps)
        Pxy = (wc[:, None] * dx).T @ dy  # cross covariance of x_{t-1} and x_t
        # statistical linearisation, used by the RTS smoother: F = Pxy^T P^-1
        self.last_F = np.linalg.solve(st.P, Pxy).T
        st.x = xm
        st.P = 0.5 * (Pn + Pn.T)
        if stamp_ns is not None:
            st.stamp_ns = int(stamp_ns)


def run_filter(filt: "_NonlinearPdrFilter | LinearPdrKf", steps: np.ndarray, dtheta: np.ndarray, z: np.ndarray,
               R: np.ndarray) -> KfTrack:
    """Run any filter with ``predict(steps, dtheta)``/``update(Fix)``/``state`` over T epochs
    (predict, then update where ``z[t]`` is finite) and record a :class:`KfTrack`.

    For the nonlinear filters ``F`` is the EKF Jacobian or the UKF statistical linearisation,
    so :func:`indoor_loc.fusion.linear_pdr.rts_smooth` gives the (extended/unscented) RTS smoother.
    """
    T = len(steps)
    n = len(filt.state.x)
    out = KfTrack(np.zeros((T, n)), np.zeros((T, n, n)), np.zeros((T, n)), np.zeros((T, n, n)),
                  np.zeros((T, n, n)), np.zeros(T, bool), np.full(T, np.nan))
    for t in range(T):
        filt.predict(float(steps[t]), float(dtheta[t]))
        out.x_pred[t], out.P_pred[t] = filt.state.x, filt.state.P
        out.F[t] = filt.last_F
        if np.all(np.isfinite(z[t])):
            out.accepted[t] = filt.update(Fix(0, z[t], R[t]))
            out.nis[t] = filt.state.last_nis
        out.x_filt[t], out.P_filt[t] = filt.state.x, filt.state.P
    return out
