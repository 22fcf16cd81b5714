"""FFT stepometer and PDR core: oracle, online/batch, save/restore, synthetic walks, real-data regression."""
from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import dataset
from indoor_loc.errors import ConfigError, InvalidInputError
from indoor_loc.imu.pdr import HeadingHistory, Pdr, PdrParams, pdr_batch
from indoor_loc.measurements import pdr_intervals
from indoor_loc.imu.stepometer import Stepometer, filtfilt, lowpass_design, stepometer_batch, total_steps
from indoor_loc.imu.step_spectrum import (ACF_LAG_TOL, CANDIDATE_STEP_HZ, WindowDesign, amplitude_spectrum,
                                          analyse_windows, harmonic_score, normalised_autocorr, power_spectrum)
from indoor_loc.imu.stepometer_types import StepometerParams
from indoor_loc.params import params_from_dict

G = 9.81


def walk_signal(rng, *, cadence_hz=1.8, rate_hz=100.0, duration_s=60.0, jitter=0.2, stride_amp=0.5,
                step_amp=2.0, noise=0.1, tilt=True):
    """Synthetic walking accelerometer: |a| = g + stride (f/2) + step (f) + 2nd harmonic, irregular
    stamps (uniform jitter of ``jitter`` sample periods), the specific force split over a tilted axis."""
    n = int(duration_s * rate_hz)
    t = (np.arange(n) + rng.uniform(-jitter / 2, jitter / 2, n)) / rate_hz
    t.sort()
    ph = 2 * np.pi * cadence_hz * t
    mag = (G + stride_amp * np.sin(ph / 2 + 0.3) + step_amp * np.sin(ph) + 0.5 * np.sin(2 * ph + 1.0)
           + noise * rng.standard_normal(n))
    axis = np.array([0.3, 0.2, 0.93]) if tilt else np.array([0.0, 0.0, 1.0])
    axis = axis / np.linalg.norm(axis)
    acc = mag[:, None] * axis[None, :]
    stamps = (1_000_000_000 + np.round(t * 1e9)).astype(np.int64)
    return stamps, acc


