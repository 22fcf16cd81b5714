"""Stepometer: the hops do not depend on how the samples are cut into calls, nor on the offline
look-ahead (:meth:`Stepometer.prefetch`) — bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.imu.stepometer import Stepometer
from indoor_loc.imu.step_spectrum import _ANALYSIS_BLOCK, WindowDesign, analyse_windows
from indoor_loc.imu.stepometer_types import StepometerParams
from test_stepometer import walk_signal, walk_turn_walk


@pytest.fixture
def rng():
    return np.random.default_rng(20261123)


def _recording(rng):
    """A walk with a turn and a stop, a still phone, a 3 s gap, a second walk with jittered stamps."""
    s1, a1, _ = walk_turn_walk(rng, turn_s=2.0, resume=False)
    s2, a2 = walk_signal(rng, duration_s=25.0, rate_hz=100.0)
    return np.concatenate((s1, s2 - s2[0] + s1[-1] + 3 * 10**9)), np.concatenate((a1, a2))


def _runs_and_reference(rng, run_len):
    """The test recording cut into runs of ``run_len`` (low, high) samples, and the stepometer fed
    by update() sample by sample with its hops (the reference)."""
    stamps, acc = _recording(rng)
    cuts = [0]
    while cuts[-1] < len(stamps):
        cuts.append(min(len(stamps), cuts[-1] + int(rng.integers(*run_len))))
    one = Stepometer()
    ref = [h for t, a in zip(stamps, acc) for h in one.update(int(t), a)] + one.finish()
    return stamps, acc, cuts, one, ref


def _steady_feed(s: Stepometer, stamps, acc, cuts, *, look_ahead: bool, on_run=None, on_quiet=None):
    """Feed as the offline IMU stage does: per run (``cuts``), the steady part through
    quiet_count/extend_steady (one window-completing sample at a time), optionally announced first
    with prefetch; whatever is not steady (start, gaps) through update(). ``on_run(t)`` is called
    after each run's prefetch and ``on_quiet(i, quiet)`` with each quiet_count answer."""
    hops = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        t, x = stamps[a:b], acc[a:b]
        if look_ahead:
            s.prefetch(t, x)
        if on_run is not None:
            on_run(t)
        i = 0
        while i < len(t):
            quiet = Stepometer.quiet_count(s, t[i:])
            if on_quiet is not None:
                on_quiet(i, quiet)
            if quiet is None:
                hops += s.update(int(t[i]), x[i])
                i += 1
                continue
            j = min(i + quiet, len(t) - 1)
            hops += s.extend_steady(t[i:j + 1], x[i:j + 1])
            i = j + 1
    return hops + s.finish()


def _key(hops):
    return [tuple(h) for h in hops]


def test_batched_window_analysis_equals_one_window_at_a_time(rng):
    """analyse_windows on a block of windows gives each row exactly what it gives alone (more rows
    than it analyses together, so a block boundary is crossed)."""
    d = WindowDesign.make(StepometerParams(), 100.0)
    stamps, acc = walk_signal(rng, duration_s=30.0)
    mag = np.linalg.norm(acc, axis=1)
    wins = np.lib.stride_tricks.sliding_window_view(mag, d.n_w)[:: d.n_h]
    assert len(wins) > _ANALYSIS_BLOCK
    together = analyse_windows(wins, d, StepometerParams())
    alone = [analyse_windows(w[None, :], d, StepometerParams())[0] for w in wins]
    assert together == alone


def test_chunks_of_one_to_three_samples_equal_one_sample_at_a_time(rng):
    """update_many with runs of 1-3 samples (what a merged replay of overlapping walks hands each
    user's stepometer) gives the per-sample update() hops, bit for bit."""
    stamps, acc = _recording(rng)
    one = Stepometer()
    ref = [h for t, a in zip(stamps, acc) for h in one.update(int(t), a)] + one.finish()
    small = Stepometer()
    hops, k = [], 0
    while k < len(stamps):
        n = int(rng.integers(1, 4))
        hops += small.update_many(stamps[k: k + n], acc[k: k + n])
        k += n
    hops += small.finish()
    assert sum(h.steps for h in ref) > 60
    assert _key(hops) == _key(ref)
    assert small.state() == one.state()


@pytest.mark.parametrize("run_len", [(1, 4), (20, 200), (300, 2000)])
def test_look_ahead_changes_nothing(rng, run_len):
    """The steady path with prefetch (windows analysed together) equals it without, and equals
    update() sample by sample: the same hops and final state, bit for bit, for runs of 1-3 samples
    (no window analysed ahead), of a few windows and of many."""
    stamps, acc, cuts, one, ref = _runs_and_reference(rng, run_len)
    plain, ahead = Stepometer(), Stepometer()
    assert _key(_steady_feed(plain, stamps, acc, cuts, look_ahead=False)) == _key(ref)
    assert _key(_steady_feed(ahead, stamps, acc, cuts, look_ahead=True)) == _key(ref)
    assert ahead.state() == plain.state() == one.state()


