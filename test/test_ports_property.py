"""Every input port of every stage, any message in: the stage keeps its promises (hypothesis).

Each stage is built from the simulated world's params (``test_contract_ports``' world, cases and
``build_stage``) and fed its valid input stream -- the world's sensors, and what ``imu_node`` and
``wifi_fix_node`` make of them -- with hostile messages of a port's type interleaved: a valid message
with numeric fields set to NaN, inf, +-1e308, negatives, huge or tiny values, covariance arrays at
random, strings at random, empty and 10 000-AP scans, JSON with absurd numbers. Promises:

- no ``internal_error``: a message never makes a core estimator raise (also at the end of input);
- every output finite;
- every valid message is handled as without the hostile ones: each one's rejections are the clean
  stream's, and when every hostile message was refused the outputs are exactly the clean stream's (a
  refused message leaves no state).

Hostile messages are stamped 1 ns after the valid message of their topic before them (1 ns before
its first), so stamps say nothing about them (the time policy is tested elsewhere); one case gives
them any stamp and asserts only the first two promises. An example goes on from a copy of the clean
run's stage at one of a few points of the stream (``SNAP_FRACTIONS``), so it costs only the rest of
the stream. Beside the random examples, a sweep sets each field of each port's message absurd in turn.
"""
from __future__ import annotations

import copy
import copyreg
import json
import math
from collections import Counter
from typing import Any, Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from scipy.sparse.linalg import SuperLU

import test_contract_ports
from indoor_loc.bench import hostile as hostile_msgs
from test_contract_ports import CASES, build_stage
from indoor_loc.bag import read_bag
from msg_adapters.pose import pose_to_msg
from msg_adapters.time import MAX_STAMP_NS
from msg_adapters.wifi_json import scan_to_json_msg
from msg_adapters.wifi_scan import scan_from_msg

SEC = 1_000_000_000
#: the simulated world (a module fixture) every stage is built from, as in test_contract_ports
world = test_contract_ports.world
#: the IMU streams are cut to this long from their start (the stepometer hops a few times in it)
IMU_S = 3.0
USER = "walker0"
#: fewer particles and smoothed trajectories: the same code paths at a fifth of the cost
LIGHTER = {"pf": {"n_particles": 200, "smooth_samples": 10}}
INPUT_CASES = [(n, o) for n, o in CASES if not (n == "wifi_scan" and o.get("source", "topic") != "topic")]

#: hostile values and messages per port: shared with the fault benchmark (indoor_loc/bench/hostile.py)
HOSTILE_FLOATS, hostile_float = hostile_msgs.HOSTILE_FLOATS, hostile_msgs.hostile_float


# -- the valid streams ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def streams(world) -> dict[str, list[tuple[int, Any]]]:
    return valid_streams(world)


def valid_streams(world) -> dict[str, list[tuple[int, Any]]]:
    """Valid messages per relative topic, ``(stamp_ns, msg)`` in stamp order: the world's IMU and
    scans, imu_node's ``pdr/odom`` and ``imu/data``, wifi_fix_node's ``wifi/fix``, the driver topics
    of wifi_scan_node (the scans as ``wifi/scan_raw`` and JSON) and one ``initialpose`` at the first fix."""
    sim = [(m.topic.split("/", 2)[-1], m.msg) for m in read_bag(world / "sim.mcap")]
    out: dict[str, list[tuple[int, Any]]] = {t: [] for t in ("imu/data_raw", "imu/mag", "wifi/scan", "pdr/odom",
                                                              "imu/data", "wifi/fix", "wifi/scan_raw",
                                                              "wifi/scan_json", "initialpose", "baro/pressure")}
    imu, wifi = build_stage(world, "imu", {}), build_stage(world, "wifi", {})
    t0 = None
    for topic, msg in sim:
        if topic == "baro/pressure":
            out[topic].append((_stamp(msg), msg))
        if topic not in ("imu/data_raw", "imu/mag", "wifi/scan"):
            continue
        stamp = _stamp(msg)
        t0 = stamp if t0 is None else t0
        produced = imu.process(topic, msg, stamp) if imu.handles(topic) else wifi.process(topic, msg, stamp)
        for o_topic, o_msg in produced:
            if o_topic != "imu/data" or stamp - t0 <= IMU_S * SEC:
                out[o_topic].append((_stamp(o_msg), o_msg))
        if topic == "wifi/scan" or stamp - t0 <= IMU_S * SEC:
            out[topic].append((stamp, msg))
    out["pdr/odom"] += [(_stamp(m), m) for t, m in imu.run_finish() if t == "pdr/odom"]
    out["odom"] = list(out["pdr/odom"])     # a robot's odometry (motion_source odom): the same valid poses
    for stamp, msg in out["wifi/scan"]:
        out["wifi/scan_raw"].append((stamp, msg))
        out["wifi/scan_json"].append((stamp, scan_to_json_msg(scan_from_msg(msg))))
    s0, fix = out["wifi/fix"][0]
    p = fix.pose.pose.position
    out["initialpose"].append((s0 + 1, pose_to_msg(s0 + 1, [p.x, p.y], 0.3, np.eye(2) * 0.25, yaw_var=0.07)))
    assert not imu.diag.rejected and not wifi.diag.rejected
    assert len(out["pdr/odom"]) > 5 and len(out["wifi/fix"]) >= 2 and len(out["imu/data"]) > 100
    return out