# ---------------------------------------------------------------------------------------------
# oracle: spectrum and harmonic score against plain numpy
# ---------------------------------------------------------------------------------------------
def test_amplitude_spectrum_matches_plain_fft(rng):
    p = StepometerParams()
    d = WindowDesign.make(p, 100.0)
    w = rng.normal(G, 1.0, size=(3, d.n_w))
    ours = amplitude_spectrum(w, d)
    for i in range(3):
        x = (w[i] - w[i].mean()) * np.hanning(d.n_w + 2)[1:-1]
        padded = np.zeros(d.n_fft)
        padded[: d.n_w] = x
        plain = np.abs(np.fft.fft(padded))[: d.n_fft // 2 + 1] * 2 / np.hanning(d.n_w + 2)[1:-1].sum()
        np.testing.assert_allclose(ours[i], plain, rtol=1e-9, atol=1e-12)



@pytest.mark.parametrize("rate_hz", [100.0, 222.5])
def test_blocked_power_spectrum_and_fast_autocorr_equal_the_direct_formulation(rng, rate_hz):
    """The blocked, truncated power spectrum and the autocorrelation at a fast FFT length give what the
    plain formulation gives (full-length |rfft|², autocorrelation zero-padded to exactly 2 n_w; the fast one
    holds the lags the analysis reads), on a
    number of windows that is not a multiple of the FFT block."""
    d = WindowDesign.make(StepometerParams(), rate_hz)
    n = 37
    t = np.arange(d.n_w) / rate_hz
    w = G + 2.0 * np.sin(2 * np.pi * 1.8 * t)[None, :] + rng.normal(0.0, 0.5, size=(n, d.n_w))
    x = w - w.mean(axis=1, keepdims=True)
    taper = np.hanning(d.n_w + 2)[1:-1]
    direct = (np.abs(np.fft.rfft(x * taper, d.n_fft, axis=1)) * (2.0 / taper.sum())) ** 2
    ours = power_spectrum(x, d)
    assert ours.shape == (n, d.n_bins)
    # every bin the analysis reads is inside the computed range
    assert d.i0.max() + 1 < d.n_bins and int(np.floor(d.cand[0] * d.n_fft / d.fs)) < d.n_bins
    np.testing.assert_allclose(ours, direct[:, : d.n_bins], rtol=1e-9, atol=1e-9 * direct.max())
    np.testing.assert_allclose(power_spectrum(x, d, d.n_fft // 2 + 1), direct, rtol=1e-9, atol=1e-9 * direct.max())
    spec = np.fft.rfft(x, 2 * d.n_w, axis=1)
    acf = np.fft.irfft(np.abs(spec) ** 2, 2 * d.n_w, axis=1)[:, : d.n_w] / (d.n_w - np.arange(d.n_w))
    # the shorter FFT holds every lag the analysis reads: up to the stride lag of the lowest candidate
    assert d.n_lags >= np.ceil(2.0 * rate_hz / d.cand[0] * (1 + ACF_LAG_TOL)) + 1 and d.n_acf < 2 * d.n_w - 1
    np.testing.assert_allclose(normalised_autocorr(x, d), (acf / acf[:, :1])[:, : d.n_lags], rtol=1e-9, atol=1e-9)
    with pytest.raises(InvalidInputError):
        normalised_autocorr(x, d, 0, d.n_lags + 1)      # those lags would wrap around
    lag = int(round(rate_hz / 1.8))
    plain = np.dot(x[0, :-lag], x[0, lag:]) / (d.n_w - lag) / (np.dot(x[0], x[0]) / d.n_w)
    assert normalised_autocorr(x[:1], d)[0, lag] == pytest.approx(plain, rel=1e-9)


def test_harmonic_score_matches_explicit_sum(rng):
    p = StepometerParams()
    d = WindowDesign.make(p, 100.0)
    power = amplitude_spectrum(rng.normal(G, 1.0, size=(2, d.n_w)), d) ** 2
    score = harmonic_score(power, d)
    freqs = np.arange(power.shape[1]) * d.fs / d.n_fft
    for c in (0, len(d.cand) // 3, len(d.cand) - 1):
        f = d.cand[c]
        expected = sum((p.odd_harmonic_weight if k % 2 else 1.0) * np.interp(k * f / 2, freqs, power[1])
                       for k in range(1, p.harmonics + 1))
        assert score[1, c] == pytest.approx(expected, rel=1e-9)


@pytest.mark.parametrize("f_true", [1.37, 1.62, 1.81, 2.13])
def test_refined_frequency_beats_the_plain_fft_bin(f_true, rng):
    """A pure step tone: the refined estimate is within 0.01 Hz; plain np.fft's largest bin of the
    same window is only good to half a bin (0.13 Hz at 3.84 s)."""
    p = StepometerParams()
    d = WindowDesign.make(p, 100.0)
    t = np.arange(d.n_w) / 100.0
    x = G + 1.5 * np.sin(2 * np.pi * f_true * t + 0.7) + 0.02 * rng.standard_normal(d.n_w)
    est = analyse_windows(x[None, :], d, p)[0]
    assert est.walking
    assert abs(est.freq_hz - f_true) < 0.01
    plain = np.fft.rfftfreq(d.n_w, 0.01)[np.argmax(np.abs(np.fft.rfft(x - x.mean())))]
    assert abs(plain - f_true) <= 0.5 * 100.0 / d.n_w + 1e-9
    assert CANDIDATE_STEP_HZ < 100.0 / d.n_w


def test_stride_dominated_spectrum_counts_the_cadence(rng):
    """Phone on one leg: the largest peak is the stride (f/2) and 3f/2; the step frequency is f."""
    p = StepometerParams()
    d = WindowDesign.make(p, 100.0)
    t = np.arange(d.n_w) / 100.0
    f = 1.75
    x = (G + 3.0 * np.sin(np.pi * f * t) + 2.5 * np.sin(3 * np.pi * f * t + 0.4) + 1.0 * np.sin(2 * np.pi * f * t)
         + 0.05 * rng.standard_normal(d.n_w))
    spec = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(d.n_w), 8192))
    assert abs(np.fft.rfftfreq(8192, 0.01)[np.argmax(spec)] - f) > 0.5     # plain peak is not the cadence
    est = analyse_windows(x[None, :], d, p)[0]
    assert est.walking and abs(est.freq_hz - f) < 0.02


# ---------------------------------------------------------------------------------------------
# online / batch / state
# ---------------------------------------------------------------------------------------------
def test_online_equals_batch(rng):
    stamps, acc = walk_signal(rng, duration_s=40.0, rate_hz=97.0)
    batch = stepometer_batch(stamps, acc)
    s = Stepometer()
    online = []
    for t, a in zip(stamps, acc):
        online += s.update(int(t), a)
    online += s.finish()
    assert len(online) == len(batch) > 50
    assert [(h.t_start_ns, h.t_end_ns, h.walking) for h in online] == [(h.t_start_ns, h.t_end_ns, h.walking) for h in batch]
    np.testing.assert_allclose([h.steps for h in online], [h.steps for h in batch], rtol=1e-9, atol=1e-12)
    # hops tile the time axis without gaps or overlaps
    assert all(a.t_end_ns == b.t_start_ns for a, b in zip(batch, batch[1:]))
    assert batch[0].t_start_ns == stamps[0]


def test_whole_recording_at_once_equals_sample_by_sample_and_small_chunks(rng):
    """The batch path (a whole recording in one call: the rate is estimated inside the chunk) gives the
    hops of the per-sample online path and of small chunks (the rate estimate spanning calls) — the same
    hop bounds, walking flags and confidences, counts to 1e-12 — across a walk, an irregular stop, a
    still phone, a gap and a second walk."""
    s1, a1, _ = walk_turn_walk(rng, turn_s=2.0, resume=False)
    s2, a2 = walk_signal(rng, duration_s=25.0, rate_hz=100.0)
    stamps = np.concatenate((s1, s2 - s2[0] + s1[-1] + 3 * 10**9))
    acc = np.concatenate((a1, a2))
    batch = stepometer_batch(stamps, acc)
    one = Stepometer()
    online = [h for t, a in zip(stamps, acc) for h in one.update(int(t), a)] + one.finish()
    small = Stepometer()
    chunks = [h for k in range(0, len(stamps), 7) for h in small.update_many(stamps[k: k + 7], acc[k: k + 7])]
    chunks += small.finish()
    fixed = stepometer_batch(stamps, acc, StepometerParams(grid_hz=100.0))     # no rate estimate at all
    assert one.rate_hz == small.rate_hz == 100.0                              # stamps exactly 10 ms apart
    assert sum(h.steps for h in batch) > 60
    for other in (online, chunks, fixed):
        assert [(h.t_start_ns, h.t_end_ns, h.walking, h.confidence) for h in other] == \
            [(h.t_start_ns, h.t_end_ns, h.walking, h.confidence) for h in batch]
        np.testing.assert_allclose([h.steps for h in other], [h.steps for h in batch], rtol=0, atol=1e-12)
        np.testing.assert_allclose([h.steps_std for h in other], [h.steps_std for h in batch], rtol=0, atol=1e-12)


def test_save_restore_resumes_exactly(rng):
    stamps, acc = walk_signal(rng, duration_s=30.0)
    ref = Stepometer()
    full = ref.update_many(stamps[:1000], acc[:1000]) + ref.update_many(stamps[1000:], acc[1000:]) + ref.finish()
    a = Stepometer()
    first = a.update_many(stamps[:1000], acc[:1000])
    saved = a.state()
    a.update_many(stamps[1000:1500], acc[1000:1500])          # advancing `a` must not touch `saved`
    b = Stepometer()
    b.set_state(saved)
    second = b.update_many(stamps[1000:], acc[1000:]) + b.finish()
    assert first + second == full
    assert b.total_steps == pytest.approx(ref.total_steps, rel=1e-12)


@pytest.mark.parametrize("rate_hz", [50.0, 100.0, 200.0, 400.0])
@pytest.mark.parametrize("cadence_hz", [1.4, 1.8, 2.1])
def test_synthetic_walk_step_count(rate_hz, cadence_hz, rng):
    duration = 60.0
    stamps, acc = walk_signal(rng, cadence_hz=cadence_hz, rate_hz=rate_hz, duration_s=duration)
    steps = total_steps(stepometer_batch(stamps, acc))
    expected = cadence_hz * (stamps[-1] - stamps[0]) * 1e-9
    assert steps == pytest.approx(expected, rel=0.01)


def test_stride_dominated_walk_step_count(rng):
    stamps, acc = walk_signal(rng, cadence_hz=1.7, stride_amp=3.0, step_amp=0.8, duration_s=60.0)
    steps = total_steps(stepometer_batch(stamps, acc))
    assert steps == pytest.approx(1.7 * (stamps[-1] - stamps[0]) * 1e-9, rel=0.01)


def test_stationary_gives_zero_steps(rng):
    n = 6000
    stamps = 10**9 + np.arange(n, dtype=np.int64) * 10_000_000
    acc = np.array([0.5, -0.3, 9.79]) + 0.03 * rng.standard_normal((n, 3))
    hops = stepometer_batch(stamps, acc)
    assert len(hops) > 100 and total_steps(hops) == 0.0 and not any(h.walking for h in hops)


def test_walk_stop_walk_with_gap(rng):
    """Walking, a 5 s hole in the data (segment restart), walking again: both bouts counted."""
    s1, a1 = walk_signal(rng, duration_s=20.0, cadence_hz=1.8)
    s2, a2 = walk_signal(rng, duration_s=20.0, cadence_hz=1.6)
    s2 = s2 - s2[0] + s1[-1] + 5 * 10**9
    steps = total_steps(stepometer_batch(np.concatenate([s1, s2]), np.vstack([a1, a2])))
    expected = 1.8 * (s1[-1] - s1[0]) * 1e-9 + 1.6 * (s2[-1] - s2[0]) * 1e-9
    assert steps == pytest.approx(expected, rel=0.02)


def test_bad_samples_raise_and_leave_state_untouched(rng):
    stamps, acc = walk_signal(rng, duration_s=10.0)
    s = Stepometer()
    s.update_many(stamps[:600], acc[:600])
    before = s.state()
    with pytest.raises(InvalidInputError) as e1:
        s.update(int(stamps[600]), [np.nan, 0.0, 9.8])
    assert e1.value.reason == "nan"
    with pytest.raises(InvalidInputError) as e2:
        s.update(int(stamps[100]), acc[100])
    assert e2.value.reason == "non_monotonic_stamp"
    with pytest.raises(InvalidInputError):
        s.update_many(stamps[600:610], np.vstack([acc[600:609], [np.inf, 0, 0]]))
    after = s.state()
    assert after.buffer == before.buffer and after.n_grid == before.n_grid and after.last_t_ns == before.last_t_ns


@pytest.mark.parametrize("bad", [{"window_s": 0.0}, {"hop_s": 10.0}, {"f_min_hz": 1.0, "f_max_hz": 2.5},
                                 {"harmonics": 0}, {"search_margin": 1.5}, {"grid_hz": 5.0},
                                 {"odd_harmonic_weight": 2.0}])
def test_invalid_params(bad):
    with pytest.raises(ConfigError, match="StepometerParams"):
        params_from_dict(StepometerParams, bad)


# ---------------------------------------------------------------------------------------------
# PDR
# ---------------------------------------------------------------------------------------------
def test_pdr_contract_recovers_steps_and_heading_change(rng):
    n = 40
    t0 = 10**9 + np.arange(n, dtype=np.int64) * 320_000_000
    steps = rng.uniform(0.0, 0.7, n)
    yaw = np.cumsum(rng.normal(0, 0.3, n))
    poses = pdr_batch(t0, t0 + 320_000_000, steps, yaw, np.full(n, 0.01), PdrParams(step_length_m=0.7))
    xy = np.array([[0.0, 0.0]] + [[p.x, p.y] for p in poses])
    yaws = np.array([poses[0].yaw] + [p.yaw for p in poses])
    iv = pdr_intervals(np.arange(len(xy)), xy, yaws, step_length_m=0.7)
    rec_steps, rec_dpsi = iv.steps, iv.dtheta
    np.testing.assert_allclose(rec_steps, steps, atol=1e-9)
    np.testing.assert_allclose(rec_dpsi[1:], (np.diff(yaw) + np.pi) % (2 * np.pi) - np.pi, atol=1e-9)
    # speed and yaw rate as documented; covariance grows with distance
    assert poses[5].speed == pytest.approx(steps[5] * 0.7 / 0.32)
    assert np.all(np.diff([np.trace(p.cov[:2, :2]) for p in poses]) >= 0)
    assert all(np.allclose(p.cov, p.cov.T) and np.all(np.linalg.eigvalsh(p.cov) >= -1e-12) for p in poses)


def test_pdr_unknown_heading():
    pdr = Pdr()
    for i in range(10):
        pose = pdr.update(i * 10**9, (i + 1) * 10**9, 2.0, None)
    assert pose.cov[2, 2] == 1e6 and pose.x == pytest.approx(10 * 2 * 0.65) and pose.y == 0.0
    # position uncertainty is bounded by the distance walked, not by the huge yaw variance
    assert np.sqrt(np.trace(pose.cov[:2, :2])) < 2 * 13.0


def test_heading_history_interpolates_across_wrap():
    h = HeadingHistory(horizon_s=5.0)
    h.add(0, math.pi - 0.1, 0.01)
    h.add(1_000_000_000, -math.pi + 0.1, 0.02)
    yaw, var = h.at(500_000_000)
    assert abs(abs(yaw) - math.pi) < 1e-9 and var == 0.02


# ---------------------------------------------------------------------------------------------
# real data
# ---------------------------------------------------------------------------------------------
#: The bar on the 12 validation walks (``indoor-loc bench steps``: median 0.44 %, worst 0.91 % since
#: the last steps of a stop are counted; 0.58 % / 1.05 % with the first FFT stepometer).
OXFORD_MEDIAN_PCT = 0.58
OXFORD_WORST_PCT = 1.05


def test_oxford_step_count_regression():
    from indoor_loc.bench.imu import load_oxford, oxford_traces
    root = dataset("oxford_steps")
    errs = []
    for path in oxford_traces(root.parent):
        tr = load_oxford(path)
        gt = tr["gt"][-1] - tr["gt"][0]
        errs.append(100 * (total_steps(stepometer_batch(tr["stamps_ns"], tr["acc"])) - gt) / gt)
    assert len(errs) == 12
    errs = np.abs(errs)
    assert np.median(errs) <= OXFORD_MEDIAN_PCT
    assert errs.max() <= OXFORD_WORST_PCT


# ---------------------------------------------------------------------------------------------
# synthetic gaits across cadences, carry positions, floors and phones (known step counts)
# ---------------------------------------------------------------------------------------------
def bursty_stamps(rng, rate_hz, duration_s):
    """Android-style delivery: nominal period with ±30 % jitter, and every ~2 s a 60 ms stall
    followed by the delayed samples stamped close together (batched FIFO reads)."""
    dt = rng.uniform(0.7, 1.3, int(duration_s * rate_hz * 1.2)) / rate_hz
    stall = rng.random(len(dt)) < 1.0 / (2.0 * rate_hz)
    dt[stall] += 0.06
    t = np.cumsum(dt)
    t = t[t < duration_s]
    return (1_000_000_000 + np.round(t * 1e9)).astype(np.int64)


def gait(rng, stamps, *, cadence_hz, step_amp=2.0, stride_amp=0.5, harm_amp=0.5, noise=0.1):
    """|a| = g + stride (f/2) + step (f) + 2nd step harmonic + white noise at ``stamps``, over a
    tilted axis; the true step count is cadence x duration."""
    t = (stamps - stamps[0]) * 1e-9
    ph = 2 * np.pi * cadence_hz * t
    mag = (G + stride_amp * np.sin(ph / 2 + 0.3) + step_amp * np.sin(ph) + harm_amp * np.sin(2 * ph + 1.0)
           + noise * rng.standard_normal(len(t)))
    axis = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])
    return mag[:, None] * axis[None, :]


