"""Messages stamped before the node's clock went back that reach a stage after the jump (a replay's last
samples, queued in the node while ``/clock`` goes back) are handled in the pass they were stamped in,
whatever their order with the clock-jump callback; the user is reset at its first message of the new
pass (pipeline/time_policy.py, the node's clock going back)."""
from __future__ import annotations

import pytest

from test_contract_ports import build_stage, world  # noqa: F401  (world: the module fixture it uses)
from test_ports_property import USER, _leaves, _valid_stream, valid_streams
from test_time_policy import STAMPED
from indoor_loc.errors import InvalidInputError
from indoor_loc.pipeline.time_policy import Held, Order, TimeParams, TimePolicy, Verdict

SEC = 1_000_000_000
QUEUED = 5          # the stream's last messages, taken only after the clock-jump callback


@pytest.fixture(scope="module")
def streams(world):  # noqa: F811 (the fixture)
    return valid_streams(world)


def test_the_policy_judges_the_old_epoch_by_the_clock_before_the_jump():
    p = TimePolicy(TimeParams())
    for t in (98, 99):
        assert p.judge("", "a", t * SEC, t * SEC, Order.STRICT) == Verdict.PASS
        p.accepted("", "a", t * SEC)
    assert p.clock_jump(10 * SEC, 90 * SEC) == [""]
    # queued before the jump: 100 s is 90 s ahead of the new clock, but the old pass's next stamp
    assert p.judge("", "a", 100 * SEC, 10 * SEC, Order.STRICT) == Verdict.PASS
    p.accepted("", "a", 100 * SEC)
    with pytest.raises(Exception, match="not after"):        # still judged by the old pass's watermark
        p.judge("", "a", 100 * SEC, 10 * SEC, Order.STRICT)
    # the first stamp of the new clock's present: the user's reset
    assert p.judge("", "a", 10 * SEC, 10 * SEC, Order.STRICT) == Verdict.EPOCH
    p.restart("")
    assert p.judge("", "a", 10 * SEC, 10 * SEC, Order.STRICT) == Verdict.PASS


def test_a_new_epoch_message_waits_until_every_source_of_the_old_pass_has_moved_on():
    """Topics of one user reach a node in any order with each other: a message of the new pass on one
    topic is held while another topic may still bring the old pass's last messages."""
    p = TimePolicy(TimeParams())
    for t in (98, 99):
        for topic in ("a", "b"):
            assert p.judge("", topic, t * SEC, t * SEC, Order.STRICT) == Verdict.PASS
            p.accepted("", topic, t * SEC)
    p.clock_jump(10 * SEC, 90 * SEC)
    assert p.judge("", "b", 10 * SEC, 10 * SEC, Order.STRICT) == Verdict.EPOCH_HOLD    # b moved on, a not yet
    assert p.judge("", "a", 100 * SEC, 10 * SEC, Order.STRICT) == Verdict.PASS          # a's last, old pass
    p.accepted("", "a", 100 * SEC)
    with pytest.raises(InvalidInputError) as err:                     # b has moved on: its old pass is over
        p.judge("", "b", 100 * SEC, 10 * SEC, Order.STRICT)
    assert err.value.reason == "before_jump"
    assert p.judge("", "a", 10 * SEC + 1, 10 * SEC, Order.STRICT) == Verdict.EPOCH
    # ... or the node's clock runs jump_s past the jump: whatever was queued has come
    q = TimePolicy(TimeParams())
    for topic in ("a", "b"):
        q.judge("", topic, 99 * SEC, 99 * SEC, Order.STRICT)
        q.accepted("", topic, 99 * SEC)
    q.clock_jump(10 * SEC, 90 * SEC)
    assert q.judge("", "b", 10 * SEC, 10 * SEC, Order.STRICT) == Verdict.EPOCH_HOLD
    assert q.judge("", "b", 13 * SEC, 13 * SEC, Order.STRICT) == Verdict.EPOCH


@pytest.mark.parametrize("case", STAMPED, ids=[f"{n}{'-' + '-'.join(map(str, o.values())) if o else ''}"
                                               for n, o in STAMPED])
def test_a_pass_ends_the_same_whether_its_last_messages_come_before_or_after_the_clock_jump(
        world, streams, case):  # noqa: F811
    """Before, the reset came at the callback: the last messages were handled on the reset state (or
    refused, ``before_jump``) and the new pass then read as a second jump back (``time_jumps`` 2)."""
    ref = build_stage(world, *case)
    clean = _valid_stream(ref, streams)
    user = USER if ref.MULTI_USER else None
    want: list = []
    for stamp, topic, msg in clean:
        want += ref.process(topic, msg, stamp, user)
    stage = build_stage(world, *case)
    span = clean[-1][0] - clean[0][0] + SEC
    # a stream of a few messages (the world's two scans, 4 s apart) has no last messages to queue that
    # would leave its pass ahead of the clock gone back by more than jump_s: it is taken whole before
    # the jump, and must still reset once in the new pass
    queued = QUEUED if len(clean) > 2 * QUEUED else 0
    got: list = []
    for stamp, topic, msg in clean[:len(clean) - queued]:
        got += stage.process(topic, msg, stamp, user)
    got += stage.run_clock_jump(span, clean[0][0])
    for _stamp, topic, msg in clean[len(clean) - queued:]:     # taken after the callback, the clock gone back
        got += stage.process(topic, msg, clean[0][0], user)
    assert sum(stage.diag.rejected.values()) == 0, stage.diag.rejected
    assert [(t, tuple(_leaves(m))) for t, m in got] == [(t, tuple(_leaves(m))) for t, m in want]
    at_reset: list = []
    real_reset = stage._reset_and_restart

    def reset_and_restart(u):
        outs, held = real_reset(u)
        at_reset.extend(m for _, m in outs)
        return outs, held
    stage._reset_and_restart = reset_and_restart
    second: list = []
    for stamp, topic, msg in clean:
        second += stage.process(topic, msg, stamp, user)
    assert stage.diag.time_jumps == 1 and sum(stage.diag.rejected.values()) == 0, stage.diag.rejected
    first = [(t, tuple(_leaves(m))) for t, m in want if t != "map/graph"]
    again = [(t, tuple(_leaves(m))) for t, m in second if not any(m is r for r in at_reset)]
    if stage.MULTI_USER:
        assert [t for t, _ in again] == [t for t, _ in first]
    else:
        assert again == first


def test_a_clock_lagging_the_stamps_confirms_no_jump_back_only_a_clock_gone_back_does():
    p = TimePolicy(TimeParams())
    for t in (106, 107, 108):                    # stamps 6-8 s ahead of a clock that lags them
        assert p.judge("", "a", t * SEC, 100 * SEC, Order.STRICT) == Verdict.PASS
        p.accepted("", "a", t * SEC)
    assert p.judge("", "a", 100 * SEC, 100 * SEC, Order.STRICT) == Verdict.HOLD    # the clock's present
    p.hold("", Held("a", None, 100 * SEC, 100 * SEC))
    assert p.judge("", "a", 109 * SEC, 100 * SEC, Order.STRICT) == Verdict.PASS
    assert p.in_step("", "a") and len(p.drop_held("")) == 1 and p.users[""].jumps == 0
    q = TimePolicy(TimeParams())
    for t in (128, 129, 130):                    # the clock with the stamps, then back (no callback yet)
        q.judge("", "a", t * SEC, t * SEC, Order.STRICT)
        q.accepted("", "a", t * SEC)
    assert q.judge("", "a", 100 * SEC, 100 * SEC, Order.STRICT) == Verdict.JUMP
