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

import math
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy.signal import find_peaks

from indoor_loc.errors import InvalidInputError
from indoor_loc.imu.step_lookahead import GridAhead, LookAhead, StepLookAhead
from indoor_loc.imu.step_spectrum import WindowDesign, WindowEstimate, filtfilt, lowpass_design, magnitude
from indoor_loc.imu.stepometer_types import StepHop, StepometerParams, StepometerState


# ----------------------------------------------------------------------------------------------
# Online estimator
# ----------------------------------------------------------------------------------------------

def _median(values: list[float]) -> float:
    """Median of a short list (what ``np.median`` gives: the mean of the two middle values when even)."""
    v = sorted(values)
    k = len(v) // 2
    return v[k] if len(v) % 2 else (v[k - 1] + v[k]) / 2.0


class Stepometer(StepLookAhead):
    """Online FFT stepometer. Feed samples with :meth:`update` (one) or :meth:`update_many` (a
    chunk); each returns the :class:`StepHop` s completed so far, in time order. :meth:`finish`
    flushes the tail at the end of the stream. ``state()``/``set_state()`` save and resume."""

    def __init__(self, params: StepometerParams | None = None) -> None:
        self.params = params if params is not None else StepometerParams()
        self.params.validate()
        self._st = StepometerState(grid_hz=float(self.params.grid_hz))
        self._design: WindowDesign | None = None
        self._ahead: LookAhead | None = None      # windows analysed ahead (prefetch); not state
        self._grid_ahead: GridAhead | None = None  # grid values computed ahead (prefetch); not state
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

    def _get_design(self) -> WindowDesign | None:
        if self._design is None and self._st.grid_hz > 0:
            self._design = WindowDesign.make(self.params, self._st.grid_hz)
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

    # -- chunks (offline runs; the look-ahead: indoor_loc.imu.step_lookahead) --------------------
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
        m = magnitude(a)
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
        lp = lowpass_design(4, min(p.bridge_cutoff_hz, 0.45 * st.grid_hz), st.grid_hz)
        if len(seg) > lp.pad:
            y = filtfilt(lp, seg - seg.mean())
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