def true_count(stamps, cadence_hz):
    return cadence_hz * (stamps[-1] - stamps[0]) * 1e-9


@pytest.mark.parametrize("rate_hz", [50.0, 100.0, 200.0])
@pytest.mark.parametrize("cadence_hz", [1.4, 1.7, 2.0, 2.2, 2.4])
def test_cadences_and_rates_with_bursty_stamps(cadence_hz, rate_hz, rng):
    stamps = bursty_stamps(rng, rate_hz, 45.0)
    hops = stepometer_batch(stamps, gait(rng, stamps, cadence_hz=cadence_hz))
    assert total_steps(hops) == pytest.approx(true_count(stamps, cadence_hz), rel=0.01)
    assert all(h.confidence == 1.0 and h.steps_std == 0.0 for h in hops)


@pytest.mark.parametrize("rate_hz", [50.0, 100.0, 200.0])
@pytest.mark.parametrize("cadence_hz", [1.4, 1.9, 2.4])
def test_swinging_arm_stride_harmonic_stronger_than_step(cadence_hz, rate_hz, rng):
    """A swinging arm or a purse: the stride (f/2) carries 4x the step harmonic's amplitude."""
    stamps = bursty_stamps(rng, rate_hz, 45.0)
    acc = gait(rng, stamps, cadence_hz=cadence_hz, stride_amp=3.2, step_amp=0.8, harm_amp=0.3)
    assert total_steps(stepometer_batch(stamps, acc)) == pytest.approx(true_count(stamps, cadence_hz), rel=0.01)


