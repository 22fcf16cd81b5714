"""FFT stepometer (SPEC §1.1, seed 001 §3.1): step frequency of the accelerometer magnitude.

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
import math
from dataclasses import dataclass, field as dc_field
from typing import NamedTuple

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

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
    f_max_hz: float = field(2.2, "highest step frequency counted as walking, Hz")
    harmonics: int = field(8, "stride harmonics k f/2, k = 1..H, summed in the harmonic spectrum "
                              "(H = 8 reaches 4x the cadence); 1 = plain largest peak in the band")
    odd_harmonic_weight: float = field(0.5, "weight of the odd stride harmonics (f/2, 3f/2, ...) "
                                            "relative to the step harmonics, 0..1")
    search_margin: float = field(1.15, "the harmonic-sum peak is searched over the band widened by "
                                       "this factor on both ends; a peak outside the band = not walking")
    min_autocorr: float = field(0.3, "minimum normalised autocorrelation at the stride lag 2/f "
                                     "(±15 %) for walking, -1..1")
    min_std_m_s2: float = field(0.5, "minimum standard deviation of |a| in the window for walking, m/s²")
    zero_pad: int = field(8, "FFT length >= zero_pad x window samples (power of two)")
    grid_hz: float = field(0.0, "resampling rate, Hz; 0 = the median input rate of the first "
                                "rate_samples samples")
    rate_samples: int = field(32, "samples used to estimate the input rate when grid_hz = 0")
    max_gap_s: float = field(1.0, "a larger gap between samples ends the current segment (its tail "
                                  "is flushed) and starts a new one, s")

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
        require(self.min_std_m_s2 >= 0, n, "min_std_m_s2", ">= 0", self.min_std_m_s2)
        require(isinstance(self.zero_pad, int) and 1 <= self.zero_pad <= 64, n, "zero_pad",
                "an int in [1, 64]", self.zero_pad)
        require(self.grid_hz == 0 or 10.0 <= self.grid_hz <= 2000.0, n, "grid_hz",
                "0 (auto) or in [10, 2000]", self.grid_hz)
        require(isinstance(self.rate_samples, int) and self.rate_samples >= 2, n, "rate_samples",
                "an int >= 2", self.rate_samples)
        require(self.max_gap_s > 0, n, "max_gap_s", "> 0", self.max_gap_s)


class StepHop(NamedTuple):
    """Steps counted over ``[t_start_ns, t_end_ns)``: ``steps`` = ``freq_hz`` x duration when
    ``walking`` (else 0); ``freq_hz`` is the window's step frequency estimate (also when not walking)."""
    t_start_ns: int
    t_end_ns: int
    steps: float
    freq_hz: float
    walking: bool


class WindowEstimate(NamedTuple):
    """Spectral analysis of one window: refined step frequency (Hz), walking decision, the
    stride-lag autocorrelation (1) and the standard deviation of |a| (m/s²)."""
    freq_hz: float
    walking: bool
    autocorr: float
    std_m_s2: float


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
    taper: np.ndarray        # (n_w,)
    cand: np.ndarray         # (C,) candidate step frequencies, Hz
    i0: np.ndarray           # (H, C) lower FFT bin of each harmonic of each candidate
    frac: np.ndarray         # (H, C) interpolation fraction
    weight: np.ndarray       # (H, 1)

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
        return _Design(fs, n_w, n_h, offset, n_fft, taper, cand, i0, idx - i0, weight)


def amplitude_spectrum(windows: np.ndarray, design: _Design) -> np.ndarray:
    """Amplitude spectrum (m/s², one-sided sinusoid amplitude) of mean-removed, Hann-tapered,
    zero-padded windows. ``windows`` (N, n_w) -> (N, n_fft//2 + 1); bin spacing fs/n_fft Hz."""
    x = windows - windows.mean(axis=1, keepdims=True)
    return np.abs(np.fft.rfft(x * design.taper, design.n_fft, axis=1)) * (2.0 / design.taper.sum())


def harmonic_score(power: np.ndarray, design: _Design) -> np.ndarray:
    """Harmonic sum ``S(f) = Σ_k w_k P(k f/2)`` over the candidate grid: (N, n_bins) -> (N, C)."""
    vals = power[:, design.i0] * (1.0 - design.frac) + power[:, design.i0 + 1] * design.frac
    return np.einsum("nhc,hk->nc", vals, design.weight)


