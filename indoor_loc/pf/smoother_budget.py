"""A bound in bytes on the particle smoother's history, whatever the input rate.

The tracker keeps, for the backward-simulation smoother, every particle set of the last
``smooth_window_s`` of stamp time (:meth:`indoor_loc.pf.tracker.GraphTracker.forget_before`): about
40 kB per 1000 particles and step, one step per ``pdr/odom`` hop and per fix. A window in time alone
makes the memory proportional to the rate of steps: the soak's ``tll_pf`` held ≈ 100 MB while it
lost half its ``pdr/odom`` on a starved machine and ≈ 190 MB once it took all of them (its one step
to 340 MB, docs/benchmarks/soak.md); a robot's odometry at 20 Hz would hold ≈ 600 MB, an adaptive
filter at ``n_max`` particles gigabytes. :class:`SmootherBudget` also keeps the history within
``max_bytes``: past it, the oldest steps go (the smoothed window then starts later; the path
before it stays filtered, as past ``smooth_window_s``) down to :data:`TRIM_TO` of the budget, so the
work is amortised. The bytes are summed exactly (the particle count may vary) every
:data:`CHECK_EVERY` steps.
"""
from __future__ import annotations

from typing import Any

#: The held bytes are summed once per this many new steps (the history grows by one step a call at most).
CHECK_EVERY = 32
#: Past the budget the history is cut to this fraction of it (amortised: the next cut is many steps later).
TRIM_TO = 0.8


def step_bytes(step: Any) -> int:
    """Bytes of one smoother step's particle arrays."""
    n = step.xy.nbytes + step.log_w.nbytes + step.scale.nbytes + step.yaw_offset.nbytes
    for opt in (step.redrawn_log_q, step.z):
        if opt is not None:
            n += opt.nbytes
    return int(n)


def held_bytes(tracker: Any) -> int:
    """Bytes of every step the tracker keeps for smoothing (closed segments and the open history)."""
    return sum(step_bytes(s) for seg in tracker.segments + [tracker.history] for s in seg)


class SmootherBudget:
    """Keeps a tracker's smoother history within ``max_bytes`` (0 = no bound); see the module doc."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self._since = 0
        self.trimmed_steps = 0          # steps dropped for the budget (before their time window ended)
        self.held = 0                   # bytes at the last check

    def after_step(self, tracker: Any, keep_estimates: int) -> None:
        """Called after each new step: every :data:`CHECK_EVERY` calls, sum the bytes held and, past
        the budget, drop the oldest steps down to :data:`TRIM_TO` of it."""
        if self.max_bytes <= 0:
            return
        self._since += 1
        if self._since < CHECK_EVERY:
            return
        self._since = 0
        steps = [s for seg in tracker.segments + [tracker.history] for s in seg]
        sizes = [step_bytes(s) for s in steps]
        self.held = sum(sizes)
        if self.held <= self.max_bytes:
            return
        target = TRIM_TO * self.max_bytes
        total, k = 0, len(steps)
        while k > 0 and total + sizes[k - 1] <= target:    # the newest steps that fit the target
            k -= 1
            total += sizes[k]
        if k >= len(steps):           # not even the newest step fits: keep it (the filter's present)
            k = len(steps) - 1
        cutoff = steps[k].stamp_ns
        before = len(steps)
        tracker.forget_before(cutoff, keep_estimates)
        after = len(tracker.history) + sum(len(seg) for seg in tracker.segments)
        self.trimmed_steps += before - after
        self.held = held_bytes(tracker)