@pytest.mark.parametrize("rate_hz", [50.0, 100.0, 200.0])
def test_soft_floor_low_amplitude_gait(rate_hz, rng):
    """Carpet, phone in hand: |a| varies by ~0.25 m/s² std (the old 0.5 m/s² gate counted nothing)."""
    stamps = bursty_stamps(rng, rate_hz, 45.0)
    acc = gait(rng, stamps, cadence_hz=1.6, step_amp=0.3, stride_amp=0.1, harm_amp=0.1, noise=0.04)
    expected = true_count(stamps, 1.6)
    assert total_steps(stepometer_batch(stamps, acc)) == pytest.approx(expected, rel=0.01)
    assert total_steps(stepometer_batch(stamps, acc, StepometerParams(min_std_m_s2=0.5))) < 0.1 * expected


def test_sway_and_vibration_are_not_walking(rng):
    """A 0.5 Hz sway and a 7 Hz vibration (a vehicle, a machine) are not counted as walking. (Between
    them the spectrum alone is ambiguous: 0.8 Hz with harmonics is also a 1.6 Hz swinging-arm gait.)"""
    stamps = bursty_stamps(rng, 100.0, 30.0)
    t = (stamps - stamps[0]) * 1e-9
    for f in (0.5, 7.0):
        mag = G + 1.5 * np.sin(2 * np.pi * f * t) + 0.05 * rng.standard_normal(len(t))
        acc = mag[:, None] * np.array([0.0, 0.0, 1.0])[None, :]
        assert total_steps(stepometer_batch(stamps, acc)) == 0.0