def analyse_windows(windows: np.ndarray, design: _Design, p: StepometerParams) -> list[WindowEstimate]:
    """Step frequency and walking decision for each row of ``windows`` (N, n_w) of |a| in m/s²."""
    windows = np.atleast_2d(np.asarray(windows, dtype=float))
    n = len(windows)
    if n == 0:
        return []
    power = amplitude_spectrum(windows, design) ** 2
    score = harmonic_score(power, design)
    c = len(design.cand)
    j = np.clip(np.argmax(score, axis=1), 1, c - 2)
    r = np.arange(n)
    a, b, cc = score[r, j - 1], score[r, j], score[r, j + 1]
    den = a - 2.0 * b + cc
    safe = np.where(den < 0, den, -1.0)
    delta = np.where(den < 0, 0.5 * (a - cc) / safe, 0.0)
    f = design.cand[j] + np.clip(delta, -1.0, 1.0) * CANDIDATE_STEP_HZ
    in_band = (f >= p.f_min_hz) & (f <= p.f_max_hz)
    # Unbiased normalised autocorrelation (Wiener-Khinchin, zero-padded to avoid wrap-around).
    x = windows - windows.mean(axis=1, keepdims=True)
    n_w = design.n_w
    spec = np.fft.rfft(x, 2 * n_w, axis=1)
    acf = np.fft.irfft(spec.real ** 2 + spec.imag ** 2, 2 * n_w, axis=1)[:, :n_w]
    acf = acf / (n_w - np.arange(n_w))
    acf0 = acf[:, :1]
    acf = np.divide(acf, acf0, out=np.zeros_like(acf), where=acf0 > 0)
    lag = 2.0 / np.maximum(f, 1e-6) * design.fs
    lo = np.clip(np.floor(lag * (1 - ACF_LAG_TOL)).astype(np.int64), 1, n_w - 1)
    hi = np.clip(np.ceil(lag * (1 + ACF_LAG_TOL)).astype(np.int64) + 1, 2, n_w)
    lags = np.arange(n_w)
    mask = (lags[None, :] >= lo[:, None]) & (lags[None, :] < hi[:, None])
    ac = np.where(mask, acf, -np.inf).max(axis=1)
    ac = np.where(np.isfinite(ac), ac, -1.0)
    std = x.std(axis=1)
    walking = in_band & (ac >= p.min_autocorr) & (std >= p.min_std_m_s2)
    return [WindowEstimate(float(f[i]), bool(walking[i]), float(ac[i]), float(std[i])) for i in range(n)]


# ----------------------------------------------------------------------------------------------
# Online estimator
# ----------------------------------------------------------------------------------------------
@dataclass
class StepometerState:
    """Everything :class:`Stepometer` needs to resume (save with :meth:`Stepometer.state`)."""
    grid_hz: float = 0.0                 # resampling rate in force (0 = not yet known)
    pending_t: list = dc_field(default_factory=list)   # raw samples waiting for the rate estimate
    pending_m: list = dc_field(default_factory=list)
    t0_ns: int | None = None             # stamp of grid index 0 of the current segment
    n_grid: int = 0                      # grid samples produced in the current segment
    last_t_ns: int | None = None         # last raw sample (for interpolation)
    last_m: float = 0.0
    buffer: list = dc_field(default_factory=list)   # last grid samples of |a|, m/s²
    buffer_start: int = 0                # grid index of buffer[0]
    next_window: int = 0                 # index j of the next window to analyse
    last_freq_hz: float = 0.0
    last_walking: bool = False
    total_steps: float = 0.0
    walking_s: float = 0.0
    samples: int = 0

    def copy(self) -> "StepometerState":
        return dataclasses.replace(self, pending_t=list(self.pending_t), pending_m=list(self.pending_m),
                                   buffer=list(self.buffer))


def _magnitude(acc) -> np.ndarray:
    a = np.asarray(acc, dtype=float)
    return np.sqrt(np.sum(a * a, axis=-1))