def test_look_ahead_on_other_samples_is_not_used(rng):
    """A look-ahead announced with samples other than those then fed (a caller that changed its mind,
    a rejected message) is never used: the windows actually fed are analysed."""
    stamps, acc = walk_signal(rng, duration_s=30.0)
    ref_s = Stepometer()
    ref = ref_s.update_many(stamps, acc) + ref_s.finish()
    s = Stepometer()
    hops = s.update_many(stamps[:500], acc[:500])
    assert s.prefetch(stamps[500:], acc[500:] * 1.5) > 2          # different values: analysed ahead
    hops += s.update_many(stamps[500:], acc[500:]) + s.finish()
    assert _key(hops) == _key(ref)
    # the windows announced correctly are used (same hops either way)
    s2 = Stepometer()
    hops2 = s2.update_many(stamps[:500], acc[:500])
    assert s2.prefetch(stamps[500:], acc[500:]) > 2
    hops2 += s2.update_many(stamps[500:], acc[500:]) + s2.finish()
    assert _key(hops2) == _key(ref)


def test_look_ahead_stops_at_a_gap_or_bad_sample(rng):
    """Only the steady leading part is analysed ahead: nothing without a running segment, nothing
    past a NaN or a gap longer than max_gap_s."""
    stamps, acc = walk_signal(rng, duration_s=20.0)
    s = Stepometer()
    assert s.prefetch(stamps, acc) == 0                           # rate not known yet
    s.update_many(stamps[:100], acc[:100])
    bad = acc[100:].copy()
    bad[1] = np.nan
    assert s.prefetch(stamps[100:], bad) == 0
    gap = stamps[100:].copy()
    gap[2:] += 2 * 10**9
    assert s.prefetch(gap, acc[100:]) == 0
    assert s.prefetch(stamps[100:], acc[100:]) > 10


@pytest.mark.parametrize("run_len", [(20, 200), (300, 2000)])
def test_quiet_plan_counts_equal_quiet_count(rng, run_len):
    """quiet_plan (one look at a run) answers each quiet_count of the run's steady feed exactly,
    from its lookup (not by falling back to quiet_count), and the hops stay those of update()."""
    stamps, acc, cuts, one, ref = _runs_and_reference(rng, run_len)
    s = Stepometer()
    fallbacks = []
    s.quiet_count = lambda t: fallbacks.append(len(t)) or Stepometer.quiet_count(s, t)   # type: ignore[method-assign]
    plans, checked = [None], [0]

    def check(i, quiet):
        n_fallbacks = len(fallbacks)
        assert plans[0].count(i) == quiet
        assert len(fallbacks) == n_fallbacks
        checked[0] += 1

    hops = _steady_feed(s, stamps, acc, cuts, look_ahead=True,
                        on_run=lambda t: plans.__setitem__(0, s.quiet_plan(t)),
                        on_quiet=lambda i, quiet: plans[0] is not None and check(i, quiet))
    assert checked[0] > 50
    assert _key(hops) == _key(ref)
    assert s.state() == one.state()


def test_grid_ahead_used_only_for_the_samples_announced(rng):
    """extend_steady takes its grid values from the look-ahead only when fed exactly the samples
    announced: with other values announced it computes them (no hit), with the same it reuses
    them (hits); the hops are those of update() either way."""
    stamps, acc = walk_signal(rng, duration_s=30.0)
    one = Stepometer()
    ref = [h for t, a in zip(stamps, acc) for h in one.update(int(t), a)] + one.finish()
    for announced, want_hits in ((acc[500:] * 1.5, False), (acc[500:], True)):
        s = Stepometer()
        hits = []

        def counted(t, a, s=s, hits=hits):
            got = Stepometer._grid_from_ahead(s, t, a)
            hits.append(got is not None)
            return got
        s._grid_from_ahead = counted  # type: ignore[method-assign]
        hops = [h for t, a in zip(stamps[:500], acc[:500]) for h in s.update(int(t), a)]
        assert s.prefetch(stamps[500:], announced) > 2
        t, x = stamps[500:], acc[500:]
        i = 0
        while i < len(t):
            quiet = s.quiet_count(t[i:])
            assert quiet is not None
            j = min(i + quiet, len(t) - 1)
            hops += s.extend_steady(t[i:j + 1], x[i:j + 1])
            i = j + 1
        assert _key(hops + s.finish()) == _key(ref)
        assert s.state() == one.state()
        assert len(hits) > 10 and (all(hits) if want_hits else not any(hits))


class _GeneralCount(Stepometer):
    """The reference: every hop through the general path (_count, _emit)."""

    def _walk_on(self, j, lo, hi, est):
        return None


def test_walking_run_short_path_equals_the_general_count():
    """A clearly periodic walking run's hops are counted by a short path (_walk_on); the general path
    (_count, _emit) gives the same hops and state, bit for bit, through walking, a turn, stops and a
    gap."""
    rng = np.random.default_rng(12345)       # a turn that is bridged
    parts = [walk_turn_walk(rng)[:2], walk_turn_walk(rng, resume=False)[:2], walk_signal(rng, duration_s=30.0)]
    t0 = 0
    stamps, acc = [], []
    for t, a in parts:                       # one after another, 3 s apart (a gap: a new segment)
        stamps.append(t - t[0] + t0)
        acc.append(a)
        t0 = int(stamps[-1][-1]) + 3_000_000_000
    t, a = np.concatenate(stamps), np.concatenate(acc)
    runs = []
    for kind in (Stepometer, _GeneralCount):
        s = kind()
        hops = s.update_many(t[:9000], a[:9000]) + s.update_many(t[9000:], a[9000:]) + s.finish()
        runs.append((hops, s.state()))
    (h_in, st_in), (h_gen, st_gen) = runs
    assert sum(h.walking and h.confidence == 1.0 for h in h_in) > 100
    assert any(h.confidence == 0.5 for h in h_in)          # the bridged turn went through _count
    assert h_in == h_gen
    assert st_in == st_gen