def standing_then_walking(rng, stand_s=3.0, walk_s=30.0, rate_hz=100.0):
    n_s, n_w = int(stand_s * rate_hz), int(walk_s * rate_hz)
    stamps = 10**9 + np.round(np.arange(n_s + n_w) * 1e9 / rate_hz).astype(np.int64)
    acc = np.tile([0.4, 0.2, 9.79], (n_s + n_w, 1)) + 0.02 * rng.standard_normal((n_s + n_w, 3))
    acc[n_s:] = gait(rng, stamps[n_s:], cadence_hz=1.8)
    return stamps, acc, true_count(stamps[n_s:], 1.8)


def test_standing_before_the_walk_is_not_counted(rng):
    stamps, acc, expected = standing_then_walking(rng)
    hops = stepometer_batch(stamps, acc)
    assert total_steps(hops) == pytest.approx(expected, abs=1.0)
    assert sum(h.steps for h in hops if h.t_end_ns <= stamps[0] + 2_500_000_000) == 0.0


def aperiodic_motion(rng, stamps, std=1.5):
    """Handling the phone: band-limited random |a| (no gait periodicity)."""
    from scipy.signal import butter, sosfilt
    fs = 1e9 / np.median(np.diff(stamps))
    x = sosfilt(butter(2, [0.5, 4.0], btype="band", fs=fs, output="sos"), rng.standard_normal(len(stamps)))
    mag = G + std * x / x.std()
    return mag[:, None] * np.array([0.0, 0.0, 1.0])[None, :]


