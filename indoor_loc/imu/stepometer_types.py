"""Parameters, state and output of the FFT stepometer (:mod:`indoor_loc.imu.stepometer`)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field as dc_field
from typing import NamedTuple

from indoor_loc.params import field, require


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
