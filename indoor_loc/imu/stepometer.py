"""FFT stepometer (Nowicki & Skrzypczyński 2019, Sec. 3.1): step frequency of the accelerometer magnitude.

The magnitude ``|a|`` (m/s²) is resampled onto a uniform grid from the sample stamps (linear
interpolation, so 50–400 Hz and irregular sampling are all fine), and a window of ``window_s``
seconds is analysed every ``hop_s`` seconds:

1. Gravity removal: the window mean (≈ g) is subtracted; a Hann taper is applied and the window is
   zero-padded to at least ``zero_pad`` times its length before the real FFT (amplitude spectrum
   ``A(ν) = 2|X(ν)|/Σw``, m/s²).
2. Dominant step frequency by a **harmonic sum** of the power spectrum over the stride harmonics:
   ``S(f) = Σ_{k=1..H} w_k P(k f / 2)`` with ``w_k = 1`` for even ``k`` (the step harmonics f, 2f,
   …) and ``odd_harmonic_weight`` for odd ``k`` (stride harmonics f/2, 3f/2, …: a phone on one leg —
   pocket, bag, armband — sees the stride, so its spectrum's largest peak is often at f/2 or 3f/2
   rather than at the cadence; the plain largest-bin rule of the paper then reads half a cadence,
   which falls outside the walking band). ``S`` is evaluated on a 0.005 Hz candidate grid over the
   walking band widened by ``search_margin`` on both sides and refined by parabolic interpolation of
   its peak; the power spectrum is interpolated linearly between the (zero-padded) FFT bins.
3. Walking iff the refined ``f`` lies in ``[f_min_hz, f_max_hz]`` (the paper's 1.3–2.2 Hz; a maximum
   on the widened margin means the true peak is outside the band), the window is periodic at the
   stride (largest normalised autocorrelation within ±15 % of the stride lag ``2/f`` at least
   ``min_autocorr``) and the magnitude varies enough (standard deviation ≥ ``min_std_m_s2``).
4. Steps of the hop centred in the window: ``f · hop`` (paper: ``d_i = l_s f_i n T``). Attributing
   each window to its centre hop makes the count causal with a bounded latency of
   ``(window_s − hop_s)/2`` and symmetric at start/stop of walking; at the beginning of a stream the
   first window also covers the half window before its centre hop, and :meth:`Stepometer.finish`
   (end of stream, or a gap longer than ``max_gap_s``) lets the last window cover the remaining tail.

Measured on the Oxford step-counter validation walks (``indoor-loc bench imu``), the 1.28 s
window of the paper (256 samples at 200 Hz) resolves only 0.78 Hz bins and cannot separate the
stride from the step harmonics; a 3.84 s window (768 samples at 200 Hz) with a 0.32 s hop
(64 samples) is the default.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field as dc_field
from typing import NamedTuple, Sequence

import numpy as np
from numpy.typing import ArrayLike
from numpy.lib.stride_tricks import sliding_window_view
from scipy.fft import next_fast_len
from scipy.signal import butter, find_peaks, sosfilt, sosfilt_zi
from scipy.sparse import csr_array

from indoor_loc.errors import InvalidInputError
from indoor_loc.params import field, require

#: Resolution of the candidate step-frequency grid before parabolic refinement, Hz.
CANDIDATE_STEP_HZ = 0.005
#: Half width of the stride-lag search for the periodicity check, relative to ``2/f``.
ACF_LAG_TOL = 0.15


@dataclass(frozen=True)
class StepometerParams:
    """Parameters of :class:`Stepometer` (seconds, Hz, m/s²)."""

    window_s: float = field(3.84, "analysis window length, s (768 samples at 200 Hz; the paper's "
                                  "256 samples at 200 Hz = 1.28 s)")
    hop_s: float = field(0.32, "time between window evaluations = duration of one counted hop, s")
    f_min_hz: float = field(1.3, "lowest step frequency counted as walking, Hz")
    f_max_hz: float = field(2.45, "highest step frequency counted as walking, Hz (brisk walking and "
                                    "short turning steps reach 2.3-2.4 Hz)")
    harmonics: int = field(8, "stride harmonics k f/2, k = 1..H, summed in the harmonic spectrum "
                              "(H = 8 reaches 4x the cadence); 1 = plain largest peak in the band")
    odd_harmonic_weight: float = field(0.5, "weight of the odd stride harmonics (f/2, 3f/2, ...) "
                                            "relative to the step harmonics, 0..1")
    search_margin: float = field(1.05, "the harmonic-sum peak is searched over the band widened by "
                                       "this factor on both ends; a peak outside the band = not walking")
    min_autocorr: float = field(0.3, "minimum normalised autocorrelation at the stride lag 2/f "
                                     "(±15 %) for walking, -1..1")
    min_std_m_s2: float = field(0.2, "minimum standard deviation of |a| in the window for walking, m/s² "
                                      "(a hand-held phone on a soft floor can stay below 0.5)")
    min_fundamental_share: float = field(0.15, "minimum share of the harmonic sum in the stride and "
                                               "step fundamentals (f/2, f) for walking, 0..1")
    zero_pad: int = field(8, "FFT length >= zero_pad x window samples (power of two)")
    grid_hz: float = field(0.0, "resampling rate, Hz; 0 = the median input rate of the first "
                                "rate_samples samples")
    rate_samples: int = field(32, "samples used to estimate the input rate when grid_hz = 0")
    max_gap_s: float = field(1.0, "a larger gap between samples ends the current segment (its tail "
                                  "is flushed) and starts a new one, s")
    motion_window_s: float = field(1.0, "length of the span centred on a counted hop whose |a| standard "
                                        "deviation decides moving vs still, s")
    min_motion_std_m_s2: float = field(0.08, "minimum standard deviation of |a| over motion_window_s for "
                                            "a hop to count as moving (below: still, 0 steps), m/s²")
    coast_s: float = field(0.6, "after a clearly periodic walking run, the moving but not periodic hops "
                                "that follow it without a break and start within this long of its end are "
                                "counted at its last cadence (the last steps of a stop, which the windows "
                                "already see as not periodic; longer values also coast through turns), s; "
                                "0 = never")
    coast_energy_ratio: float = field(0.65, "coasting also needs the hop's |a| standard deviation (over "
                                            "motion_window_s) at least this fraction of the median over the "
                                            "walking run's last window_s/2: the steps of a stop keep most of "
                                            "the gait's energy, a still phone does not, 1")
    turn_coast_s: float = field(0.0, "with a heading (add_heading), a moving but not periodic hop within "
                                     "this long of the last walking window is counted at the last cadence "
                                     "while the heading turns (a corridor turn), s; 0 = never")
    turn_min_rad: float = field(0.5, "heading change over the window span of such a hop that makes it a turn, rad")
    coast_confidence: float = field(0.5, "confidence of a hop counted while coasting or bridging, or of a "
                                         "moving hop counted as 0 steps, 0..1")
    bridge_s: float = field(8.0, "a moving but not periodic span after a periodic walking window (a corridor "
                                 "turn, a bag bumping) is held back for up to this long: if the periodic gait "
                                 "resumes it is counted step by step (confidence coast_confidence), else as 0 "
                                 "steps; delays only those hops, s; 0 = never")
    tentative_gap_s: float = field(1.0, "a walking run whose windows are only marginally periodic (autocorrelation "
                                        "below bridge_min_autocorr) is held back until a clearly periodic window "
                                        "(or bridge_s of it): if a still hop, or moving but not walking hops for "
                                        "longer than this, end it first, it was handling the phone and counts "
                                        "0 steps, s")
    bridge_cutoff_hz: float = field(3.0, "low-pass cut-off of |a| for counting the steps of a bridged span one "
                                         "by one, Hz")
    bridge_prominence: float = field(1.0, "minimum prominence of a counted peak in a bridged span, relative to "
                                          "the standard deviation of the low-passed |a| over the span, 1")
    bridge_min_autocorr: float = field(0.5, "a bridge needs a clearly periodic gait on both sides: the largest "
                                            "stride-lag autocorrelation of the walking run before it, and that "
                                            "of the window that ends it, at least this, -1..1")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.window_s > 0, n, "window_s", "> 0", self.window_s)
        require(0 < self.hop_s <= self.window_s, n, "hop_s", "in (0, window_s]", self.hop_s)
        require(0 < self.f_min_hz < self.f_max_hz, n, "f_min_hz", "in (0, f_max_hz)", self.f_min_hz)
        require(self.f_max_hz < 2 * self.f_min_hz, n, "f_max_hz",
                "< 2 f_min_hz (the band must be narrower than an octave)", self.f_max_hz)
        require(isinstance(self.harmonics, int) and 1 <= self.harmonics <= 32, n, "harmonics",
                "an int in [1, 32]", self.harmonics)
        require(0.0 <= self.odd_harmonic_weight <= 1.0, n, "odd_harmonic_weight", "in [0, 1]",
                self.odd_harmonic_weight)
        require(1.0 <= self.search_margin <= 1.18, n, "search_margin",
                "in [1, 1.18] (wider would reach the octave of the band)", self.search_margin)
        require(-1.0 <= self.min_autocorr <= 1.0, n, "min_autocorr", "in [-1, 1]", self.min_autocorr)
        require(0.0 <= self.min_fundamental_share <= 1.0, n, "min_fundamental_share", "in [0, 1]",
                self.min_fundamental_share)
        require(self.min_std_m_s2 >= 0, n, "min_std_m_s2", ">= 0", self.min_std_m_s2)
        require(isinstance(self.zero_pad, int) and 1 <= self.zero_pad <= 64, n, "zero_pad",
                "an int in [1, 64]", self.zero_pad)
        require(self.grid_hz == 0 or 10.0 <= self.grid_hz <= 2000.0, n, "grid_hz",
                "0 (auto) or in [10, 2000]", self.grid_hz)
        require(isinstance(self.rate_samples, int) and self.rate_samples >= 2, n, "rate_samples",
                "an int >= 2", self.rate_samples)
        require(self.max_gap_s > 0, n, "max_gap_s", "> 0", self.max_gap_s)
        require(0 < self.motion_window_s <= self.window_s, n, "motion_window_s", "in (0, window_s]",
                self.motion_window_s)
        require(self.min_motion_std_m_s2 >= 0, n, "min_motion_std_m_s2", ">= 0", self.min_motion_std_m_s2)
        require(self.coast_s >= 0, n, "coast_s", ">= 0", self.coast_s)
        require(self.turn_coast_s >= 0, n, "turn_coast_s", ">= 0", self.turn_coast_s)
        require(self.turn_min_rad > 0, n, "turn_min_rad", "> 0", self.turn_min_rad)
        require(self.coast_energy_ratio >= 0, n, "coast_energy_ratio", ">= 0", self.coast_energy_ratio)
        require(0.0 <= self.coast_confidence <= 1.0, n, "coast_confidence", "in [0, 1]", self.coast_confidence)
        require(self.bridge_s >= 0, n, "bridge_s", ">= 0", self.bridge_s)
        require(self.tentative_gap_s >= 0, n, "tentative_gap_s", ">= 0", self.tentative_gap_s)
        require(self.bridge_cutoff_hz > 0, n, "bridge_cutoff_hz", "> 0", self.bridge_cutoff_hz)
        require(self.bridge_prominence >= 0, n, "bridge_prominence", ">= 0", self.bridge_prominence)
        require(-1.0 <= self.bridge_min_autocorr <= 1.0, n, "bridge_min_autocorr", "in [-1, 1]",
                self.bridge_min_autocorr)


class StepHop(NamedTuple):
    """Steps counted over ``[t_start_ns, t_end_ns)``: ``steps`` = cadence x duration when
    ``walking`` (else 0); ``freq_hz`` is the window's step frequency estimate (also when not walking).

    ``confidence`` (0..1) says how sure the count is: 1 for a periodic walking window and for a
    still hop (0 steps), ``coast_confidence`` for a moving hop whose window is not periodic (counted
    at the last walking cadence while coasting, else 0 steps). ``steps_std`` = (1 − confidence) x
    the steps the hop would hold at that cadence: the standard deviation of the count (steps)."""
    t_start_ns: int
    t_end_ns: int
    steps: float
    freq_hz: float
    walking: bool
    confidence: float = 1.0
    steps_std: float = 0.0


class WindowEstimate(NamedTuple):
    """Spectral analysis of one window: refined step frequency (Hz), periodic-walking decision, the
    stride-lag autocorrelation (1), the standard deviation of |a| over the window and over the
    ``motion_window_s`` centred on the window's counted hop (m/s²)."""
    freq_hz: float
    walking: bool
    autocorr: float
    std_m_s2: float
    motion_std_m_s2: float = 0.0