def test_moving_but_not_walking_is_flagged_not_dropped_silently(rng):
    """Aperiodic handling (band-limited noise, 30 s): most hops count no steps and say they are
    unsure (confidence < 1, count standard deviation > 0) — some windows of random motion do look
    periodic by chance, and the unsure hops that count steps are only those coasted right after such
    a window (as the last steps of a stop); a still phone: no steps with confidence 1."""
    stamps = 10**9 + np.arange(3000, dtype=np.int64) * 10_000_000
    hops = stepometer_batch(stamps, aperiodic_motion(rng, stamps))
    unsure = [h for h in hops if h.confidence < 1.0]
    assert total_steps(hops) < 0.4 * 1.8 * 30.0
    assert len(unsure) > 0.5 * len(hops)
    assert all(h.confidence == 0.5 and h.steps_std > 0 for h in unsure)
    for prev, h in zip(hops, hops[1:]):
        if h.confidence < 1.0 and h.steps > 0:
            assert prev.steps > 0 and prev.t_end_ns == h.t_start_ns
    assert sum(h.steps > 0 for h in unsure) < 0.1 * len(unsure)
    still = stepometer_batch(stamps, np.tile([0.0, 0.0, G], (len(stamps), 1)) + 0.01 * rng.standard_normal((len(stamps), 3)))
    assert all(h.confidence == 1.0 and h.steps == 0.0 and h.steps_std == 0.0 for h in still)


def test_coasting_counts_through_a_short_aperiodic_spell(rng):
    """Walk, 2 s of aperiodic motion (a turn with the bag bumping), walk: with coast_s the spell is
    counted at the last cadence with reduced confidence; without (and without bridging), it is left out
    (and flagged)."""
    rate = 100.0
    stamps = 10**9 + np.round(np.arange(int(40 * rate)) * 1e9 / rate).astype(np.int64)
    acc = gait(rng, stamps, cadence_hz=1.8)
    spell = (stamps >= stamps[0] + 20 * 10**9) & (stamps < stamps[0] + 22 * 10**9)
    acc[spell] = aperiodic_motion(rng, stamps[spell], std=2.0)
    truth = true_count(stamps, 1.8)
    off = stepometer_batch(stamps, acc, StepometerParams(bridge_s=0.0, coast_s=0.0))
    on = stepometer_batch(stamps, acc, StepometerParams(coast_s=4.0, bridge_s=0.0))
    assert total_steps(on) == pytest.approx(truth, rel=0.02)
    assert total_steps(off) < total_steps(on) - 2.0
    assert any(h.confidence == 0.5 and h.steps > 0 for h in on)
    assert any(h.confidence == 0.5 and h.steps == 0 for h in off)


def test_online_equals_batch_and_resumes_with_gates_and_coasting(rng):
    p = StepometerParams(coast_s=3.0)
    s1, a1, _ = standing_then_walking(rng, walk_s=20.0)
    a1[1500:1700] = aperiodic_motion(rng, s1[1500:1700])
    batch = stepometer_batch(s1, a1, p)
    st = Stepometer(p)
    online = []
    for i, (t, a) in enumerate(zip(s1, a1)):
        if i == 1200:                          # save and resume on a fresh object
            saved = st.state()
            st = Stepometer(p)
            st.set_state(saved)
        online += st.update(int(t), a)
    online += st.finish()
    assert online == batch
    assert all(a.t_end_ns == b.t_start_ns for a, b in zip(batch, batch[1:]))


def test_pdr_step_uncertainty_grows_along_track_variance_and_speed_variance():
    sure = Pdr(PdrParams(step_length_m=0.7, step_length_rel_std=0.1))
    unsure = Pdr(PdrParams(step_length_m=0.7, step_length_rel_std=0.1))
    a = sure.update(0, 320_000_000, 0.6, 0.0, 0.0)
    b = unsure.update(0, 320_000_000, 0.6, 0.0, 0.0, steps_std=0.3)
    assert (a.x, a.y) == (b.x, b.y)
    assert a.cov[0, 0] == pytest.approx((0.1 * 0.42) ** 2)
    assert b.cov[0, 0] == pytest.approx((0.1 * 0.42) ** 2 + (0.7 * 0.3) ** 2)
    assert b.speed_var == pytest.approx(b.cov[0, 0] / 0.32 ** 2)
    # the consumer's recovery of the count's standard deviation (message contract, docs/nodes.md)
    dt = 0.32
    rec = math.sqrt(b.speed_var * dt * dt - (0.1 * 0.42) ** 2) / 0.7
    assert rec == pytest.approx(0.3)


