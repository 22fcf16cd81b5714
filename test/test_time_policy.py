"""The one time policy every stage shares (pipeline/time_policy.py): the policy on its own, then
every stamped input port of every stage with wrongly stamped messages among valid ones, and the
clock jumps a stage must survive (a replay loop, a restarted simulation)."""
from __future__ import annotations

import copy
from collections import Counter

import pytest

from test_contract_ports import CASES, build_stage, world  # noqa: F401  (world: the module fixture it uses)
from test_ports_property import LIGHTER, USER, Run, _leaves, _valid_stream, valid_streams
from indoor_loc.errors import InvalidInputError
from indoor_loc.pipeline.time_policy import Held, Order, TimeParams, TimePolicy, Verdict
from msg_adapters.time import stamp_from_ns

SEC = 1_000_000_000
YEAR_2036_NS = 2_082_758_400 * SEC


# -- the policy on its own --------------------------------------------------------------------------
def _policy(**kw) -> TimePolicy:
    return TimePolicy(TimeParams(**kw))


def _feed(p: TimePolicy, topic: str, stamps, now=0, order=Order.STRICT, user="") -> list:
    """Judge ``stamps`` as the stage driver does (hold, confirm, accept); returns each verdict or the
    rejection's reason."""
    out = []
    for s in stamps:
        try:
            v = p.judge(user, topic, s, now, order)
        except InvalidInputError as err:
            out.append(err.reason)
            continue
        if v == Verdict.HOLD:
            p.hold(user, Held(topic, None, now, s))
        elif v == Verdict.JUMP:
            for h in p.restart(user) + [Held(topic, None, now, s)]:
                p.accepted(user, h.topic, h.stamp_ns)
        else:
            if p.in_step(user, topic):
                p.drop_held(user)
            p.accepted(user, topic, s)
        out.append(v.name)
    return out


def test_future_stamps_are_rejected_against_the_clock_and_leave_the_watermark():
    p = _policy(max_future_s=10.0)
    assert _feed(p, "a", [100 * SEC, YEAR_2036_NS, 101 * SEC], now=100 * SEC) == ["PASS", "future_stamp", "PASS"]
    assert p.users[""].marks["a"] == 101 * SEC
    # no clock yet (sim time before /clock): nothing is judged ahead
    assert _feed(_policy(), "a", [YEAR_2036_NS], now=0) == ["PASS"]


def test_order_within_jump_s_by_the_topic_order():
    p = _policy()
    assert _feed(p, "s", [10 * SEC, 10 * SEC, 9 * SEC], order=Order.STRICT) == \
        ["PASS", "non_monotonic_stamp", "non_monotonic_stamp"]
    assert _feed(p, "n", [10 * SEC, 10 * SEC, 9 * SEC], order=Order.NONDECREASING) == \
        ["PASS", "PASS", "stamp_backwards"]
    assert _feed(p, "any", [10 * SEC, 9 * SEC], order=Order.ANY) == ["PASS", "PASS"]
    assert _feed(p, "x", [10 * SEC, 0, -1], order=Order.EXEMPT) == ["PASS", "PASS", "PASS"]


