"""Seed-004 linear PDR Kalman filter, RTS smoother and the EKF/UKF comparison models."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from indoor_loc.errors import ConfigError, InvalidInputError
from indoor_loc.fusion.linear_pdr import (LinearPdrKf, LinearPdrParams, filter_batch, fixes_to_arrays,
                                          process_noise, rts_smooth)
from indoor_loc.fusion.nonlinear import NonlinearPdrParams, PdrEkf, PdrUkf, run_filter
from indoor_loc.params import params_from_dict
from indoor_loc.measurements import Fix


def synthetic_walk(rng: np.random.Generator, n_epochs: int = 240, wifi_every: int = 4, wifi_sigma: float = 3.0):
    """A rectangular corridor loop walked twice: 2 steps per epoch, 90-degree turns spread over
    three epochs. Returns truth positions (T, 2), measured steps (T,), measured dtheta (T,), fixes
    z (T, 2) with NaN between fixes and R (T, 2, 2)."""
    seg = [20, 3, 20, 3, 20, 3, 20, 3]  # epochs per leg (turn legs in between)
    turns = []
    for i, n in enumerate(seg):
        turns += [0.0] * n if i % 2 == 0 else [np.pi / 2 / n] * n
    dth_true = np.resize(np.array(turns), n_epochs)
    dth_true[0] = 0.0
    steps_true = np.full(n_epochs, 2.0)
    step_len = 0.7 + 0.03 * rng.standard_normal(n_epochs)
    theta = 0.3
    v = step_len[0] * np.array([np.cos(theta), np.sin(theta)])
    r = np.array([5.0, 5.0])
    truth = np.zeros((n_epochs, 2))
    for t in range(n_epochs):
        r = r + steps_true[t] * v  # eq. 53: position advances with the previous step vector
        theta += dth_true[t]
        v = step_len[t] * np.array([np.cos(theta), np.sin(theta)])
        truth[t] = r
    steps_meas = steps_true + 0.1 * rng.standard_normal(n_epochs)
    dth_meas = dth_true + 0.05 * rng.standard_normal(n_epochs)
    z = np.full((n_epochs, 2), np.nan)
    R = np.tile(np.eye(2) * wifi_sigma ** 2, (n_epochs, 1, 1))
    idx = np.arange(0, n_epochs, wifi_every)
    z[idx] = truth[idx] + wifi_sigma * rng.standard_normal((len(idx), 2))
    return truth, steps_meas, dth_meas, z, R


def _err(est: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    return float(np.mean(np.linalg.norm(est[mask, :2] - truth[mask], axis=1)))


def test_filter_beats_wifi_and_smoother_beats_filter():
    rng = np.random.default_rng(4)
    errs = {"wifi": [], "filt": [], "smooth": []}
    p = LinearPdrParams(sigma_dtheta_rad=0.08, sigma_ds_m=0.05)
    for _ in range(5):
        truth, steps, dth, z, R = synthetic_walk(rng)
        has = np.isfinite(z[:, 0])
        trk = filter_batch(p, steps, dth, z, R, xy0=z[0], pos_cov0=R[0])
        xs, _ = rts_smooth(trk)
        warm = has & (np.arange(len(z)) >= 20)  # skip the first fixes while the heading converges
        errs["wifi"].append(_err(z, truth, warm))
        errs["filt"].append(_err(trk.x_filt, truth, warm))
        errs["smooth"].append(_err(xs, truth, warm))
    e = {k: float(np.mean(v)) for k, v in errs.items()}
    assert e["filt"] < 0.8 * e["wifi"], e
    assert e["smooth"] < 0.85 * e["filt"], e


def test_nees_consistent_when_truth_follows_the_model():
    """Truth sampled from the model itself -> mean NEES of the 4-state close to 4."""
    rng = np.random.default_rng(7)
    p = LinearPdrParams(gate=False)
    T, runs = 80, 40
    nees = np.zeros((runs, T))
    in95 = []
    for k in range(runs):
        steps = np.full(T, 1.5)
        dth = 0.2 * rng.standard_normal(T)
        xy0 = np.array([10.0, 3.0])
        x = np.r_[xy0 + rng.multivariate_normal(np.zeros(2), np.eye(2) * p.init_pos_var_m2),
                  rng.standard_normal(2) * np.sqrt(p.init_step_var_m2)]
        kf = LinearPdrKf(p, xy0=xy0)
        for t in range(T):
            c, s = np.cos(dth[t]), np.sin(dth[t])
            x = np.r_[x[:2] + steps[t] * x[2:], np.array([[c, -s], [s, c]]) @ x[2:]]
            x[2:] += rng.multivariate_normal(np.zeros(2), process_noise(p, steps[t])[2:, 2:])
            kf.predict(steps[t], dth[t])
            if t % 3 == 0:
                kf.update(Fix(0, x[:2] + 2.0 * rng.standard_normal(2), 4.0 * np.eye(2)))
            e = x - kf.x
            nees[k, t] = e @ np.linalg.solve(kf.P, e)
            in95.append(kf.mahalanobis(x[:2][None])[0] <= chi2.ppf(0.95, 2))
    m = float(nees.mean())
    lo, hi = chi2.ppf(0.005, 4 * runs * T) / (runs * T), chi2.ppf(0.995, 4 * runs * T) / (runs * T)
    # samples are correlated in time, so widen the chi-square band by a factor
    assert lo - 0.4 < m < hi + 0.4, (m, lo, hi)
    assert 0.92 < np.mean(in95) < 0.98


def test_online_equals_batch_and_state_restore():
    rng = np.random.default_rng(1)
    _, steps, dth, z, R = synthetic_walk(rng, n_epochs=100)
    p = LinearPdrParams()
    trk = filter_batch(p, steps, dth, z, R, xy0=np.zeros(2))
    kf = LinearPdrKf(p, xy0=np.zeros(2))
    saved = None
    for t in range(100):
        kf.predict(steps[t], dth[t])
        if np.isfinite(z[t, 0]):
            kf.update(Fix(0, z[t], R[t]))
        np.testing.assert_allclose(kf.x, trk.x_filt[t], atol=1e-9)
        np.testing.assert_allclose(kf.P, trk.P_filt[t], atol=1e-9)
        if t == 49:
            saved = kf.state.copy()
    kf2 = LinearPdrKf(p)
    kf2.state = saved
    for t in range(50, 100):
        kf2.predict(steps[t], dth[t])
        if np.isfinite(z[t, 0]):
            kf2.update(Fix(0, z[t], R[t]))
    np.testing.assert_allclose(kf2.x, kf.x, atol=1e-12)
    np.testing.assert_allclose(kf2.P, kf.P, atol=1e-12)


def test_rts_without_measurements_equals_forward():
    rng = np.random.default_rng(2)
    _, steps, dth, _, R = synthetic_walk(rng, n_epochs=60)
    z = np.full((60, 2), np.nan)
    trk = filter_batch(LinearPdrParams(), steps, dth, z, R, xy0=np.ones(2))
    xs, Ps = rts_smooth(trk)
    np.testing.assert_allclose(xs, trk.x_filt, atol=1e-9)
    np.testing.assert_allclose(Ps, trk.P_filt, atol=1e-7)


def test_joseph_form_keeps_covariance_symmetric_psd():
    rng = np.random.default_rng(3)
    kf = LinearPdrKf(LinearPdrParams(gate=False), xy0=np.zeros(2), pos_cov0=1e6 * np.eye(2))
    for _ in range(300):
        kf.predict(1.0, 0.3 * rng.standard_normal())
        kf.update(Fix(0, rng.standard_normal(2), 1e-8 * np.eye(2)))
        assert np.array_equal(kf.P, kf.P.T)
        assert np.linalg.eigvalsh(kf.P).min() > -1e-12


def test_gate_rejects_outlier_fix_and_counts_it():
    kf = LinearPdrKf(LinearPdrParams(), xy0=np.zeros(2), pos_cov0=np.eye(2))
    before = kf.x.copy()
    assert not kf.update(Fix(0, np.array([100.0, 0.0]), np.eye(2)))
    np.testing.assert_array_equal(kf.x, before)
    assert kf.state.n_rejected == 1 and kf.state.last_nis > 100
    assert kf.nis(Fix(0, np.array([1.0, 0.0]), np.eye(2))) == pytest.approx(0.5)
    assert not kf.update(Fix(0, np.zeros(2), np.eye(2), ok=False))
    ungated = LinearPdrKf(LinearPdrParams(gate=False), xy0=np.zeros(2), pos_cov0=np.eye(2))
    assert ungated.update(Fix(0, np.array([100.0, 0.0]), np.eye(2)))


def test_mahalanobis_of_candidate_points():
    kf = LinearPdrKf(LinearPdrParams(), xy0=np.array([1.0, 2.0]), pos_cov0=np.diag([4.0, 1.0]))
    d = kf.mahalanobis(np.array([[1.0, 2.0], [3.0, 2.0], [1.0, 4.0]]))
    np.testing.assert_allclose(d, [0.0, 1.0, 4.0])


def test_bad_params_and_inputs():
    with pytest.raises(ConfigError, match="gate_prob"):
        params_from_dict(LinearPdrParams, {"gate_prob": 1.5})
    with pytest.raises(ConfigError, match="unknown"):
        params_from_dict(LinearPdrParams, {"sigma": 1.0})
    kf = LinearPdrKf()
    with pytest.raises(InvalidInputError, match="steps"):
        kf.predict(-1.0, 0.0)
    with pytest.raises(InvalidInputError, match="finite"):
        kf.update(Fix(0, np.array([np.nan, 0.0]), np.eye(2)))
    with pytest.raises(InvalidInputError, match="T"):
        filter_batch(LinearPdrParams(), np.ones(3), np.zeros(2), np.zeros((3, 2)), np.zeros((3, 2, 2)))


def test_fixes_to_arrays_skips_missing_and_declined():
    z, R = fixes_to_arrays([None, Fix(0, np.ones(2), 2 * np.eye(2)), Fix(0, np.ones(2), np.eye(2), ok=False)])
    assert np.isnan(z[0]).all() and np.isnan(z[2]).all()
    np.testing.assert_array_equal(R[1], 2 * np.eye(2))


def test_ukf_captures_curvature_better_than_ekf():
    """One prediction from a known position with uncertain heading (Raitoharju et al. 2015, Fig. 2): the UKF's
    mean and covariance are closer to the exact moments than the EKF's."""
    p = NonlinearPdrParams(init_pos_var_m2=1e-6, init_heading_var_rad2=0.2, init_step_var_m2=1e-6,
                           sigma_dtheta_rad=0.0, sigma_ds_m=0.0)
    ekf, ukf = PdrEkf(p, xy0=np.zeros(2)), PdrUkf(p, xy0=np.zeros(2))
    ekf.predict(3.0, 0.0)
    ukf.predict(3.0, 0.0)
    a, v = 3.0 * 0.7, 0.2  # displacement and heading variance: exact moments of a (cos th, sin th)
    mean = np.array([a * np.exp(-v / 2), 0.0])
    cov = np.diag([a * a * ((1 + np.exp(-2 * v)) / 2 - np.exp(-v)), a * a * (1 - np.exp(-2 * v)) / 2])
    assert np.linalg.norm(ukf.position - mean) < 0.1 * np.linalg.norm(ekf.position - mean)
    assert np.linalg.norm(ukf.position_cov - cov) < 0.7 * np.linalg.norm(ekf.position_cov - cov)