def test_turn_coasting_counts_a_corridor_turn_only_with_a_turning_heading(rng):
    """Walk, a 2.5 s turn whose |a| loses its periodicity, walk. With turn_coast_s and a heading that
    swings by 90° during the spell the turn is counted (confidence 0.5); with a straight heading or
    none it is not (bridging off). Online (headings interleaved) = batch."""
    rate = 100.0
    stamps = 10**9 + np.round(np.arange(int(40 * rate)) * 1e9 / rate).astype(np.int64)
    acc = gait(rng, stamps, cadence_hz=1.8)
    t = (stamps - stamps[0]) * 1e-9
    spell = (t >= 20.0) & (t < 22.5)
    acc[spell] = aperiodic_motion(rng, stamps[spell], std=2.0)
    hs = stamps[::5]
    turn = np.clip((t[::5] - 20.0) / 2.5, 0.0, 1.0) * (np.pi / 2)
    p = StepometerParams(turn_coast_s=4.0, bridge_s=0.0, coast_s=0.0)
    truth = true_count(stamps, 1.8)
    turned = stepometer_batch(stamps, acc, p, heading_stamps_ns=hs, heading_rad=turn)
    straight = stepometer_batch(stamps, acc, p, heading_stamps_ns=hs, heading_rad=np.zeros(len(hs)))
    none = stepometer_batch(stamps, acc, p)
    assert total_steps(turned) == pytest.approx(truth, rel=0.02)
    assert total_steps(straight) == total_steps(none) < total_steps(turned) - 2.0
    assert any(h.confidence == 0.5 and h.steps > 0 for h in turned)
    s = Stepometer(p)
    online, k = [], 0
    for i in range(len(stamps)):
        while k < len(hs) and hs[k] <= stamps[i]:
            s.add_heading(int(hs[k]), float(turn[k]))
            k += 1
        online += s.update(int(stamps[i]), acc[i])
    assert online + s.finish() == turned


def walk_turn_walk(rng, *, turn_s=3.0, rate_hz=100.0, resume=True):
    """Walk 20 s at 1.8 Hz, then ``turn_s`` of irregular steps (intervals 0.4-0.75 s, impacts of
    random height: a corridor turn, periodicity lost), then 20 s more walking (or, with ``resume``
    False, standing still). Returns stamps, acc and the true step count."""
    n = int((40.0 + turn_s) * rate_hz)
    stamps = 10**9 + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    t = (stamps - stamps[0]) * 1e-9
    acc = gait(rng, stamps, cadence_hz=1.8)
    spell = (t >= 20.0) & (t < 20.0 + turn_s)
    steps, k = [], 20.0 + 0.2
    while k < 20.0 + turn_s - 0.2:
        steps.append(k)
        k += rng.uniform(0.4, 0.75)
    mag = G + 0.2 * rng.standard_normal(int(spell.sum()))
    for s in steps:
        mag += rng.uniform(1.5, 3.0) * np.exp(-0.5 * ((t[spell] - s) / 0.06) ** 2)
    acc[spell] = mag[:, None] * np.array([0.0, 0.0, 1.0])[None, :]
    after = t >= 20.0 + turn_s
    truth = true_count(stamps[: int(20.0 * rate_hz)], 1.8) + len(steps)
    if resume:
        truth += true_count(stamps[after], 1.8)
    else:
        acc[after] = np.array([0.0, 0.0, G]) + 0.01 * rng.standard_normal((int(after.sum()), 3))
    return stamps, acc, truth


def test_bridge_counts_the_steps_of_a_turn_between_two_walking_spans(rng):
    """The turn's windows are not periodic; the gait resumes, so the held span is counted step by
    step (confidence 0.5). Without bridging those steps are lost."""
    stamps, acc, truth = walk_turn_walk(rng)
    on = stepometer_batch(stamps, acc)
    off = stepometer_batch(stamps, acc, StepometerParams(bridge_s=0.0))
    assert total_steps(on) == pytest.approx(truth, abs=1.5)
    assert total_steps(off) < total_steps(on) - 2.0
    assert any(h.confidence == 0.5 and h.steps > 0 for h in on)
    assert all(a.t_end_ns == b.t_start_ns for a, b in zip(on, on[1:]))


