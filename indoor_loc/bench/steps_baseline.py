"""Plain peak-detection step counter: the baseline the FFT stepometer is measured against.

Offline (zero-phase) by construction: ``|a|`` is resampled onto a uniform grid, low-passed at
``cutoff_hz`` (4th-order Butterworth, forward-backward), and every local maximum at least
``min_interval_s`` after the previous one and ``min_height_m_s2`` above the recording's mean of the
filtered signal counts one step.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import butter, find_peaks, sosfiltfilt


def peak_steps(stamps_ns, acc, *, cutoff_hz: float = 3.0, min_interval_s: float = 0.3,
               min_height_m_s2: float = 0.2, order: int = 4, max_gap_s: float = 1.0) -> np.ndarray:
    """Stamps (int ns) of the detected steps. ``stamps_ns`` (N,) non-decreasing, ``acc`` (N, 3) m/s².
    Gaps longer than ``max_gap_s`` split the recording into segments counted separately."""
    t = np.asarray(stamps_ns, dtype=np.int64)
    a = np.asarray(acc, dtype=float)
    cuts = np.flatnonzero(np.diff(t) > max_gap_s * 1e9) + 1
    if len(cuts):
        parts = [peak_steps(tt, aa, cutoff_hz=cutoff_hz, min_interval_s=min_interval_s,
                            min_height_m_s2=min_height_m_s2, order=order, max_gap_s=max_gap_s)
                 for tt, aa in zip(np.split(t, cuts), np.split(a, cuts))]
        return np.concatenate(parts)
    if len(t) < 16 or t[-1] - t[0] < 1e9:
        return np.zeros(0, np.int64)
    rel = (t - t[0]) * 1e-9
    dt = np.diff(rel)
    fs = 1.0 / float(np.median(dt[dt > 0]))
    grid = np.arange(0.0, rel[-1], 1.0 / fs)
    m = np.interp(grid, rel, np.linalg.norm(a, axis=1))
    sos = butter(order, cutoff_hz, fs=fs, output="sos")
    y = sosfiltfilt(sos, m)
    peaks, _ = find_peaks(y, distance=max(1, int(round(min_interval_s * fs))),
                          height=float(np.mean(y)) + min_height_m_s2)
    return t[0] + np.round(grid[peaks] * 1e9).astype(np.int64)
