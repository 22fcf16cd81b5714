"""What a slow WiFi node does to the back-end, on a recorded run: ``python -m indoor_loc.bench.fix_delay
RUN.mcap PARAMS.yaml INPUT_BAGS --delays 2 4 7``.

RUN.mcap is an ``indoor-loc run … --nodes imu,wifi,backend`` output (its ``pdr/odom`` and
``wifi/fix``), INPUT_BAGS the comma-separated bags it ran on (their ``wifi/scan``), PARAMS the run's
params file (``/**/backend_node``). The messages are fed to ``BackendStage`` in stamp order with each
fix right after its scan (as the offline run had them), then with every fix held back until its
user's odometry is D s past it; prints whether the paths are the on-time ones, the largest
difference, and the stage's fix-wait counters.
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import yaml

from indoor_loc.bag import read_bag
from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
from msg_adapters.path import path_from_msg
from msg_adapters.time import stamp_to_ns

KIND = {"pdr/odom": 0, "wifi/scan": 1, "wifi/fix": 2}


def messages(run: str, inputs: list[str]) -> list[tuple[str, str, object]]:
    """(user, topic, msg) of the run's odometry and fixes and the inputs' scans, in stamp order."""
    ev = []
    for bag in [run] + inputs:
        for m in read_bag(bag):
            user, _, topic = m.topic.strip("/").partition("/")
            if topic in KIND and (bag == run) != (topic == "wifi/scan"):
                ev.append((stamp_to_ns(m.msg.header.stamp), KIND[topic], len(ev), user, topic, m.msg))
    ev.sort(key=lambda e: e[:3])
    return [(u, t, m) for *_, u, t, m in ev]


def delayed(msgs, lag_s: float):
    """The same messages, each fix held back until its user's odometry is ``lag_s`` past its stamp."""
    out, held = [], {}
    for user, topic, msg in msgs:
        if topic == "wifi/fix" and lag_s > 0:
            held.setdefault(user, []).append((user, topic, msg))
            continue
        out.append((user, topic, msg))
        h = held.get(user, [])
        while topic == "pdr/odom" and h and (stamp_to_ns(msg.header.stamp)
                                             - stamp_to_ns(h[0][2].header.stamp)) >= lag_s * 1e9:
            out.append(h.pop(0))
    return out + [m for h in held.values() for m in h]


def run(params: BackendParams, msgs):
    st = BackendStage(params)
    outs = []
    for user, topic, msg in msgs:
        outs += st.process(topic, msg, 0, user)
    outs += st.finish()
    return st, {t: path_from_msg(m) for t, m in outs if t.endswith("/path")}


def main() -> None:
    assert __doc__ is not None
    ap = argparse.ArgumentParser(prog="python -m indoor_loc.bench.fix_delay", description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("params")
    ap.add_argument("inputs", help="comma-separated input bags (their wifi/scan)")
    ap.add_argument("--delays", type=float, nargs="+", default=[2.0, 4.0, 7.0])
    a = ap.parse_args()
    with open(a.params) as f:
        raw = yaml.safe_load(f)["/**/backend_node"]["ros__parameters"]
    params = params_from_dict(BackendParams, raw)
    msgs = messages(a.run, a.inputs.split(","))
    st0, base = run(params, msgs)
    n_fix = sum(t == "wifi/fix" for _, t, _ in msgs)
    print(f"on time: {len(base)} paths, {sum(len(v[0]) for v in base.values())} poses, {n_fix} fixes")
    for lag in a.delays:
        st, paths = run(dataclasses.replace(params), delayed(msgs, lag))
        same_shape = paths.keys() == base.keys() and all(np.array_equal(paths[k][0], base[k][0]) for k in base)
        diff = max((float(np.max(np.abs(paths[k][1] - base[k][1]))) for k in base), default=0.0) \
            if same_shape else float("nan")
        d = st.extra_diagnostics()
        print(f"fixes {lag:g} s late: same poses {same_shape}, max |Δxy| {diff:.2g} m; waited for "
              f"{d['fix_wait.fixes_waited_for']}, longest lag {d['fix_wait.lag_max_s']} s, given up "
              f"{d['fix_wait.scans_given_up']}, rejected {dict(st.diag.rejected) or 0}")


if __name__ == "__main__":
    main()