def test_bridge_does_not_count_handling_after_the_last_walk(rng):
    """Walk, then handling (aperiodic motion) and a still phone: the gait never resumes, so the held
    hops stay as they were judged on their own — the same count as without bridging. The walk is
    counted to its end; of the 3 s of handling only windows of random motion that look periodic by
    chance count (less than half of what walking would)."""
    stamps, acc, _ = walk_turn_walk(rng, resume=False)
    t = (stamps - stamps[0]) * 1e-9
    spell = (t >= 20.0) & (t < 23.0)
    acc[spell] = aperiodic_motion(rng, stamps[spell], std=2.0)
    on = stepometer_batch(stamps, acc)
    off = stepometer_batch(stamps, acc, StepometerParams(bridge_s=0.0))
    assert total_steps(on) == total_steps(off)
    end_ns = stamps[0] + 20 * 10**9 + 10**6
    assert sum(h.steps for h in on if h.t_end_ns <= end_ns) == pytest.approx(1.8 * 20.0, abs=1.0)
    assert sum(h.steps for h in on if h.t_end_ns > end_ns) < 0.5 * 1.8 * 3.0


def test_bridge_online_equals_batch_with_save_restore_inside_the_held_span(rng):
    stamps, acc, _ = walk_turn_walk(rng)
    batch = stepometer_batch(stamps, acc)
    st = Stepometer()
    online = []
    for i, (t, a) in enumerate(zip(stamps, acc)):
        if i == 2500:                          # 25 s: the turn's hops (about 2 s back) are held
            saved = st.state()
            assert saved.held
            st = Stepometer()
            st.set_state(saved)
        online += st.update(int(t), a)
    online += st.finish()
    assert online == batch


def handling_then_walk(rng, rate_hz=100.0):
    """The phone is picked up and put on (3 s of handling: random motion plus a few jiggles at
    1.5 Hz, which the first window finds marginally periodic), then lies still until 8 s, then a
    32-s walk at 1.8 Hz. Returns stamps, acc and the true step count (the walk's)."""
    n = int(40 * rate_hz)
    stamps = 10**9 + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    t = (stamps - stamps[0]) * 1e-9
    acc = np.array([0.0, 0.0, G]) + 0.01 * rng.standard_normal((n, 3))
    h = t < 3.0
    jig = aperiodic_motion(rng, stamps[h], std=1.0)
    jig[:, 2] += 1.5 * np.sin(2 * np.pi * 1.5 * t[h]) * np.hanning(int(h.sum()))
    acc[h] = jig
    w = t >= 8.0
    acc[w] = gait(rng, stamps[w], cadence_hz=1.8)
    return stamps, acc, true_count(stamps[w], 1.8)


def test_handling_before_the_walk_is_not_counted():
    """A walking run that never becomes clearly periodic (handling at the start of the recording,
    passing the periodicity test for a window or two) counts no steps: the count is the walk's.
    Without holding such runs back (bridge_s = 0) the head of the recording gets the first window's
    cadence."""
    stamps, acc, truth = handling_then_walk(np.random.default_rng(1))
    on = stepometer_batch(stamps, acc)
    off = stepometer_batch(stamps, acc, StepometerParams(bridge_s=0.0))
    assert total_steps(on) == pytest.approx(truth, abs=1.5)
    assert total_steps(off) > total_steps(on) + 2.0
    early = [h for h in on if h.t_end_ns <= stamps[0] + 6_000_000_000]
    assert early and all(h.steps == 0.0 for h in early)
    assert any(h.confidence == 0.5 and h.steps_std > 0 for h in early)      # flagged, not dropped
    assert all(a.t_end_ns == b.t_start_ns for a, b in zip(on, on[1:]))


def test_tentative_run_online_equals_batch_with_save_restore_inside_it():
    stamps, acc, _ = handling_then_walk(np.random.default_rng(1))
    batch = stepometer_batch(stamps, acc)
    st = Stepometer()
    online = []
    saved_inside = False
    for t, a in zip(stamps, acc):
        if not saved_inside and st.state().tentative:
            saved = st.state()
            st = Stepometer()
            st.set_state(saved)
            saved_inside = True
        online += st.update(int(t), a)
    online += st.finish()
    assert saved_inside
    assert online == batch


@pytest.mark.parametrize("rate_hz", [25.0, 100.0, 177.3, 400.0])
def test_filtfilt_with_cached_initial_conditions_is_scipys_sosfiltfilt(rate_hz, rng):
    """The bridged span's zero-phase low-pass: scipy's ``sosfiltfilt`` bit for bit, from the shortest
    signal it takes (one sample more than the odd extension) up."""
    from scipy.signal import sosfiltfilt
    lp = lowpass_design(4, min(3.0, 0.45 * rate_hz), rate_hz)
    assert lp.pad == 15
    for n in (lp.pad + 1, lp.pad + 2, 64, 1000):
        x = rng.standard_normal(n) + 5.0
        assert filtfilt(lp, x).tobytes() == sosfiltfilt(lp.sos.copy(), x).tobytes()