def _stamp(msg) -> int:
    return msg.header.stamp.sec * SEC + msg.header.stamp.nanosec


def _valid_stream(stage, streams) -> list[tuple[int, str, Any]]:
    """The stage's inputs merged in stamp order (ties: topic order of ``inputs()``)."""
    topics = [p.topic for p in stage.inputs()]
    merged = [(s, k, t, m) for k, t in enumerate(topics) for s, m in streams[t]]
    merged.sort(key=lambda r: (r[0], r[1]))
    return [(s, t, m) for s, _, t, m in merged]


# -- running a stream -------------------------------------------------------------------------------
def _leaves(msg) -> Iterator[Any]:
    """Every value of a ROS message (numbers, strings), recursively, in field order: what it says,
    without the padding bytes its serialisation may carry."""
    for name, typ in msg.get_fields_and_field_types().items():
        v = getattr(msg, name)
        if typ.startswith("sequence<") and "/" in typ or typ.endswith("]") and "/" in typ:
            for item in v:
                yield from _leaves(item)
        elif hasattr(v, "get_fields_and_field_types"):
            yield from _leaves(v)
        elif isinstance(v, (str, bytes, int, float, bool)):
            yield v
        else:                                   # a number array
            yield from (x.item() if hasattr(x, "item") else x for x in v)


def _values(topic: str, msg) -> tuple:
    """What an output says, checked finite."""
    values = tuple(_leaves(msg))
    bad = [v for v in values if isinstance(v, float) and not math.isfinite(v)]
    assert not bad, f"{topic}: non-finite output values {bad[:5]}"
    return values


class Run:
    """A stream through a stage, from ``stage`` as it is (a fresh one, or a copy of a clean run's at a
    snapshot): the outputs (their values, in order), the rejections each message caused (a Counter
    by reason), those of the end of input, and copies of the stage before each message of ``snap_at``."""

    def __init__(self, stage, stream: list[tuple[int, str, Any]], snap_at: tuple[int, ...] = ()) -> None:
        user = USER if stage.MULTI_USER else None
        self.outputs: list[tuple[str, tuple]] = []
        self.deltas: list[Counter] = []
        self.snapshots: dict[int, tuple[Any, int]] = {}     # message index -> (stage copy, outputs so far)
        for i, (stamp, topic, msg) in enumerate(stream):
            if i in snap_at:
                self.snapshots[i] = (copy.deepcopy(stage), len(self.outputs))
            before = Counter(stage.diag.rejected)
            outs = stage.process(topic, msg, stamp, user)
            self.deltas.append(Counter(stage.diag.rejected) - before)
            self.outputs += [(t, _values(t, m)) for t, m in outs]
        before = Counter(stage.diag.rejected)
        outs = stage.run_finish_user(USER) if stage.MULTI_USER else []
        outs += stage.run_finish()
        self.outputs += [(t, _values(t, m)) for t, m in outs]
        self.finish_delta = Counter(stage.diag.rejected) - before
        self.rejected = Counter(stage.diag.rejected)
        self.last_error = stage.diag.last_error


_SHARED: dict[int, Any] = {}


def _shared(obj: Any) -> tuple:
    """copyreg reducer: a copy of ``obj`` is ``obj`` itself (a read-only factorisation, scipy's SuperLU,
    which cannot be copied, held by the back-end between a solve and its covariances)."""
    _SHARED[id(obj)] = obj
    return _SHARED.__getitem__, (id(obj),)


copyreg.pickle(SuperLU, _shared)
#: where the clean run is copied for the examples to go on from: the start, and three points on
SNAP_FRACTIONS = (0.0, 0.4, 0.7, 0.9)
_CLEAN: dict[str, Run] = {}


def _clean(world, case, valid) -> Run:
    key = repr(case)
    if key not in _CLEAN:
        snaps = tuple(sorted({int(f * len(valid)) for f in SNAP_FRACTIONS}))
        name, overrides = case
        _CLEAN[key] = Run(build_stage(world, name, {**overrides, **LIGHTER.get(name, {})}), valid, snaps)
        assert _CLEAN[key].rejected["internal_error"] == 0, _CLEAN[key].last_error
    return _CLEAN[key]


