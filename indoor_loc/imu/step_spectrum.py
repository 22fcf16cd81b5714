"""The stepometer's spectral core (pure, vectorised over windows): the analysis design of a sampling
rate, the low-pass and spectra of windows of |a|, the harmonic sum, the stride-lag autocorrelation and
the walking decision of each window (:mod:`indoor_loc.imu.stepometer` describes the method)."""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike
from scipy.fft import next_fast_len
from scipy.signal import butter, sosfilt, sosfilt_zi
from scipy.sparse import csr_array

from indoor_loc.errors import InvalidInputError
from indoor_loc.imu.stepometer_types import StepometerParams

#: Resolution of the candidate step-frequency grid before parabolic refinement, Hz.
CANDIDATE_STEP_HZ = 0.005
#: Half width of the stride-lag search for the periodicity check, relative to ``2/f``.
ACF_LAG_TOL = 0.15


class WindowEstimate(NamedTuple):
    """Spectral analysis of one window: refined step frequency (Hz), periodic-walking decision, the
    stride-lag autocorrelation (1), the standard deviation of |a| over the window and over the
    ``motion_window_s`` centred on the window's counted hop (m/s²)."""
    freq_hz: float
    walking: bool
    autocorr: float
    std_m_s2: float
    motion_std_m_s2: float = 0.0