# ----------------------------------------------------------------------------------------------
# Spectral core (pure, vectorised over windows)
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Design:
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
    def make(p: StepometerParams, fs: float) -> "_Design":
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
        return _Design(fs, n_w, n_h, offset, n_fft, n_bins, n_lags, n_acf, taper, 2.0 / float(taper.sum()), cand, i0, frac,
                       weight, harmonic_map, n_m, m_lo, m_hi)


class _Lowpass(NamedTuple):
    """A Butterworth low-pass designed once per (order, cutoff, rate): second-order sections, the
    steady-state initial conditions of a unit step (``sosfilt_zi``) and the odd-extension length of
    :func:`_filtfilt` (scipy's ``sosfiltfilt`` default: 3 x the number of taps)."""
    sos: np.ndarray
    zi: np.ndarray           # (n_sections, 2)
    pad: int


@functools.lru_cache(maxsize=64)
def _lowpass_design(order: int, cutoff_hz: float, fs: float) -> _Lowpass:
    sos = butter(order, cutoff_hz, fs=fs, output="sos")
    ntaps = 2 * len(sos) + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    zi = sosfilt_zi(sos)
    sos.setflags(write=False)
    zi.setflags(write=False)
    return _Lowpass(sos, zi, 3 * ntaps)


def _filtfilt(lp: _Lowpass, x: np.ndarray) -> np.ndarray:
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