# -- hostile messages -------------------------------------------------------------------------------
_numeric_leaves, _set, _groups = hostile_msgs.numeric_leaves, hostile_msgs.set_path, hostile_msgs.leaf_groups
_array_fields, _huge_scan = hostile_msgs.array_fields, hostile_msgs.huge_scan
numeric_mutation, scan_mutation, json_mutation = (hostile_msgs.numeric_mutation, hostile_msgs.scan_mutation,
                                                  hostile_msgs.json_mutation)
hostile_for, _restamp = hostile_msgs.hostile_for, hostile_msgs.restamp


@st.composite
def mixed_streams(draw, valid: list[tuple[int, str, Any]], ports: list[str], snaps: list[int], any_stamp: bool):
    """From a snapshot at valid message ``start`` on, the valid stream with 1-2 hostile messages among
    its first few: (start, stream, index of each valid message in it, indices of the hostile ones)."""
    start = draw(st.sampled_from(snaps))
    tail = valid[start:]
    picks = sorted(draw(st.lists(st.integers(0, min(8, len(tail))), min_size=1, max_size=2)))
    stream: list[tuple[int, str, Any]] = []
    valid_at, hostile_at = [], []
    k = 0
    for pos in picks:
        while k < pos:
            valid_at.append(len(stream))
            stream.append(tail[k])
            k += 1
        topic = draw(st.sampled_from(ports))
        before = [(s, m) for s, t, m in valid[:start + k] if t == topic]
        after = [(s, m) for s, t, m in valid[start + k:] if t == topic]
        msg = draw(hostile_for(topic, (before or after)[-1 if before else 0][1] if before or after else valid[0][2]))
        # just after the topic's previous valid message (its next one stays later), or just before its first
        stamp = before[-1][0] + 1 if before else after[0][0] - 1 if after else valid[0][0]
        if any_stamp:
            stamp = draw(st.integers(0, MAX_STAMP_NS))
        if msg is _huge_scan():                 # shared: a header of its own to stamp
            from diagnostic_msgs.msg import DiagnosticArray
            msg = DiagnosticArray(status=msg.status)
        hostile_at.append(len(stream))
        stream.append((stamp, topic, _restamp(msg, stamp)))
    while k < len(tail):
        valid_at.append(len(stream))
        stream.append(tail[k])
        k += 1
    return start, stream, valid_at, hostile_at


# -- the properties --------------------------------------------------------------------------------
IDS = [n + "".join(f"-{v}" for v in o.values() if v != "radiomap") for n, o in INPUT_CASES]
#: examples per stage, by what one costs (an IMU stream is 750 messages, a particle filter run 0.2 s)
EXAMPLES = {"imu": 10, "pf": 8, "backend": 20, "wifi": 15, "pdr_kf": 30, "wifi_scan": 10}
PROPERTY = settings(max_examples=6, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large])


def _go_on(clean: Run, start: int, stream) -> tuple[Run, list, list]:
    """``stream`` from a copy of the clean run's stage at ``start``; with the clean run's deltas and
    outputs from there on."""
    stage, n_out = clean.snapshots[start]
    return Run(copy.deepcopy(stage), stream), clean.deltas[start:], clean.outputs[n_out:]


def _commanded(stream, run: Run, hostile_at: list[int], i: int, burst_ns: int) -> set[str]:
    """The refusals valid message ``i`` may gain from a hostile ``initialpose`` the stage obeyed before
    it: a plausible pose is a command, so the rate bound refuses the next pose within
    ``pose_interval_min_s`` (``pose_burst``) and what is older than the commanded restart is stale
    (``too_late``) -- whoever sent the command. The one way a message, by being taken, changes how a
    later valid one is handled."""
    stamp, topic, _ = stream[i]
    may: set[str] = set()
    for j in hostile_at:
        if j < i and stream[j][1] == "initialpose" and not run.deltas[j]:
            if topic == "initialpose" and 0 <= stamp - stream[j][0] < burst_ns:
                may.add("pose_burst")
            if stamp < stream[j][0]:
                may.add("too_late")
    return may