def test_a_jump_back_needs_jump_confirm_messages_in_step_or_the_clock():
    p = _policy(jump_s=2.0, jump_confirm=3)
    walk = [t * SEC // 2 for t in range(40, 60)]                   # 20 .. 29.5 s
    assert set(_feed(p, "a", walk)) == {"PASS"}
    # two stragglers, then the topic goes on in step: held, dropped, no jump
    assert _feed(p, "a", [1 * SEC, 1 * SEC + SEC // 2, 30 * SEC]) == ["HOLD", "HOLD", "PASS"]
    assert p.users[""].jumps == 0 and p.rejected_held == 2
    # a replay from the start: the third message in step confirms it
    assert _feed(p, "a", [1 * SEC, 1 * SEC + SEC // 2, 2 * SEC, 2 * SEC + SEC // 2]) == ["HOLD", "HOLD", "JUMP", "PASS"]
    assert p.users[""].jumps == 1 and p.users[""].marks["a"] == 2 * SEC + SEC // 2
    # far-back messages not in step with each other never confirm
    q = _policy(jump_confirm=3)
    _feed(q, "a", [100 * SEC])
    assert _feed(q, "a", [5 * SEC, 50 * SEC, 20 * SEC, 80 * SEC]) == ["HOLD"] * 4 and q.users[""].jumps == 0
    # the node's clock confirms at once: the old pass is ahead of it
    r = _policy()
    _feed(r, "a", [100 * SEC], now=100 * SEC)
    assert _feed(r, "a", [1 * SEC], now=2 * SEC) == ["JUMP"]


def test_topics_are_judged_apart_and_the_old_pass_is_fenced_after_a_jump():
    p = _policy(jump_s=2.0, jump_confirm=2)
    # a user's first scan before its first odometry (the stepometer's latency) is no jump
    assert _feed(p, "wifi/scan", [103 * SEC], order=Order.ANY) == ["PASS"]
    assert _feed(p, "pdr/odom", [100 * SEC, 101 * SEC]) == ["PASS", "PASS"]
    assert p.users[""].jumps == 0
    # a replay: odometry from 1 s confirms; the old pass's last fix, in flight, is then refused
    _feed(p, "wifi/fix", [103 * SEC], order=Order.ANY)
    assert _feed(p, "pdr/odom", [1 * SEC, 2 * SEC]) == ["HOLD", "JUMP"]
    assert _feed(p, "wifi/fix", [103 * SEC], order=Order.ANY) == ["before_jump"]
    assert _feed(p, "wifi/fix", [2 * SEC], order=Order.ANY) == ["PASS"]


def test_clock_jump_names_the_users_ahead_of_the_clock():
    p = _policy(jump_s=2.0)
    _feed(p, "a", [100 * SEC], user="ann")
    _feed(p, "a", [5 * SEC], user="ben")
    assert p.clock_jump(10 * SEC) == ["ann"]


@pytest.mark.parametrize("bad", [dict(max_future_s=0.0), dict(jump_s=0.0), dict(jump_confirm=0),
                                 dict(max_future_s=float("nan"))])
def test_bad_time_parameters_are_refused(bad):
    from indoor_loc.errors import ConfigError
    with pytest.raises(ConfigError, match=next(iter(bad))):
        TimeParams(**bad).validate()


# -- every stamped input port of every stage ----------------------------------------------------------
STAMPED = [(n, o) for n, o in CASES if not (n == "wifi_scan" and o.get("source", "topic") != "topic")]


@pytest.fixture(scope="module")
def streams(world):  # noqa: F811 (the fixture)
    return valid_streams(world)


def _restamped(msg, stamp_ns: int):
    out = copy.deepcopy(msg)
    if hasattr(out, "header"):
        out.header.stamp = stamp_from_ns(stamp_ns)
        return out
    import json
    d = json.loads(out.data)                        # a JSON scan: its stamp is in the text
    d["timestamp"] = stamp_ns / SEC
    d["stamp_ns"] = stamp_ns
    out.data = json.dumps(d)
    return out


@pytest.mark.parametrize("case", STAMPED, ids=[f"{n}{'-' + '-'.join(map(str, o.values())) if o else ''}"
                                               for n, o in STAMPED])
def test_wrongly_stamped_messages_leave_every_stage_as_without_them(world, streams, case):  # noqa: F811
    """One message (or two) of each stamped input port, copied from the valid stream with a wrong
    stamp — in 2036, 0, two 20 s back — amid the valid stream (the node's clock: the valid stamps): it
    is rejected or held and dropped, counted, never resets anything, and the outputs are exactly the
    clean stream's (before: one message stamped in 2036 made wifi_fix_node, imu_node and pdr_kf_node
    refuse every later one; one stamped 0 reset tll_pf)."""
    name, overrides = case

    def fresh():          # (a lighter filter where the stage allows: the test is about time, not accuracy)
        return build_stage(world, name, {**overrides, **LIGHTER.get(name, {})})
    clean = _valid_stream(fresh(), streams)
    base = Run(fresh(), clean)
    assert base.rejected["internal_error"] == 0, base.last_error
    for topic in sorted({t for _, t, _ in clean}):
        if topic == "initialpose":                  # not judged (a person's command)
            continue
        idx = [k for k, (_, t, _) in enumerate(clean) if t == topic]
        k = idx[len(idx) // 2]                       # a message mid-stream
        stamp, _, msg = clean[k]
        for kind, bad in (("future_2036", [YEAR_2036_NS]), ("zero", [0]),
                          ("two_20s_back", [stamp - 20 * SEC, stamp - 20 * SEC + SEC // 10])):
            if min(bad) < 0 or (topic == "wifi/scan_json" and kind == "zero"):
                continue                             # (a JSON timestamp 0 means none: the receive time)
            stream = clean[:k + 1] + [(stamp, topic, _restamped(msg, b)) for b in bad] + clean[k + 1:]
            stage = fresh()
            run = Run(stage, stream)
            assert run.rejected["internal_error"] == 0, run.last_error
            assert stage.diag.time_jumps == 0, (topic, kind)
            extra = run.rejected - base.rejected
            assert sum(extra.values()) == len(bad), (topic, kind, extra)
            assert set(extra) <= {"future_stamp", "stale_stamp", "non_monotonic_stamp", "stamp_backwards"}, extra
            assert run.outputs == base.outputs, (topic, kind)


@pytest.mark.parametrize("case", STAMPED, ids=[f"{n}{'-' + '-'.join(map(str, o.values())) if o else ''}"
                                               for n, o in STAMPED])
@pytest.mark.parametrize("clock", ["sim_time", "log_time"])
def test_a_stream_replayed_gives_the_same_outputs_twice(world, streams, case, clock):  # noqa: F811
    """The valid stream twice in a row (a bag played in a loop): the stage resets once, says so, and
    the second pass gives exactly the first pass's outputs (the multi-user back-end, which keeps the
    first track in its graph, as many poses) — with the node's clock going back with the stamps
    (``use_sim_time``: ``Stage.run_clock_jump`` between the passes, as the node's clock-jump callback
    calls it) or going on (wall or log time: the stamps confirm the jump). Before, the second pass was
    refused message by message (non_monotonic_stamp, stamp_backwards, too_late)."""
    stage = build_stage(world, *case)
    clean = _valid_stream(stage, streams)
    if clock == "log_time":
        # a topic with fewer messages than jump_confirm (the world's 10 s hold 2 scans) cannot confirm
        # a jump by its stamps alone: confirmed by as many as the stream has
        fewest = min(sum(t == topic for _, t, _ in clean) for topic in {t for _, t, _ in clean})
        if fewest < stage.params.time.jump_confirm:
            name, overrides = case
            stage = build_stage(world, name, {**overrides, "time": {"jump_confirm": max(fewest, 1)}})
    user = USER if stage.MULTI_USER else None
    span = clean[-1][0] - clean[0][0] + SEC
    at_reset: list = []                              # outputs of the jump's reset (the old pass's end), kept alive
    real_reset = stage._reset_and_restart            # (an initialpose in the stream resets too: not counted)

    def reset_and_restart(u):
        outs, held = real_reset(u)
        at_reset.extend(m for _, m in outs)
        return outs, held
    stage._reset_and_restart = reset_and_restart
    passes: list[list] = [[], []]
    for k in (0, 1):
        if k == 1 and clock == "sim_time":
            stage.run_clock_jump(span, clean[0][0])
        for stamp, topic, msg in clean:
            passes[k] += stage.process(topic, msg, stamp + (span if clock == "log_time" and k else 0), user)
    stage.run_finish()
    assert stage.diag.rejected["internal_error"] == 0, stage.diag.last_error
    assert sum(stage.diag.rejected.values()) == 0, stage.diag.rejected
    assert stage.diag.time_jumps == 1 and len(stage.take_notices()) == 1
    # map/graph is latched, sent once in a node's life
    first = [(t, tuple(_leaves(m))) for t, m in passes[0] if t != "map/graph"]
    second = [(t, tuple(_leaves(m))) for t, m in passes[1] if not any(m is r for r in at_reset)]
    if stage.MULTI_USER:
        assert [t for t, _ in second] == [t for t, _ in first]
    else:
        assert second == first


# -- a user's topics are judged apart: the demo's false jump ------------------------------------------
def test_a_first_scan_before_the_first_odometry_is_no_jump_and_no_pose_goes_back(world, streams):  # noqa: F811
    """Live, a user's first WiFi scan (and its fix) reaches the back-end and the particle filter
    seconds before its first ``pdr/odom`` (the stepometer reports a hop half a window late). Before,
    the back-end took the odometry for a clock jump back ("pdr/odom stamp jumped back 3.077 s ... the
    user starts afresh") and tll_pf's pose went back in time (603.397 -> 600.640 s)."""
    from msg_adapters.pose import pose_from_msg
    for name, first_topic in (("backend", "wifi/scan"), ("pf", "wifi/fix")):
        stage = build_stage(world, name, {})
        clean = [m for m in _valid_stream(stage, streams) if m[1] != "initialpose"]   # (a command: not here)
        firsts = [k for k, (_, t, _) in enumerate(clean) if t == first_topic][:1]
        odom = [k for k, (_, t, _) in enumerate(clean) if t == "pdr/odom"]
        assert firsts and odom and clean[firsts[0]][0] > clean[odom[0]][0] + SEC
        # the first scan/fix delivered before any odometry: arrival order, the node's clock its stamp
        order = [clean[firsts[0]]] + [m for k, m in enumerate(clean) if k != firsts[0]]
        user = USER if stage.MULTI_USER else None
        outs = []
        for stamp, topic, msg in order:
            outs += stage.process(topic, msg, max(stamp, order[0][0]), user)
            outs += stage.run_tick(max(stamp, order[0][0]))
        assert stage.diag.time_jumps == 0 and stage.take_notices() == [], name
        assert sum(stage.diag.rejected.values()) == 0, (name, stage.diag.rejected)
        poses = [pose_from_msg(m).stamp_ns for t, m in outs if t in ("pf/pose", f"backend/{USER}/pose")]
        assert poses and poses == sorted(poses), name


def test_a_constant_wrong_stamp_repeated_is_no_jump():
    """Hostile messages sharing one wrong stamp (three copies stamped 30 s back, or 0) are held and
    dropped as stragglers: a replayed pass moves on, a repeated stamp does not confirm a jump."""
    for now in (0, 100 * SEC):
        p = _policy(jump_confirm=3)
        _feed(p, "a", [99 * SEC, 100 * SEC], now=now)
        assert _feed(p, "a", [70 * SEC] * 3 + [0] * 3, now=now) == ["HOLD"] * 6
        assert _feed(p, "a", [100 * SEC + 1], now=now) == ["PASS"]
        assert p.users[""].jumps == 0 and p.rejected_held == 6


def test_a_scan_of_more_access_points_than_a_receiver_hears_is_refused_cheaply():
    import time

    import numpy as np

    from indoor_loc.bench.hostile import huge_scan
    from indoor_loc.wifi.types import WifiScan
    from msg_adapters.wifi_json import parse_json_msg, scan_to_json_msg
    from msg_adapters.wifi_scan import scan_from_msg
    msg = huge_scan(100_000)
    t0 = time.perf_counter()
    with pytest.raises(InvalidInputError) as err:
        scan_from_msg(msg)
    assert err.value.reason == "too_many_aps" and time.perf_counter() - t0 < 0.5
    assert len(scan_from_msg(huge_scan(3000))) == 3000
    n = 6000
    big = WifiScan(stamp_ns=SEC, bssid=tuple(f"02:00:00:{i >> 16 & 255:02x}:{i >> 8 & 255:02x}:{i & 255:02x}"
                                             for i in range(n)),
                   rssi_dbm=np.full(n, -70.0), freq_mhz=np.full(n, 2412.0), ssid=("x",) * n)
    with pytest.raises(InvalidInputError, match="too_many_aps"):
        parse_json_msg(scan_to_json_msg(big))


@pytest.mark.parametrize("case", STAMPED, ids=[f"{n}{'-' + '-'.join(map(str, o.values())) if o else ''}"
                                               for n, o in STAMPED])
def test_a_clock_jump_counts_each_output_once(world, streams, case):  # noqa: F811
    """What a stage returns at a clock jump (the old pass's end, held messages handed on) is counted
    once in ``out.<topic>.count`` — the fault benchmark saw imu_node count 6 pdr/odom at a loop that no
    consumer received: they had been counted twice."""
    stage = build_stage(world, *case)
    clean = _valid_stream(stage, streams)
    user = USER if stage.MULTI_USER else None
    outs = []
    for stamp, topic, msg in clean:
        outs += stage.process(topic, msg, stamp, user)
    outs += stage.run_clock_jump(clean[-1][0] - clean[0][0] + SEC, clean[0][0])
    stamp, topic, msg = clean[0]            # the new pass's first message: the user's reset (time_policy.py),
    outs += stage.process(topic, msg, stamp, user)
    outs += stage.run_finish()              # or at the input's end, if it waits for the old pass's other topics
    assert stage.diag.time_jumps == 1
    published = {t: n for t, n in stage.diag.published.items() if n}
    assert published == dict(Counter(t for t, _ in outs))