def amplitude_spectrum(windows: np.ndarray, design: _Design) -> np.ndarray:
    """Amplitude spectrum (m/s², one-sided sinusoid amplitude) of mean-removed, Hann-tapered,
    zero-padded windows. ``windows`` (N, n_w) -> (N, n_fft//2 + 1); bin spacing fs/n_fft Hz."""
    x = windows - windows.mean(axis=1, keepdims=True)
    return np.sqrt(power_spectrum(x, design, design.n_fft // 2 + 1))


#: Windows transformed per FFT call: the zero-padded spectra of a block stay in cache.
_FFT_BLOCK = 16


def power_spectrum(x: np.ndarray, design: _Design, n_bins: int | None = None) -> np.ndarray:
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


def normalised_autocorr(x: np.ndarray, design: _Design, lag_lo: int = 0, lag_hi: int | None = None) -> np.ndarray:
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


def harmonic_score(power: np.ndarray, design: _Design) -> np.ndarray:
    """Harmonic sum ``S(f) = Σ_k w_k P(k f/2)`` over the candidate grid: (N, >= n_bins) -> (N, C), as
    one sparse product (each candidate reads two bins per harmonic, :attr:`_Design.harmonic_map`)."""
    return np.ascontiguousarray((design.harmonic_map @ np.ascontiguousarray(power[:, : design.n_bins].T)).T)


#: Windows analysed together: a block's arrays stay small enough to be reused, not mapped afresh.
_ANALYSIS_BLOCK = 64


def analyse_windows(windows: np.ndarray, design: _Design, p: StepometerParams) -> list[WindowEstimate]:
    """Step frequency and walking decision for each row of ``windows`` (N, n_w) of |a| in m/s²
    (row by row: a block of rows gives each the estimate it gets alone)."""
    windows = np.atleast_2d(np.asarray(windows, dtype=float))
    out: list[WindowEstimate] = []
    for i in range(0, len(windows), _ANALYSIS_BLOCK):
        out += _analyse_block(windows[i: i + _ANALYSIS_BLOCK], design, p)
    return out


def _analyse_block(windows: np.ndarray, design: _Design, p: StepometerParams) -> list[WindowEstimate]:
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


# ----------------------------------------------------------------------------------------------
# Online estimator
# ----------------------------------------------------------------------------------------------
@dataclass
class StepometerState:
    """Everything :class:`Stepometer` needs to resume (save with :meth:`Stepometer.state`)."""
    grid_hz: float = 0.0                 # resampling rate in force (0 = not yet known)
    pending_t: list[int] = dc_field(default_factory=list)   # raw samples waiting for the rate estimate
    pending_m: list[float] = dc_field(default_factory=list)
    t0_ns: int | None = None             # stamp of grid index 0 of the current segment
    n_grid: int = 0                      # grid samples produced in the current segment
    last_t_ns: int | None = None         # last raw sample (for interpolation)
    last_m: float = 0.0
    buffer: list[float] = dc_field(default_factory=list)   # last grid samples of |a|, m/s²
    buffer_start: int = 0                # grid index of buffer[0]
    next_window: int = 0                 # index j of the next window to analyse
    last_freq_hz: float = 0.0
    last_walking: bool = False
    walk_freq_hz: float = 0.0            # cadence of the last periodic walking window (0 = none yet)
    walk_end: int | None = None          # grid index where the last periodic walking hop ended
    walk_motion_recent: list[float] = dc_field(default_factory=list)
    # ^ |a| std around each of the walking run's hops over its last window_s/2, m/s² (the gait's energy:
    #   their median)
    coast_end: int | None = None         # grid index where the last coasted hop ended
    walk_autocorr: float = 0.0           # largest stride-lag autocorrelation of the current walking run
    head_t: list[int] = dc_field(default_factory=list)      # recent headings (add_heading): stamps ns
    head_yaw: list[float] = dc_field(default_factory=list)    # and unwrapped yaw, rad
    held: list[tuple[int, int, float, float, bool, float, float]] = dc_field(default_factory=list)
    # ^ hops held back while bridging: (lo, hi, freq_hz, count_hz, walking, confidence, steps_std) as
    #   they are emitted if the gait does not resume
    tentative: list[tuple[int, int, float, float, bool, float, float]] = dc_field(default_factory=list)
    # ^ hops of a walking run (and segment head) not yet clearly periodic, as they are emitted if it
    #   becomes so; walking ones count 0 steps if it ends first
    count_freq_hz: float = 0.0           # cadence of the last hop counted (0 = last hop not counted)
    count_confidence: float = 1.0
    last_confidence: float = 1.0
    total_steps: float = 0.0
    walking_s: float = 0.0
    samples: int = 0

    def copy(self) -> "StepometerState":
        return dataclasses.replace(self, pending_t=list(self.pending_t), pending_m=list(self.pending_m),
                                   buffer=list(self.buffer), head_t=list(self.head_t),
                                   head_yaw=list(self.head_yaw), held=list(self.held),
                                   tentative=list(self.tentative),
                                   walk_motion_recent=list(self.walk_motion_recent))


def _median(values: list[float]) -> float:
    """Median of a short list (what ``np.median`` gives: the mean of the two middle values when even)."""
    v = sorted(values)
    k = len(v) // 2
    return v[k] if len(v) % 2 else (v[k - 1] + v[k]) / 2.0


def _magnitude(acc: ArrayLike) -> np.ndarray:
    """|a| of (..., 3) samples: the arithmetic of :meth:`Stepometer.update`'s scalar path."""
    a = np.asarray(acc, dtype=float)
    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    return np.sqrt(x * x + y * y + z * z)


class _LookAhead(NamedTuple):
    """Windows analysed ahead of their samples (:meth:`Stepometer.prefetch`): segment (``t0_ns``,
    ``grid_hz``), index of the first window, the grid samples from its start, the estimates."""
    t0_ns: int
    grid_hz: float
    window: int
    span: np.ndarray
    estimates: list[WindowEstimate]


class _GridAhead(NamedTuple):
    """The grid values of a run's steady part computed ahead (:meth:`Stepometer.prefetch`): segment
    (``t0_ns``, ``grid_hz``), the state before the run (``n_grid``, ``last_t_ns``, ``last_m``), the
    samples (stamps, acc, |a|), the grid length after each sample and the grid values from ``n_grid``."""
    t0_ns: int
    grid_hz: float
    n_grid: int
    last_t_ns: int
    last_m: float
    t: np.ndarray
    acc: np.ndarray
    m: np.ndarray
    reach: np.ndarray
    grid: np.ndarray


class QuietPlan:
    """:meth:`Stepometer.quiet_plan`: the grid length after each sample of a run (``n_grid``, as
    :meth:`Stepometer.quiet_count` computes it), so the count from sample ``i`` on is one lookup.
    Used only while the stepometer's grid (t0, rate) is the one planned for and its last sample is
    ``stamps[i - 1]``; otherwise :meth:`Stepometer.quiet_count` answers."""

    def __init__(self, owner: Stepometer, stamps: np.ndarray, first: int, t0_ns: int, grid_hz: float,
                 n_grid: np.ndarray) -> None:
        self._owner, self._t, self._first = owner, stamps, first
        self._t0_ns, self._grid_hz, self._n_grid = t0_ns, grid_hz, n_grid

    def count(self, i: int) -> int | None:
        """``quiet_count(stamps[i:])`` once ``stamps[:i]`` have been fed (``i`` = 0: before any)."""
        if i == 0:
            return self._first
        o = self._owner
        st = o._st
        d = o._get_design()
        if (d is None or i < 0 or i >= len(self._t) or st.t0_ns != self._t0_ns or st.grid_hz != self._grid_hz
                or st.last_t_ns != int(self._t[i - 1]) or st.n_grid != int(self._n_grid[i - 1])):
            return o.quiet_count(self._t[i:])
        # n_grid is non-decreasing: the first sample from i on reaching the next window's end
        k = int(np.searchsorted(self._n_grid, st.next_window * d.n_h + d.n_w, side="left"))
        return max(k, i) - i


class Stepometer:
    """Online FFT stepometer. Feed samples with :meth:`update` (one) or :meth:`update_many` (a
    chunk); each returns the :class:`StepHop` s completed so far, in time order. :meth:`finish`
    flushes the tail at the end of the stream. ``state()``/``set_state()`` save and resume."""

    def __init__(self, params: StepometerParams | None = None) -> None:
        self.params = params if params is not None else StepometerParams()
        self.params.validate()
        self._st = StepometerState(grid_hz=float(self.params.grid_hz))
        self._design: _Design | None = None
        self._ahead: _LookAhead | None = None      # windows analysed ahead (prefetch); not state
        self._grid_ahead: _GridAhead | None = None  # grid values computed ahead (prefetch); not state
        self._grid_now: np.ndarray | None = None    # the grid from buffer_start while analysing; not state
        #: walking hops over which the gait's energy is a median: the run's last half window
        self._n_recent = max(1, int(round(0.5 * self.params.window_s / self.params.hop_s)))

    # -- state ------------------------------------------------------------------------------------
    def state(self) -> StepometerState:
        return self._st.copy()

    def set_state(self, state: StepometerState) -> None:
        self._st = state.copy()
        self._design = None
        self._ahead = None
        self._grid_ahead = None

    @property
    def total_steps(self) -> float:
        return self._st.total_steps

    @property
    def walking(self) -> bool:
        return self._st.last_walking

    @property
    def freq_hz(self) -> float:
        return self._st.last_freq_hz

    @property
    def confidence(self) -> float:
        """Confidence (0..1) of the last hop's count."""
        return self._st.last_confidence

    @property
    def rate_hz(self) -> float:
        """Resampling rate in force (Hz; 0 until estimated)."""
        return self._st.grid_hz

    @property
    def latency_s(self) -> float:
        """Delay between a sample and the end of the hop that counts it, at most, s."""
        d = self._get_design()
        if d is None:
            return 0.5 * (self.params.window_s + self.params.hop_s)
        return (d.n_w - d.offset) / d.fs

    def _get_design(self) -> _Design | None:
        if self._design is None and self._st.grid_hz > 0:
            self._design = _Design.make(self.params, self._st.grid_hz)
        return self._design

    # -- input ------------------------------------------------------------------------------------
    def add_heading(self, stamp_ns: int, yaw_rad: float) -> None:
        """A heading sample (rad, any frame; only its changes matter) for the turn test of
        :meth:`_count`. Give headings up to a stamp before the accelerometer samples of that stamp
        (live: as they arrive). Non-finite or out-of-order samples are ignored. With the turn test off
        (``turn_coast_s`` = 0, the default) nothing reads them and they are not stored."""
        if self.params.turn_coast_s <= 0:
            return
        st = self._st
        t = int(stamp_ns)
        if not math.isfinite(yaw_rad) or (st.head_t and t <= st.head_t[-1]):
            return
        y = float(yaw_rad)
        if st.head_yaw:
            y = st.head_yaw[-1] + (y - st.head_yaw[-1] + math.pi) % (2 * math.pi) - math.pi
        st.head_t.append(t)
        st.head_yaw.append(y)
        keep_ns = int((2.0 * self.params.window_s + 2.0) * 1e9)
        drop = 0
        while drop < len(st.head_t) - 2 and st.head_t[drop] < t - keep_ns:
            drop += 1
        if drop:
            del st.head_t[:drop], st.head_yaw[:drop]

    def clear_headings(self) -> None:
        """Forget the stored headings (the heading source changed its frame)."""
        self._st.head_t, self._st.head_yaw = [], []

    def _turned_rad(self, t0_ns: int, t1_ns: int) -> float:
        """|heading change| over [t0, t1] from the stored headings (0 without any)."""
        st = self._st
        if len(st.head_t) < 2:
            return 0.0
        tt = np.asarray(st.head_t, dtype=np.int64)
        yy = np.asarray(st.head_yaw, dtype=float)
        y0, y1 = np.interp([float(t0_ns - tt[0]), float(t1_ns - tt[0])], (tt - tt[0]).astype(float), yy)
        return abs(float(y1 - y0))

    def update(self, stamp_ns: int, acc: Sequence[float] | np.ndarray) -> list[StepHop]:
        """One accelerometer sample: ``acc`` (3,) m/s² incl. gravity. Raises InvalidInputError
        (``"nan"``, ``"non_monotonic_stamp"``) with the state unchanged."""
        st = self._st
        t = int(stamp_ns)
        if (st.grid_hz > 0 and st.t0_ns is not None and st.last_t_ns is not None
                and t - st.last_t_ns <= self.params.max_gap_s * 1e9 and len(acc) == 3):
            # Fast scalar path (the common case once running); same arithmetic as _extend.
            x, y, z = float(acc[0]), float(acc[1]), float(acc[2])
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
                raise InvalidInputError("nan", "acc has NaN/inf components")
            if t < st.last_t_ns:
                raise InvalidInputError("non_monotonic_stamp",
                                          f"stamp {t} goes backwards (previous {st.last_t_ns})")
            m = math.sqrt(x * x + y * y + z * z)
            st.samples += 1
            k_end = int(math.floor((t - st.t0_ns) * 1e-9 * st.grid_hz + 1e-9))
            if k_end >= st.n_grid:
                step_ns = 1e9 / st.grid_hz
                dt = float(t - st.last_t_ns)
                for k in range(st.n_grid, k_end + 1):
                    tk = st.t0_ns + round(k * step_ns)
                    st.buffer.append(st.last_m + (m - st.last_m) * (float(tk - st.last_t_ns) / dt))
                st.n_grid = k_end + 1
            st.last_t_ns, st.last_m = t, m
            d = self._get_design()
            assert d is not None
            if st.n_grid >= st.next_window * d.n_h + d.n_w:
                return self._analyse_ready()
            return []
        a = np.asarray(acc, dtype=float).reshape(-1)
        if a.shape != (3,):
            raise InvalidInputError("shape", f"acc: expected 3 components, got {a.shape}")
        return self.update_many(np.array([t], dtype=np.int64), a[None, :])

    # -- batch entry points (offline runs): the arithmetic of update()'s scalar path, vectorised ----
    def quiet_count(self, stamps_ns: np.ndarray) -> int | None:
        """How many leading samples of ``stamps_ns`` (int64, increasing) :meth:`update` would take
        without completing an analysis window (``len`` if none completes one): the next sample is
        the one that does. None unless running steadily (rate known, a segment open, no gap longer
        than ``max_gap_s`` before or between the samples)."""
        st = self._st
        d = self._get_design()
        if d is None or st.grid_hz <= 0 or st.t0_ns is None or st.last_t_ns is None or not len(stamps_ns):
            return None
        t = np.asarray(stamps_ns, dtype=np.int64)
        prev = np.concatenate((np.array([st.last_t_ns], np.int64), t[:-1]))
        if np.any(t < prev) or np.any((t - prev).astype(float) > self.params.max_gap_s * 1e9):
            return None
        k_end = np.floor((t - st.t0_ns).astype(float) * 1e-9 * st.grid_hz + 1e-9).astype(np.int64)
        n_grid = np.maximum(np.maximum.accumulate(k_end + 1), st.n_grid)
        ready = np.flatnonzero(n_grid >= st.next_window * d.n_h + d.n_w)
        return int(ready[0]) if len(ready) else len(t)

    def quiet_plan(self, stamps_ns: np.ndarray) -> QuietPlan | None:
        """:meth:`quiet_count` for a run the caller then feeds from its start in cuts that each end
        on the sample completing a window: ``plan.count(i)`` equals ``quiet_count(stamps_ns[i:])``
        once ``stamps_ns[:i]`` have been fed, from one look at the whole run. None when
        ``quiet_count(stamps_ns)`` is None."""
        st = self._st
        first = self.quiet_count(stamps_ns)
        if first is None:
            return None
        assert st.t0_ns is not None
        t = np.asarray(stamps_ns, dtype=np.int64)
        k_end = np.floor((t - st.t0_ns).astype(float) * 1e-9 * st.grid_hz + 1e-9).astype(np.int64)
        return QuietPlan(self, t, first, st.t0_ns, st.grid_hz,
                         np.maximum(np.maximum.accumulate(k_end + 1), st.n_grid))

    def extend_steady(self, stamps_ns: np.ndarray, acc: np.ndarray) -> list[StepHop]:
        """Samples of which at most the last completes a window (see :meth:`quiet_count`, which must
        have allowed them): the same grid values, state and hops as :meth:`update` one by one —
        the same floating-point operations in the same order, vectorised. ``acc`` (N, 3) finite."""
        st = self._st
        d = self._get_design()
        assert d is not None and st.t0_ns is not None and st.last_t_ns is not None
        t = np.asarray(stamps_ns, dtype=np.int64)
        ahead = self._grid_from_ahead(t, acc)
        if ahead is None:
            m = _magnitude(acc)
            new, last_m = self._steady_grid(t, m), float(m[-1])
        else:
            new, last_m = ahead
        st.samples += len(t)
        if len(new):
            st.buffer.extend(new.tolist())
            st.n_grid += len(new)
        st.last_t_ns, st.last_m = int(t[-1]), last_m
        if st.n_grid >= st.next_window * d.n_h + d.n_w:
            return self._analyse_ready()
        return []

    def _grid_from_ahead(self, t: np.ndarray, acc: np.ndarray) -> tuple[np.ndarray, float] | None:
        """The grid values (and the last |a|) that :meth:`_steady_grid` gives for these samples, taken
        from the look-ahead when it holds exactly these samples, in the same segment, following the
        sample last taken (any cut gives the same grid values); else None."""
        g = self._grid_ahead
        st = self._st
        if g is None or g.t0_ns != st.t0_ns or g.grid_hz != st.grid_hz or not len(t):
            return None
        o = int(np.searchsorted(g.t, t[0]))
        end = o + len(t)
        if end > len(g.t):
            return None
        prev = (g.last_t_ns, g.last_m, g.n_grid) if o == 0 else (int(g.t[o - 1]), float(g.m[o - 1]), int(g.reach[o - 1]))
        if prev != (st.last_t_ns, st.last_m, st.n_grid):
            return None
        if not (np.array_equal(g.t[o:end], t) and np.array_equal(g.acc[o:end], acc)):
            return None
        return g.grid[st.n_grid - g.n_grid: int(g.reach[end - 1]) - g.n_grid], float(g.m[end - 1])

    def _steady_grid(self, t: np.ndarray, m: np.ndarray) -> np.ndarray:
        """The grid values from ``n_grid`` on completed by the samples ``t`` (int64, non-decreasing,
        no gap) / ``m`` (|a|) that follow the last one taken: the arithmetic of :meth:`update`'s
        scalar path, vectorised (the same floating-point operations in the same order, so any cut
        of the samples into calls gives the same grid). The state is not changed."""
        st = self._st
        assert st.t0_ns is not None and st.last_t_ns is not None
        k_end = np.floor((t - st.t0_ns).astype(float) * 1e-9 * st.grid_hz + 1e-9).astype(np.int64)
        last_k = int(max(int(k_end.max()), st.n_grid - 1))
        if last_k < st.n_grid:
            return np.zeros(0)
        k = np.arange(st.n_grid, last_k + 1, dtype=np.int64)
        # grid point k is filled by the first sample whose k_end reaches it, between that
        # sample and the one before it (update(): last_m + (m - last_m) * ((tk - last_t) / dt))
        # (sample j fills the points above the previous samples' reach, up to its own: np.repeat)
        reach = np.maximum(np.maximum.accumulate(k_end), st.n_grid - 1)
        i = np.repeat(np.arange(len(t)), np.diff(reach, prepend=st.n_grid - 1))
        t_prev = np.concatenate((np.array([st.last_t_ns], np.int64), t))[i]
        m_prev = np.concatenate(([st.last_m], m))[i]
        tk = st.t0_ns + np.round(k * (1e9 / st.grid_hz)).astype(np.int64)
        dt = (t[i] - t_prev).astype(float)
        return m_prev + (m[i] - m_prev) * ((tk - t_prev).astype(float) / dt)

    def prefetch(self, stamps_ns: np.ndarray, acc: np.ndarray) -> int:
        """Offline look-ahead: ``stamps_ns`` (N,) int64 / ``acc`` (N, 3) are the samples the caller is
        about to feed (in the same order, by any calls). The analysis windows their steady leading
        part completes are analysed now, all together (one vectorised call instead of one per window);
        a later window analysis reuses such an estimate only when its window holds exactly the same
        grid values, so the hops and state are those of feeding the samples without it. Changes
        no state; returns the number of windows analysed ahead (0: nothing to gain)."""
        st = self._st
        d = self._get_design()
        self._ahead = None
        self._grid_ahead = None
        if d is None or st.grid_hz <= 0 or st.t0_ns is None or st.last_t_ns is None:
            return 0
        t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        a = np.asarray(acc, dtype=float)
        if a.ndim != 2 or a.shape != (len(t), 3) or not len(t):
            return 0
        # the steady leading part: finite, no stamp going back, no gap longer than max_gap_s
        prev = np.concatenate((np.array([st.last_t_ns], np.int64), t[:-1]))
        bad = np.flatnonzero((t < prev) | ((t - prev).astype(float) > self.params.max_gap_s * 1e9)
                             | ~np.isfinite(a).all(axis=1))
        n = int(bad[0]) if len(bad) else len(t)
        if n == 0:
            return 0
        n_grid = max(int(math.floor((int(t[n - 1]) - st.t0_ns) * 1e-9 * st.grid_hz + 1e-9)) + 1, st.n_grid)
        n_win = (n_grid - d.n_w) // d.n_h + 1 - st.next_window if n_grid >= d.n_w else 0
        if n_win < 2:           # one window or none: analysed when it completes, as without look-ahead
            return 0
        mags = _magnitude(a[:n])
        new = self._steady_grid(t[:n], mags)
        k_end = np.floor((t[:n] - st.t0_ns).astype(float) * 1e-9 * st.grid_hz + 1e-9).astype(np.int64)
        self._grid_ahead = _GridAhead(st.t0_ns, st.grid_hz, st.n_grid, st.last_t_ns, st.last_m, t[:n], a[:n], mags,
                                      np.maximum(np.maximum.accumulate(k_end + 1), st.n_grid), new)
        first = st.next_window * d.n_h
        span = np.concatenate((np.asarray(st.buffer[first - st.buffer_start:], dtype=float), new))
        span = span[: (n_win - 1) * d.n_h + d.n_w]
        wins = sliding_window_view(span, d.n_w)[:: d.n_h]
        self._ahead = _LookAhead(st.t0_ns, st.grid_hz, st.next_window, span,
                                 analyse_windows(wins, d, self.params))
        return n_win

    def _analysed(self, span: np.ndarray, d: _Design) -> list[WindowEstimate]:
        """Estimates of the windows of ``span`` (grid samples from window ``next_window`` on): from the
        look-ahead when it holds exactly these windows, else analysed now."""
        st = self._st
        ah = self._ahead
        if ah is not None and ah.t0_ns == st.t0_ns and ah.grid_hz == st.grid_hz:
            k = st.next_window - ah.window
            n = (len(span) - d.n_w) // d.n_h + 1
            lo = k * d.n_h
            if 0 <= k and k + n <= len(ah.estimates) and np.array_equal(ah.span[lo: lo + len(span)], span):
                return ah.estimates[k: k + n]
        return analyse_windows(sliding_window_view(span, d.n_w)[:: d.n_h], d, self.params)

    def add_headings(self, stamps_ns: list[int], yaw_rad: list[float]) -> None:
        """:meth:`add_heading` for each sample in order (same values and state)."""
        if self.params.turn_coast_s <= 0:
            return
        st = self._st
        head_t, head_yaw = st.head_t, st.head_yaw
        two_pi, pi = 2 * math.pi, math.pi
        for t, y in zip(stamps_ns, yaw_rad):
            if not math.isfinite(y) or (head_t and t <= head_t[-1]):
                continue
            y = float(y)
            if head_yaw:
                y = head_yaw[-1] + (y - head_yaw[-1] + pi) % two_pi - pi
            head_t.append(int(t))
            head_yaw.append(y)
        if not head_t:
            return
        keep_ns = int((2.0 * self.params.window_s + 2.0) * 1e9)
        t_last = head_t[-1]
        drop = 0
        while drop < len(head_t) - 2 and head_t[drop] < t_last - keep_ns:
            drop += 1
        if drop:
            del head_t[:drop], head_yaw[:drop]

    def update_many(self, stamps_ns: ArrayLike, acc: ArrayLike) -> list[StepHop]:
        """A chunk of samples: ``stamps_ns`` (N,) int ns non-decreasing, ``acc`` (N, 3) m/s².
        Validated as a whole before any state change."""
        t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        a = np.asarray(acc, dtype=float)
        if a.ndim != 2 or a.shape != (len(t), 3):
            raise InvalidInputError("shape", f"acc: expected ({len(t)}, 3), got {a.shape}")
        if not np.isfinite(a).all():
            raise InvalidInputError("nan", "acc has NaN/inf components")
        if len(t) == 0:
            return []
        prev = self._st.pending_t[-1] if self._st.pending_t else self._st.last_t_ns
        if (prev is not None and t[0] < prev) or np.any(np.diff(t) < 0):
            raise InvalidInputError("non_monotonic_stamp",
                                      f"stamp {int(t[0])} goes backwards (previous {prev})")
        m = _magnitude(a)
        st = self._st
        st.samples += len(t)
        if st.grid_hz <= 0:
            # the samples so far, as arrays (a whole recording at once is not turned into Python lists)
            t = np.concatenate((np.asarray(st.pending_t, dtype=np.int64), t))
            m = np.concatenate((np.asarray(st.pending_m, dtype=float), m))
            dt = np.diff(t[: self.params.rate_samples + 1])
            dt = dt[dt > 0]
            if len(t) <= self.params.rate_samples or len(dt) == 0:
                st.pending_t, st.pending_m = t.tolist(), m.tolist()
                return []
            st.grid_hz = float(min(2000.0, max(10.0, 1e9 / float(np.median(dt)))))
            st.pending_t, st.pending_m = [], []
        return self._ingest(t, m)

    def finish(self) -> list[StepHop]:
        """End of the stream: count the tail after the last analysed window's hop with that
        window's frequency; the next sample starts a new segment."""
        st = self._st
        if st.grid_hz <= 0 and st.pending_t:
            # Too few samples to estimate a rate: use what there is.
            dt = np.diff(np.asarray(st.pending_t, dtype=np.int64))
            dt = dt[dt > 0]
            if len(dt):
                st.grid_hz = float(min(2000.0, max(10.0, 1e9 / float(np.median(dt)))))
                t = np.asarray(st.pending_t, dtype=np.int64)
                m = np.asarray(st.pending_m, dtype=float)
                st.pending_t, st.pending_m = [], []
                self._ingest(t, m)        # too short for a window: nothing is counted
        return self._flush_segment()

    # -- internals --------------------------------------------------------------------------------
    def _grid_time(self, k: int) -> int:
        assert self._st.t0_ns is not None
        return self._st.t0_ns + int(round(k * 1e9 / self._st.grid_hz))

    def _ingest(self, t: np.ndarray, m: np.ndarray) -> list[StepHop]:
        """Resample raw samples onto the grid (segment by segment) and analyse complete windows."""
        d = self._get_design()
        assert d is not None
        st = self._st
        out: list[StepHop] = []
        gap_ns = int(self.params.max_gap_s * 1e9)
        start = 0
        n = len(t)
        while start < n:
            if st.t0_ns is None:        # new segment starts at this sample
                st.t0_ns = int(t[start])
                st.n_grid = 1
                st.last_t_ns, st.last_m = int(t[start]), float(m[start])
                st.buffer = [float(m[start])]
                st.buffer_start = 0
                st.next_window = 0
                start += 1
                continue
            # the run of samples up to the next big gap
            tt = t[start:]
            prev_t = np.concatenate((np.array([st.last_t_ns], np.int64), tt[:-1]))
            big = np.flatnonzero(tt - prev_t > gap_ns)
            stop = start + (int(big[0]) if len(big) else len(tt))
            if stop > start:
                out += self._extend(t[start:stop], m[start:stop])
            if stop < n:                # gap: close the segment, the next sample opens a new one
                out += self._flush_segment()
            start = stop
        return out

    def _extend(self, t: np.ndarray, m: np.ndarray) -> list[StepHop]:
        st = self._st
        d = self._get_design()
        assert d is not None and st.t0_ns is not None and st.last_t_ns is not None
        # grid indices k with last_t < t_k <= t[-1]; t_k = t0 + k/fs, linear between the samples
        new = self._steady_grid(t, m)
        st.n_grid += len(new)
        # keep the last sample with the largest stamp (equal stamps: the latest value)
        st.last_t_ns, st.last_m = int(t[-1]), float(m[-1])
        return self._analyse_ready(new)

    def _analyse_ready(self, new: np.ndarray | None = None) -> list[StepHop]:
        """Analyse the windows the grid completes. ``new``: grid values already counted in ``n_grid``
        but not yet appended to the buffer (a long chunk: only the part later windows need is kept
        as a list; the analysis reads the values as one array)."""
        st = self._st
        d = self._get_design()
        assert d is not None
        n_ready = (st.n_grid - d.n_w) // d.n_h + 1 - st.next_window if st.n_grid >= d.n_w else 0
        out: list[StepHop] = []
        if n_ready <= 0:
            if new is not None:
                st.buffer.extend(new.tolist())
            return out
        grid = np.asarray(st.buffer, dtype=float)
        if new is not None:
            grid = np.concatenate((grid, new))
        self._grid_now = grid
        n_h, offset = d.n_h, d.offset
        try:
            first = st.next_window * d.n_h - st.buffer_start
            span = grid[first: first + (n_ready - 1) * d.n_h + d.n_w]
            for est in self._analysed(span, d):
                j = st.next_window
                lo = j * n_h + offset
                hi = lo + n_h
                hop = self._walk_on(j, lo, hi, est)
                if hop is not None:
                    out.append(hop)
                    st.next_window = j + 1
                    continue
                if j == 0:
                    # head of the segment: the first window covers it, hop by hop (each with its own
                    # moving/still test, so standing before the walk is not counted); with a walking
                    # but only marginally periodic first window it waits with that window's hop
                    head = self._span_hops(0, lo, est.walking, est.freq_hz, 1.0)
                    if est.walking and est.autocorr < self.params.bridge_min_autocorr:
                        st.tentative += head
                    else:
                        out += [self._emit(*h) for h in head]
                out += self._count(lo, hi, est)
                st.next_window += 1
        finally:
            self._grid_now = None
            # keep the grid samples later windows (or a bridged span's step count) need
            keep_from = st.next_window * d.n_h
            if st.held:
                keep_from = min(keep_from, st.held[0][0] - int(round(0.5 * st.grid_hz)))
            keep_from = max(keep_from, st.buffer_start)
            st.buffer = grid[keep_from - st.buffer_start:].tolist()
            st.buffer_start = keep_from
        return out

    def _grid_values(self, a: int, b: int) -> np.ndarray:
        """Grid samples ``[a, b)`` (indices of the segment, at least ``buffer_start``)."""
        st = self._st
        if self._grid_now is not None:
            return self._grid_now[a - st.buffer_start: b - st.buffer_start]
        return np.asarray(st.buffer[a - st.buffer_start: b - st.buffer_start], dtype=float)

    def _walk_on(self, j: int, lo: int, hi: int, est: WindowEstimate) -> StepHop | None:
        """The common case: the hop ``[lo, hi)`` of window ``j`` (not a segment's first) when a clearly
        periodic walking run goes on with it and nothing is held or tentative — what :meth:`_count`
        and :meth:`_emit` do for it (the same operations), without their general branches. None, with
        nothing changed, in any other case."""
        st = self._st
        b_min = self.params.bridge_min_autocorr
        if not (est.walking and st.walk_end == lo and j and not st.held and not st.tentative
                and (est.autocorr >= b_min or st.walk_autocorr >= b_min)):
            return None
        f = est.freq_hz
        st.walk_freq_hz = f
        st.walk_end = hi
        recent = st.walk_motion_recent
        if len(recent) >= self._n_recent:
            del recent[: len(recent) - self._n_recent + 1]
        recent.append(est.motion_std_m_s2)
        if est.autocorr > st.walk_autocorr:
            st.walk_autocorr = est.autocorr
        fs = st.grid_hz
        dur = (hi - lo) / fs
        steps = f * dur
        st.total_steps += steps
        st.walking_s += dur
        st.last_freq_hz = st.count_freq_hz = f
        st.last_walking = True
        st.last_confidence = st.count_confidence = 1.0
        t0 = st.t0_ns
        assert t0 is not None
        return StepHop(t0 + int(round(lo * 1e9 / fs)), t0 + int(round(hi * 1e9 / fs)), steps, f, True, 1.0, 0.0)

    def _count(self, lo: int, hi: int, est: WindowEstimate) -> list[StepHop]:
        """The hop ``[lo, hi)`` (grid indices) centred in a window with estimate ``est``, and any hops
        held back before it that it resolves.

        Periodic walking window: ``f x duration`` steps, confidence 1. Still (``|a|`` quiet around
        the hop): 0 steps, confidence 1. Moving but not periodic — a corridor turn, a bag swinging
        into the body, a soft floor smearing the impacts, the last steps of a stop: right after a clearly
        periodic walking run (without a break, starting within ``coast_s`` of its end) a hop that keeps
        ``coast_energy_ratio`` of the run's recent ``|a|`` energy is counted at its last cadence, with
        confidence ``coast_confidence`` (a window centred before a stop already holds the still phone
        after it and loses its periodicity while the last steps are still being taken; the steps of a
        stop decay in amplitude, the still phone has none); within ``bridge_s`` of it, the hop (coasted
        or not)
        is held back until the gait either resumes with a clearly periodic window (the span was
        walking: its steps are counted one by one, :meth:`_release_held`) or does not (a still hop, or
        ``bridge_s`` ran out: 0 steps with that confidence). A walking window that is only marginally
        periodic while hops are held is held with them (counted at its own cadence if the gait does
        not resume)."""
        st = self._st
        p = self.params
        dur = (hi - lo) / st.grid_hz
        if est.walking and st.held and est.autocorr < p.bridge_min_autocorr:
            # not clearly periodic yet: part of the held span (counted at its own cadence if the gait
            # does not resume)
            if (hi - st.walk_end) / st.grid_hz <= p.bridge_s if st.walk_end is not None else False:
                st.held.append((lo, hi, est.freq_hz, est.freq_hz, True, 1.0, 0.0))
                return []
        if est.walking:
            out: list[StepHop] = []
            run = st.walk_end == lo and st.walk_end is not None
            if st.held:
                run = True
                out = self._release_held(est.freq_hz) if est.autocorr >= p.bridge_min_autocorr else self._drop_held()
            st.walk_freq_hz = est.freq_hz
            st.walk_end = hi
            # the gait's energy: median over the run's last half window (a stop's steps decay from it)
            recent = st.walk_motion_recent
            if not run:
                recent = st.walk_motion_recent = []
            elif len(recent) >= self._n_recent:
                del recent[: len(recent) - self._n_recent + 1]
            recent.append(est.motion_std_m_s2)
            st.walk_autocorr = max(st.walk_autocorr, est.autocorr) if run else est.autocorr
            hop = (lo, hi, est.freq_hz, est.freq_hz, True, 1.0, 0.0)
            if st.walk_autocorr < p.bridge_min_autocorr:
                # a run that is not yet clearly periodic (handling the phone passes the periodicity
                # test for a window or two): it waits until it is, or has lasted bridge_s
                st.tentative.append(hop)
                if (hi - st.tentative[0][0]) / st.grid_hz < p.bridge_s:
                    return out
                hop = st.tentative.pop()
            if st.tentative:
                out += [self._emit(*h) for h in st.tentative]
                st.tentative = []
            out.append(self._emit(*hop))
            return out
        if est.motion_std_m_s2 < p.min_motion_std_m_s2:
            return self._drop_tentative() + self._drop_held() + [self._emit(lo, hi, est.freq_hz, 0.0, False, 1.0, 0.0)]
        c = p.coast_confidence
        since_s = math.inf if st.walk_end is None else (lo - st.walk_end) / st.grid_hz
        # a stop's last steps: contiguous hops right after a clearly periodic walk that keep its energy
        contiguous = (st.walk_end is not None and lo in (st.walk_end, st.coast_end)
                      and st.walk_autocorr >= p.bridge_min_autocorr)
        coast = (since_s < p.coast_s and contiguous and bool(st.walk_motion_recent)
                 and est.motion_std_m_s2 >= p.coast_energy_ratio * _median(st.walk_motion_recent))
        if not coast and since_s < p.turn_coast_s and st.walk_freq_hz > 0:
            # a corridor turn: the heading swings while the gait loses its periodicity
            half = int(0.5 * p.window_s * 1e9)
            mid = (self._grid_time(lo) + self._grid_time(hi)) // 2
            coast = self._turned_rad(mid - half, mid + half) >= p.turn_min_rad
        if st.walk_freq_hz > 0 and coast:
            st.coast_end = hi
            f = st.walk_freq_hz
            hop = (lo, hi, est.freq_hz, f, True, c, (1.0 - c) * f * dur)
        else:
            f_ref = min(max(est.freq_hz, p.f_min_hz), p.f_max_hz)
            hop = (lo, hi, est.freq_hz, 0.0, False, c, (1.0 - c) * f_ref * dur)
        if (st.walk_end is not None and st.walk_freq_hz > 0 and st.walk_autocorr >= p.bridge_min_autocorr
                and (hi - st.walk_end) / st.grid_hz <= p.bridge_s):
            st.held.append(hop)
            return []
        if st.tentative:
            last = max(h[1] for h in st.tentative if h[4])
            if (hi - last) / st.grid_hz <= p.tentative_gap_s:
                st.tentative.append(hop)      # a gait that is starting misses the test for a moment
                return []
        return self._drop_tentative() + self._drop_held() + [self._emit(*hop)]

    def _drop_tentative(self) -> list[StepHop]:
        """A walking run ended before it became clearly periodic (or the recording ended): it was
        handling, not gait, and its walking hops count 0 steps, confidence ``coast_confidence``."""
        st = self._st
        c = self.params.coast_confidence
        out = []
        for lo, hi, fq, f, walking, conf, sd in st.tentative:
            if walking:
                out.append(self._emit(lo, hi, fq, 0.0, False, c, (1.0 - c) * f * (hi - lo) / st.grid_hz))
            else:
                out.append(self._emit(lo, hi, fq, f, walking, conf, sd))
        st.tentative = []
        return out

    def _release_held(self, freq_hz: float) -> list[StepHop]:
        """The gait resumed: the held span was walking, but not periodic enough for its cadence to be
        read from the spectrum (a turn changes the step length and timing; a pause to pick something up
        has fewer, slower steps). Its steps are counted one by one instead: peaks of ``|a|`` low-passed
        at ``bridge_cutoff_hz`` (zero phase over the held span, padded by half a second each side), at
        least ``1 / (1.5 f)`` apart for the walking cadences ``f`` either side, with a prominence of at
        least ``bridge_prominence`` times the standard deviation of the low-passed signal; each hop
        (walking, confidence ``coast_confidence``) gets the peaks inside it."""
        st = self._st
        if not st.held:
            return []
        p = self.params
        c = p.coast_confidence
        lo0, hi1 = st.held[0][0], st.held[-1][1]
        pad = int(round(0.5 * st.grid_hz))
        a = max(st.buffer_start, lo0 - pad)
        b = min(st.n_grid, hi1 + pad)
        seg = self._grid_values(a, b)
        peaks = np.zeros(0, dtype=np.int64)
        lp = _lowpass_design(4, min(p.bridge_cutoff_hz, 0.45 * st.grid_hz), st.grid_hz)
        if len(seg) > lp.pad:
            y = _filtfilt(lp, seg - seg.mean())
            f_hi = max(st.walk_freq_hz, freq_hz)
            dist = max(1, int(round(st.grid_hz / (1.5 * f_hi))))
            peaks, _ = find_peaks(y, distance=dist, prominence=p.bridge_prominence * float(y.std()))
            peaks = peaks + a
        out = []
        # peaks in each hop (find_peaks gives them in increasing order)
        n_in = (np.searchsorted(peaks, [h[1] for h in st.held]) - np.searchsorted(peaks, [h[0] for h in st.held])).tolist()
        for (lo, hi, fq, *_), n in zip(st.held, n_in):
            dur = (hi - lo) / st.grid_hz
            out.append(self._emit(lo, hi, fq, n / dur, True, c, (1.0 - c) * max(n, 1.0)))
        st.held = []
        return out

    def _drop_held(self) -> list[StepHop]:
        """The gait did not resume: the held hops are emitted as they were judged on their own."""
        st = self._st
        out = [self._emit(*h) for h in st.held]
        st.held = []
        return out

    def _emit(self, lo: int, hi: int, freq_hz: float, count_hz: float, walking: bool, confidence: float,
              steps_std: float) -> StepHop:
        st = self._st
        dur = (hi - lo) / st.grid_hz
        steps = count_hz * dur if walking else 0.0
        st.total_steps += steps
        st.walking_s += dur if walking else 0.0
        st.last_freq_hz = freq_hz
        st.last_walking = walking
        st.last_confidence = confidence
        st.count_freq_hz = count_hz if walking else 0.0
        st.count_confidence = confidence
        t0, fs = st.t0_ns, st.grid_hz      # _grid_time, inline
        assert t0 is not None
        return StepHop(t0 + int(round(lo * 1e9 / fs)), t0 + int(round(hi * 1e9 / fs)), steps, freq_hz, walking,
                       confidence, steps_std)

    def _motion_std(self, lo: int, hi: int) -> float:
        """Standard deviation of the grid samples over ``motion_window_s`` centred on ``[lo, hi)``
        (clipped to the samples held), m/s²."""
        st = self._st
        d = self._get_design()
        assert d is not None
        pad = max(0, (d.n_m - (hi - lo)) // 2)
        seg = self._grid_values(max(st.buffer_start, lo - pad), min(st.n_grid, hi + pad))
        return float(seg.std()) if len(seg) > 1 else 0.0

    def _count_span(self, lo: int, hi: int, walking: bool, freq_hz: float, confidence: float) -> list[StepHop]:
        """Head or tail of a segment ``[lo, hi)``, which no window is centred on: hop-sized pieces,
        each counted at ``freq_hz`` (with ``confidence``) if ``walking`` and moving, else 0."""
        return [self._emit(*h) for h in self._span_hops(lo, hi, walking, freq_hz, confidence)]

    def _span_hops(self, lo: int, hi: int, walking: bool, freq_hz: float,
                   confidence: float) -> list[tuple[int, int, float, float, bool, float, float]]:
        """The pieces of :meth:`_count_span`, as ``_emit`` arguments."""
        d = self._get_design()
        assert d is not None
        out: list[tuple[int, int, float, float, bool, float, float]] = []
        p = self.params
        k = lo
        while k < hi:
            e = min(hi, k + d.n_h)
            if hi - e < d.n_h // 2:
                e = hi                       # no sliver at the end
            moving = self._motion_std(k, e) >= p.min_motion_std_m_s2
            dur = (e - k) / self._st.grid_hz
            if walking and moving:
                out.append((k, e, freq_hz, freq_hz, True, confidence, (1.0 - confidence) * freq_hz * dur))
            else:
                out.append((k, e, freq_hz, 0.0, False, 1.0 if not moving else p.coast_confidence,
                            0.0 if not moving else (1.0 - p.coast_confidence) * freq_hz * dur))
            k = e
        return out

    def _flush_segment(self) -> list[StepHop]:
        st = self._st
        d = self._get_design()
        out: list[StepHop] = self._drop_held() + self._drop_tentative()
        if d is not None and st.t0_ns is not None:
            if st.next_window > 0:
                lo = (st.next_window - 1) * d.n_h + d.offset + d.n_h
                hi = st.n_grid
                if hi > lo:
                    # counted at the last cadence only after a hop counted from its own walking
                    # window (confidence 1), not after a coasted one: the segment ends inside a stop
                    f = st.count_freq_hz if st.count_freq_hz > 0 else st.last_freq_hz
                    walking = st.count_freq_hz > 0 and st.count_confidence >= 1.0
                    out += self._count_span(lo, hi, walking, f, st.count_confidence)
        self._ahead = None
        self._grid_ahead = None
        st.walk_end = None
        st.coast_end = None
        st.walk_freq_hz = 0.0
        st.walk_autocorr = 0.0
        st.t0_ns = None
        st.n_grid = 0
        st.buffer = []
        st.buffer_start = 0
        st.next_window = 0
        return out


def stepometer_batch(stamps_ns: ArrayLike, acc: ArrayLike, params: StepometerParams | None = None, *,
                     heading_stamps_ns: ArrayLike | None = None, heading_rad: ArrayLike | None = None) -> list[StepHop]:
    """Whole recording at once: ``stamps_ns`` (N,) int ns, ``acc`` (N, 3) m/s²; optionally headings
    (M,) int ns / rad for the turn test. Returns the hops (the same as feeding :class:`Stepometer`
    sample by sample, each heading before the accelerometer samples at or after its stamp, and
    calling ``finish()``)."""
    s = Stepometer(params)
    t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    a = np.asarray(acc, dtype=float)
    if heading_stamps_ns is None or heading_rad is None:
        return s.update_many(t, a) + s.finish()
    ht = np.asarray(heading_stamps_ns, dtype=np.int64).reshape(-1)
    hy = np.asarray(heading_rad, dtype=float).reshape(-1)
    cut = np.searchsorted(t, ht, side="left")          # acc samples before each heading
    hops: list[StepHop] = []
    prev = 0
    for k, c in enumerate(cut):
        if c > prev:
            hops += s.update_many(t[prev:c], a[prev:c])
            prev = int(c)
        s.add_heading(int(ht[k]), float(hy[k]))
    if prev < len(t):
        hops += s.update_many(t[prev:], a[prev:])
    return hops + s.finish()


def total_steps(hops: list[StepHop]) -> float:
    return float(sum(h.steps for h in hops))