@pytest.mark.parametrize("case", INPUT_CASES, ids=IDS)
def test_any_message_on_any_port_keeps_the_stage_promises(world, streams, case):
    probe = build_stage(world, *case)
    ports = [p.topic for p in probe.inputs()]
    valid = _valid_stream(probe, streams)
    clean = _clean(world, case, valid)
    burst_ns = int(getattr(probe.params, "pose_interval_min_s", 0.0) * 1e9)

    @settings(PROPERTY, max_examples=EXAMPLES[case[0]])
    @given(mixed_streams(valid, ports, sorted(clean.snapshots), any_stamp=False))
    def check(mixed):
        start, stream, valid_at, hostile_at = mixed
        run, deltas, outputs = _go_on(clean, start, stream)
        assert run.rejected["internal_error"] == 0, run.last_error
        got = [run.deltas[i] for i in valid_at]
        for k, i in enumerate(valid_at):                # (refusals an obeyed hostile command explains)
            extra = got[k] - deltas[k]
            if extra and set(extra) <= _commanded(stream, run, hostile_at, i, burst_ns):
                got[k] = deltas[k]
        assert got == deltas, "a valid message was handled differently"
        assert run.finish_delta == clean.finish_delta
        if all(sum(run.deltas[i].values()) for i in hostile_at):          # every hostile message refused
            assert run.outputs == outputs, "a refused message changed what the stage published"

    check()


@pytest.mark.parametrize("case", [c for c in INPUT_CASES if not c[1]], ids=[n for n, o in INPUT_CASES if not o])
def test_any_message_with_any_stamp_raises_nothing_and_outputs_stay_finite(world, streams, case):
    probe = build_stage(world, *case)
    ports = [p.topic for p in probe.inputs()]
    valid = _valid_stream(probe, streams)
    clean = _clean(world, case, valid)

    @settings(PROPERTY, max_examples=EXAMPLES[case[0]] // 3)
    @given(mixed_streams(valid, ports, sorted(clean.snapshots), any_stamp=True))
    def check(mixed):
        run = _go_on(clean, mixed[0], mixed[1])[0]          # outputs checked finite as they come
        assert run.rejected["internal_error"] == 0, run.last_error

    check()


#: the absurd values the sweep sets every field to
ABSURD = [math.nan, 1e308, -1e308, -1.0]
#: which snapshot the sweep goes on from: the 0.7 one, the last for the IMU (its streams are long)
SWEEP_FROM = {"imu": -1}


def _sweep(valid, ports, start: int) -> Iterator[tuple[str, Any]]:
    """Every field of every port's message set absurd, one at a time: ``(what, (topic, msg))``, the
    message stamped just after the valid one of its topic before ``start``."""
    from diagnostic_msgs.msg import KeyValue
    from std_msgs.msg import String
    for topic in ports:
        before = [(s, m) for s, t, m in valid[:start] if t == topic]
        after = [(s, m) for s, t, m in valid[start:] if t == topic]
        if not before and not after:
            continue
        stamp, base = (before[-1][0] + 1, before[-1][1]) if before else (after[0][0] - 1, after[0][1])
        for v in ABSURD:
            if topic == "wifi/scan_json":
                doc = json.loads(base.data)
                for key in ("rssi", "frequency_mhz", "last_seen_ms"):
                    bad = copy.deepcopy(doc)
                    bad["data"][0][key] = v
                    yield f"{topic} {key}={v}", (stamp, topic, String(data=json.dumps(bad)))
            elif topic in ("wifi/scan", "wifi/scan_raw"):
                for key in ("rssi_dbm", "frequency_mhz", "age_ms"):
                    msg = copy.deepcopy(base)
                    ap = msg.status[1]
                    ap.values = [kv for kv in ap.values if kv.key != key] + [KeyValue(key=key, value=repr(v))]
                    yield f"{topic} {key}={v}", (stamp, topic, _restamp(msg, stamp))
            else:
                for group in _groups(base):
                    msg = copy.deepcopy(base)
                    for path in group:
                        _set(msg, path, v)
                    yield f"{topic} {'.'.join(map(str, group[0][:-1]))}={v}", (stamp, topic, _restamp(msg, stamp))


@pytest.mark.parametrize("case", INPUT_CASES, ids=IDS)
def test_every_field_of_every_port_set_absurd_keeps_the_stage_promises(world, streams, case):
    """The systematic companion of the property above: each field (a vector, a quaternion, a covariance,
    a scan value) of each port's message set to NaN, +-1e308 or -1, late in the stream (the estimators
    started)."""
    probe = build_stage(world, *case)
    ports = [p.topic for p in probe.inputs()]
    valid = _valid_stream(probe, streams)
    clean = _clean(world, case, valid)
    start = sorted(clean.snapshots)[SWEEP_FROM.get(case[0], -2)]
    failures = []
    for what, hostile in _sweep(valid, ports, start):
        run, deltas, outputs = _go_on(clean, start, [hostile] + valid[start:])
        if run.rejected["internal_error"]:
            failures.append(f"{what}: internal_error {run.last_error.splitlines()[0]}")
        elif run.deltas[1:] != deltas or run.finish_delta != clean.finish_delta:
            failures.append(f"{what}: later valid messages handled differently {run.rejected}")
        elif sum(run.deltas[0].values()) and run.outputs != outputs:
            failures.append(f"{what}: refused, but the outputs changed")
    assert not failures, failures