@dataclass(frozen=True)
class WindowDesign:
    """Coefficients derived once per (params, grid rate)."""
    fs: float
    n_w: int
    n_h: int
    offset: int              # first grid index of the hop counted by window 0
    n_fft: int
    n_bins: int              # spectrum bins the analysis reads: [0, n_bins)
    n_lags: int              # autocorrelation lags the analysis reads: [0, n_lags) (<= n_w)
    n_acf: int               # FFT length of the linear autocorrelation (>= n_w + n_lags - 1, a fast size)
    taper: np.ndarray        # (n_w,)
    scale: float             # 2 / sum(taper): one-sided sinusoid amplitude
    cand: np.ndarray         # (C,) candidate step frequencies, Hz
    i0: np.ndarray           # (H, C) lower FFT bin of each harmonic of each candidate
    frac: np.ndarray         # (H, C) interpolation fraction
    weight: np.ndarray       # (H, 1)
    harmonic_map: csr_array  # (C, n_bins): S = harmonic_map @ P, the weighted, interpolated harmonic bins
    n_m: int                 # samples of the motion span (>= n_h)
    m_lo: int                # motion span of the counted hop inside the window: [m_lo, m_hi)
    m_hi: int

    @staticmethod
    def make(p: StepometerParams, fs: float) -> "WindowDesign":
        n_w = max(8, int(round(p.window_s * fs)))
        n_h = max(1, min(n_w, int(round(p.hop_s * fs))))
        offset = (n_w - n_h) // 2
        n_fft = 1 << int(math.ceil(math.log2(n_w * p.zero_pad)))
        taper = np.hanning(n_w + 2)[1:-1]
        lo, hi = p.f_min_hz / p.search_margin, p.f_max_hz * p.search_margin
        cand = np.arange(lo, hi + 0.5 * CANDIDATE_STEP_HZ, CANDIDATE_STEP_HZ)
        k = np.arange(1, p.harmonics + 1)
        if p.harmonics == 1:     # plain dominant peak inside the (widened) band
            harm = cand[None, :]
            weight = np.ones((1, 1))
        else:
            harm = k[:, None] * cand[None, :] / 2.0
            weight = np.where(k % 2 == 1, p.odd_harmonic_weight, 1.0)[:, None]
        idx = harm * n_fft / fs
        idx = np.minimum(idx, n_fft // 2 - 1.000001)      # harmonics beyond Nyquist read the last bin
        i0 = np.floor(idx).astype(np.int64)
        n_m = min(n_w, max(n_h, int(round(p.motion_window_s * fs))))
        m_lo = max(0, offset - (n_m - n_h) // 2)
        m_hi = min(n_w, m_lo + n_m)
        below = int(math.floor(cand[0] * n_fft / fs))
        n_bins = min(n_fft // 2 + 1, max(int(i0.max()) + 2, below + 1))
        # the longest stride lag the periodicity check reads: 2/f (+ ACF_LAG_TOL) at the lowest
        # refined frequency, the first candidate (a hair lower for rounding)
        n_lags = min(n_w, int(math.ceil(2.0 * fs / (cand[0] * (1.0 - 1e-9)) * (1.0 + ACF_LAG_TOL))) + 2)
        n_acf = next_fast_len(n_w + n_lags - 1, real=True)
        frac = idx - i0
        c = np.broadcast_to(np.arange(len(cand)), i0.shape)
        harmonic_map = csr_array((np.concatenate(((1.0 - frac) * weight, frac * weight), axis=None),
                                  (np.concatenate((c, c), axis=None), np.concatenate((i0, i0 + 1), axis=None))),
                                 shape=(len(cand), n_bins))
        return WindowDesign(fs, n_w, n_h, offset, n_fft, n_bins, n_lags, n_acf, taper, 2.0 / float(taper.sum()), cand, i0, frac,
                       weight, harmonic_map, n_m, m_lo, m_hi)


class _Lowpass(NamedTuple):
    """A Butterworth low-pass designed once per (order, cutoff, rate): second-order sections, the
    steady-state initial conditions of a unit step (``sosfilt_zi``) and the odd-extension length of
    :func:`filtfilt` (scipy's ``sosfiltfilt`` default: 3 x the number of taps)."""
    sos: np.ndarray
    zi: np.ndarray           # (n_sections, 2)
    pad: int


@functools.lru_cache(maxsize=64)
def lowpass_design(order: int, cutoff_hz: float, fs: float) -> _Lowpass:
    sos = butter(order, cutoff_hz, fs=fs, output="sos")
    ntaps = 2 * len(sos) + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    zi = sosfilt_zi(sos)
    sos.setflags(write=False)
    zi.setflags(write=False)
    return _Lowpass(sos, zi, 3 * ntaps)


def filtfilt(lp: _Lowpass, x: np.ndarray) -> np.ndarray:
    """Zero-phase low-pass of a 1-D signal longer than ``lp.pad``: forward and backward through the
    sections, odd extension of ``lp.pad`` samples at both ends, each pass starting in the steady
    state of its first sample — what ``scipy.signal.sosfiltfilt(lp.sos, x)`` computes (the same
    operations, bit for bit), with the design's initial conditions computed once, not per call."""
    n = lp.pad
    ext = np.concatenate((2.0 * x[0] - x[n:0:-1], x, 2.0 * x[-1] - x[-2: -n - 2: -1]))
    sos = lp.sos.copy()
    y, _ = sosfilt(sos, ext, zi=lp.zi * ext[0])
    y, _ = sosfilt(sos, y[::-1], zi=lp.zi * y[-1])
    return y[::-1][n: len(y) - n]


def amplitude_spectrum(windows: np.ndarray, design: WindowDesign) -> np.ndarray:
    """Amplitude spectrum (m/s², one-sided sinusoid amplitude) of mean-removed, Hann-tapered,
    zero-padded windows. ``windows`` (N, n_w) -> (N, n_fft//2 + 1); bin spacing fs/n_fft Hz."""
    x = windows - windows.mean(axis=1, keepdims=True)
    return np.sqrt(power_spectrum(x, design, design.n_fft // 2 + 1))


#: Windows transformed per FFT call: the zero-padded spectra of a block stay in cache.
_FFT_BLOCK = 16


def power_spectrum(x: np.ndarray, design: WindowDesign, n_bins: int | None = None) -> np.ndarray:
    """Squared :func:`amplitude_spectrum` of already mean-removed windows ``x`` (N, n_w), bins
    ``[0, n_bins)`` (default ``design.n_bins``, all the analysis reads), from the real and imaginary
    parts (no square root): (N, n_bins). The tapered windows are written into a zeroed block of
    ``n_fft`` columns (the FFT then pads nothing), a block of windows per FFT call, into buffers
    allocated once per call."""
    nb = design.n_bins if n_bins is None else n_bins
    n = len(x)
    power = np.empty((n, nb))
    k = min(_FFT_BLOCK, n)
    buf = np.zeros((k, design.n_fft))
    spec = np.empty((k, design.n_fft // 2 + 1), dtype=complex)
    im2 = np.empty((k, nb))
    for i in range(0, n, _FFT_BLOCK):
        m = min(_FFT_BLOCK, n - i)
        np.multiply(x[i: i + m], design.taper, out=buf[:m, : design.n_w])
        np.fft.rfft(buf[:m], axis=1, out=spec[:m])
        blk = power[i: i + m]
        np.square(spec[:m, :nb].real, out=blk)
        blk += np.square(spec[:m, :nb].imag, out=im2[:m])
    power *= design.scale ** 2
    return power


def normalised_autocorr(x: np.ndarray, design: WindowDesign, lag_lo: int = 0, lag_hi: int | None = None) -> np.ndarray:
    """Unbiased autocorrelation of mean-removed windows ``x`` (N, n_w) at lags ``lag_lo..lag_hi-1``
    (default, and at most, 0..n_lags-1: the lags the analysis reads), normalised by lag 0 (all zero
    for a constant window); Wiener-Khinchin, zero-padded to ``n_acf >= n_w + n_lags - 1`` so that
    nothing wraps around onto these lags (a block of windows per call)."""
    n_w = design.n_w
    hi = design.n_lags if lag_hi is None else lag_hi
    if not 0 <= lag_lo < hi <= design.n_lags:
        raise InvalidInputError("lags", f"lags [{lag_lo}, {hi}) outside [0, {design.n_lags}): they would wrap around")
    n = len(x)
    full = np.empty((n, hi - lag_lo))
    acf0 = np.empty((n, 1))
    k = min(_FFT_BLOCK, n)
    buf = np.zeros((k, design.n_acf))
    spec = np.empty((k, design.n_acf // 2 + 1), dtype=complex)
    psd = np.empty((k, design.n_acf // 2 + 1))
    im2 = np.empty_like(psd)
    blk = np.empty((k, design.n_acf))
    for i in range(0, n, _FFT_BLOCK):
        m = min(_FFT_BLOCK, n - i)
        buf[:m, :n_w] = x[i: i + m]
        np.fft.rfft(buf[:m], axis=1, out=spec[:m])
        np.square(spec[:m].real, out=psd[:m])
        psd[:m] += np.square(spec[:m].imag, out=im2[:m])
        np.fft.irfft(psd[:m], design.n_acf, axis=1, out=blk[:m])
        full[i: i + m] = blk[:m, lag_lo:hi]
        acf0[i: i + m] = blk[:m, :1]
    acf = full / (n_w - np.arange(lag_lo, hi))
    acf0 /= n_w
    return np.divide(acf, acf0, out=np.zeros_like(acf), where=acf0 > 0)


def harmonic_score(power: np.ndarray, design: WindowDesign) -> np.ndarray:
    """Harmonic sum ``S(f) = Σ_k w_k P(k f/2)`` over the candidate grid: (N, >= n_bins) -> (N, C), as
    one sparse product (each candidate reads two bins per harmonic, :attr:`WindowDesign.harmonic_map`)."""
    return np.ascontiguousarray((design.harmonic_map @ np.ascontiguousarray(power[:, : design.n_bins].T)).T)


#: Windows analysed together: a block's arrays stay small enough to be reused, not mapped afresh.
_ANALYSIS_BLOCK = 64


def analyse_windows(windows: np.ndarray, design: WindowDesign, p: StepometerParams) -> list[WindowEstimate]:
    """Step frequency and walking decision for each row of ``windows`` (N, n_w) of |a| in m/s²
    (row by row: a block of rows gives each the estimate it gets alone)."""
    windows = np.atleast_2d(np.asarray(windows, dtype=float))
    out: list[WindowEstimate] = []
    for i in range(0, len(windows), _ANALYSIS_BLOCK):
        out += _analyse_block(windows[i: i + _ANALYSIS_BLOCK], design, p)
    return out


def _analyse_block(windows: np.ndarray, design: WindowDesign, p: StepometerParams) -> list[WindowEstimate]:
    n = len(windows)
    x = windows - windows.mean(axis=1, keepdims=True)
    power = power_spectrum(x, design)
    score = harmonic_score(power, design)
    c = len(design.cand)
    j = np.argmax(score, axis=1)
    # A maximum on the lower edge of the search range is the flank of a peak below it. When that peak is
    # the stride of a fast gait (a swinging arm or a bag at 2.3-2.4 Hz puts most power at the stride,
    # 1.2 Hz, just below the band), the cadence is the largest interior local maximum: take it, and
    # let the band and periodicity tests judge it.
    edge = np.flatnonzero(j == 0)
    if len(edge):
        s = score[edge]
        interior = np.zeros_like(s, dtype=bool)
        interior[:, 1:-1] = (s[:, 1:-1] >= s[:, :-2]) & (s[:, 1:-1] >= s[:, 2:])
        j_int = np.argmax(np.where(interior, s, -np.inf), axis=1)
        # Only when the strongest component below the search range sits at that maximum's stride f/2
        # (within a bin of the unpadded window, 1/window_s): a slow sway elsewhere stays rejected.
        below = int(np.floor(design.cand[0] * design.n_fft / design.fs))
        f_pk = (np.argmax(power[edge, 1:below + 1], axis=1) + 1) * (design.fs / design.n_fft)
        stride_ok = np.abs(design.cand[j_int] / 2.0 - f_pk) <= 1.0 / p.window_s
        j[edge] = np.where(interior.any(axis=1) & stride_ok, j_int, 0)
    j = np.clip(j, 1, c - 2)
    r = np.arange(n)
    a, b, cc = score[r, j - 1], score[r, j], score[r, j + 1]
    den = a - 2.0 * b + cc
    safe = np.where(den < 0, den, -1.0)
    delta = np.where(den < 0, 0.5 * (a - cc) / safe, 0.0)
    f = design.cand[j] + np.clip(delta, -1.0, 1.0) * CANDIDATE_STEP_HZ
    in_band = (f >= p.f_min_hz) & (f <= p.f_max_hz)
    # A gait puts a good share of its harmonic sum into the stride and step fundamentals (k = 1, 2);
    # a machine vibration at 7 Hz fits "the 3rd step harmonic of 2.33 Hz" with nothing there.
    if design.weight.shape[0] >= 2:
        i0, fr = design.i0[:2, j], design.frac[:2, j]            # (2, N)
        pw = power[r[None, :], i0] * (1.0 - fr) + power[r[None, :], i0 + 1] * fr
        fund = (design.weight[:2, 0][:, None] * pw).sum(axis=0)
        in_band &= fund >= p.min_fundamental_share * score[r, j]
    # Periodicity: the normalised autocorrelation at the stride lag 2/f.
    lag = 2.0 / np.maximum(f, 1e-6) * design.fs
    lo = np.clip(np.floor(lag * (1 - ACF_LAG_TOL)).astype(np.int64), 1, design.n_lags - 1)
    hi = np.clip(np.ceil(lag * (1 + ACF_LAG_TOL)).astype(np.int64) + 1, 2, design.n_lags)
    lags = np.arange(int(lo.min()), int(hi.max()))          # only the lags some window reads
    acf = normalised_autocorr(x, design, int(lags[0]), int(lags[-1]) + 1)
    mask = (lags[None, :] >= lo[:, None]) & (lags[None, :] < hi[:, None])
    ac = np.where(mask, acf, -np.inf).max(axis=1)
    ac = np.where(np.isfinite(ac), ac, -1.0)
    std = x.std(axis=1)
    mstd = windows[:, design.m_lo: design.m_hi].std(axis=1)
    walking = in_band & (ac >= p.min_autocorr) & (std >= p.min_std_m_s2) & (mstd >= p.min_motion_std_m_s2)
    return list(map(WindowEstimate, f.tolist(), walking.tolist(), ac.tolist(), std.tolist(), mstd.tolist()))


def magnitude(acc: ArrayLike) -> np.ndarray:
    """|a| of (..., 3) samples: the arithmetic of :meth:`Stepometer.update`'s scalar path."""
    a = np.asarray(acc, dtype=float)
    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    return np.sqrt(x * x + y * y + z * z)