class Stepometer:
    """Online FFT stepometer. Feed samples with :meth:`update` (one) or :meth:`update_many` (a
    chunk); each returns the :class:`StepHop` s completed so far, in time order. :meth:`finish`
    flushes the tail at the end of the stream. ``state()``/``set_state()`` save and resume."""

    def __init__(self, params: StepometerParams | None = None) -> None:
        self.params = params if params is not None else StepometerParams()
        self.params.validate()
        self._st = StepometerState(grid_hz=float(self.params.grid_hz))
        self._design: _Design | None = None

    # -- state ------------------------------------------------------------------------------------
    def state(self) -> StepometerState:
        return self._st.copy()

    def set_state(self, state: StepometerState) -> None:
        self._st = state.copy()
        self._design = None

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
    def update(self, stamp_ns: int, acc) -> list[StepHop]:
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

    def update_many(self, stamps_ns, acc) -> list[StepHop]:
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
            st.pending_t.extend(int(v) for v in t)
            st.pending_m.extend(float(v) for v in m)
            if len(st.pending_t) <= self.params.rate_samples:
                return []
            dt = np.diff(np.asarray(st.pending_t[: self.params.rate_samples + 1], dtype=np.int64))
            dt = dt[dt > 0]
            if len(dt) == 0:
                return []
            st.grid_hz = float(min(2000.0, max(10.0, 1e9 / float(np.median(dt)))))
            t = np.asarray(st.pending_t, dtype=np.int64)
            m = np.asarray(st.pending_m, dtype=float)
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
            prev_t = np.concatenate(([st.last_t_ns], tt[:-1]))
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
        t_all = np.concatenate(([st.last_t_ns], t)).astype(np.int64)
        m_all = np.concatenate(([st.last_m], m))
        # grid indices k with last_t < t_k <= t[-1]; t_k = t0 + k/fs
        rel_end = (int(t[-1]) - st.t0_ns) * 1e-9 * st.grid_hz
        k_end = int(math.floor(rel_end + 1e-9))
        if k_end >= st.n_grid:
            k = np.arange(st.n_grid, k_end + 1)
            tk = st.t0_ns + np.round(k * (1e9 / st.grid_hz)).astype(np.int64)
            # relative times (float seconds from last_t) keep the interpolation exact enough
            base = t_all[0]
            new = np.interp((tk - base).astype(float), (t_all - base).astype(float), m_all)
            st.buffer.extend(new.tolist())
            st.n_grid = k_end + 1
        # keep the last sample with the largest stamp (equal stamps: the latest value)
        st.last_t_ns, st.last_m = int(t[-1]), float(m[-1])
        return self._analyse_ready()

    def _analyse_ready(self) -> list[StepHop]:
        st = self._st
        d = self._get_design()
        assert d is not None
        n_ready = (st.n_grid - d.n_w) // d.n_h + 1 - st.next_window if st.n_grid >= d.n_w else 0
        out: list[StepHop] = []
        if n_ready > 0:
            first = st.next_window * d.n_h - st.buffer_start
            span = np.asarray(st.buffer[first: first + (n_ready - 1) * d.n_h + d.n_w], dtype=float)
            wins = sliding_window_view(span, d.n_w)[:: d.n_h]
            for est in analyse_windows(wins, d, self.params):
                j = st.next_window
                lo = j * d.n_h + d.offset
                hi = lo + d.n_h
                if j == 0:
                    lo = 0                   # head of the segment: the first window covers it
                out.append(self._count(lo, hi, est))
                st.next_window += 1
        # drop grid samples no later window needs
        keep_from = st.next_window * d.n_h
        if keep_from > st.buffer_start:
            del st.buffer[: keep_from - st.buffer_start]
            st.buffer_start = keep_from
        return out

    def _count(self, lo: int, hi: int, est: WindowEstimate) -> StepHop:
        st = self._st
        dur = (hi - lo) / st.grid_hz
        steps = est.freq_hz * dur if est.walking else 0.0
        st.total_steps += steps
        st.walking_s += dur if est.walking else 0.0
        st.last_freq_hz = est.freq_hz
        st.last_walking = est.walking
        return StepHop(self._grid_time(lo), self._grid_time(hi), steps, est.freq_hz, est.walking)

    def _flush_segment(self) -> list[StepHop]:
        st = self._st
        d = self._get_design()
        out: list[StepHop] = []
        if d is not None and st.t0_ns is not None:
            if st.next_window > 0:
                lo = (st.next_window - 1) * d.n_h + d.offset + d.n_h
                hi = st.n_grid
                if hi > lo:
                    est = WindowEstimate(st.last_freq_hz, st.last_walking, 0.0, 0.0)
                    out.append(self._count(lo, hi, est))
        st.t0_ns = None
        st.n_grid = 0
        st.buffer = []
        st.buffer_start = 0
        st.next_window = 0
        return out


def stepometer_batch(stamps_ns, acc, params: StepometerParams | None = None) -> list[StepHop]:
    """Whole recording at once: ``stamps_ns`` (N,) int ns, ``acc`` (N, 3) m/s². Returns the hops
    (the same as feeding :class:`Stepometer` sample by sample and calling ``finish()``)."""
    s = Stepometer(params)
    hops = s.update_many(stamps_ns, acc)
    return hops + s.finish()


def total_steps(hops: list[StepHop]) -> float:
    return float(sum(h.steps for h in hops))