@pytest.mark.parametrize("cls", [PdrEkf, PdrUkf])
def test_nonlinear_filters_on_the_synthetic_walk(cls):
    rng = np.random.default_rng(4)
    truth, steps, dth, z, R = synthetic_walk(rng)
    has = np.isfinite(z[:, 0]) & (np.arange(len(z)) >= 20)
    p = NonlinearPdrParams(init_heading_rad=0.3, init_heading_var_rad2=0.05, sigma_dtheta_rad=0.04,
                           sigma_ds_m=0.02)
    trk = run_filter(cls(p, xy0=z[0], pos_cov0=R[0]), steps, dth, z, R)
    xs, Ps = rts_smooth(trk)
    assert _err(trk.x_filt, truth, has) < _err(z, truth, has)
    assert _err(xs, truth, has) < _err(trk.x_filt, truth, has)
    assert np.all(np.linalg.eigvalsh(Ps).min(axis=1) > -1e-9)
    f = cls(p, xy0=np.zeros(2), pos_cov0=np.eye(2))
    assert f.nis(Fix(0, np.array([1.0, 0.0]), np.eye(2))) == pytest.approx(0.5)
    assert f.mahalanobis(np.array([[0.0, 2.0]]))[0] == pytest.approx(4.0)
    # the linear model wraps the same interface: run_filter == filter_batch
    lp = LinearPdrParams()
    a = run_filter(LinearPdrKf(lp, xy0=z[0], pos_cov0=R[0]), steps, dth, z, R)
    b = filter_batch(lp, steps, dth, z, R, xy0=z[0], pos_cov0=R[0])
    np.testing.assert_allclose(a.x_filt, b.x_filt, atol=1e-9)
