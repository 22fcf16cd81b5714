"""The stepometer's offline look-ahead (:class:`StepLookAhead`, mixed into
:class:`indoor_loc.imu.stepometer.Stepometer`): how many samples complete no window (``quiet_count``,
``quiet_plan``), runs of such samples taken at once (``extend_steady``), and the windows a chunk of
samples will complete analysed together ahead of it (``prefetch``). Each gives the hops and state of
feeding the samples one by one: the same floating-point operations in the same order, vectorised."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from indoor_loc.imu.step_spectrum import WindowEstimate, WindowDesign, analyse_windows, magnitude
from indoor_loc.imu.stepometer_types import StepHop, StepometerParams, StepometerState


class LookAhead(NamedTuple):
    """Windows analysed ahead of their samples (:meth:`Stepometer.prefetch`): segment (``t0_ns``,
    ``grid_hz``), index of the first window, the grid samples from its start, the estimates."""
    t0_ns: int
    grid_hz: float
    window: int
    span: np.ndarray
    estimates: list[WindowEstimate]


class GridAhead(NamedTuple):
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

    def __init__(self, owner: StepLookAhead, stamps: np.ndarray, first: int, t0_ns: int, grid_hz: float,
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


class StepLookAhead:
    """The look-ahead entry points of :class:`~indoor_loc.imu.stepometer.Stepometer` (offline runs)."""

    if TYPE_CHECKING:     # provided by Stepometer
        params: StepometerParams
        _st: StepometerState
        _ahead: LookAhead | None
        _grid_ahead: GridAhead | None

        def _get_design(self) -> WindowDesign | None: ...
        def _steady_grid(self, t: np.ndarray, m: np.ndarray) -> np.ndarray: ...
        def _analyse_ready(self, new: np.ndarray | None = None) -> list[StepHop]: ...

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
            m = magnitude(acc)
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
        mags = magnitude(a[:n])
        new = self._steady_grid(t[:n], mags)
        k_end = np.floor((t[:n] - st.t0_ns).astype(float) * 1e-9 * st.grid_hz + 1e-9).astype(np.int64)
        self._grid_ahead = GridAhead(st.t0_ns, st.grid_hz, st.n_grid, st.last_t_ns, st.last_m, t[:n], a[:n], mags,
                                      np.maximum(np.maximum.accumulate(k_end + 1), st.n_grid), new)
        first = st.next_window * d.n_h
        span = np.concatenate((np.asarray(st.buffer[first - st.buffer_start:], dtype=float), new))
        span = span[: (n_win - 1) * d.n_h + d.n_w]
        wins = sliding_window_view(span, d.n_w)[:: d.n_h]
        self._ahead = LookAhead(st.t0_ns, st.grid_hz, st.next_window, span,
                                 analyse_windows(wins, d, self.params))
        return n_win

    def _analysed(self, span: np.ndarray, d: WindowDesign) -> list[WindowEstimate]:
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
