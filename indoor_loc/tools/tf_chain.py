"""What a tf user of a recorded run gets: ``map -> <user>/odom`` (``/tf``) composed with ``<user>/odom ->
<user>/base_link`` (``<user>/pdr/odom``), against the ground truth.

``python -m indoor_loc.tools.tf_chain OUT/demo`` (a demo's output: ``live.mcap`` and ``sim/``) prints,
per user and source (``/tf``, and each estimator's ``map_odom`` topic: ``pf``, ``pdr_kf``, ``backend``):

* *at corrections*: the chain at each correction's own stamp (for ``/tf``: its stamp less the
  ``transform_tolerance`` it was future-dated by, found as the difference to ``pf/map_odom``'s stamps),
  i.e. the estimate itself;
* *tf lookups*: the chain at every odometry stamp, with the newest correction a tf buffer holds by then
  (its future-dated stamp at or after the odometry's, its own stamp before it): the estimate carried
  forward by the odometry, what navigation sees between estimates;
* *odometry alone*: the odometry put in the map once, by the first correction, and never corrected.

Errors are the distances (m) to the ground truth interpolated at the stamp; mean / p95.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from indoor_loc.pipeline.map_odom import OdomTrack, compose


def _source(topic: str) -> tuple[str, str] | None:
    """``(user, estimator)`` of a correction topic: ``/alice/pf/map_odom``, ``/backend/alice/map_odom``."""
    parts = topic.strip("/").split("/")
    if len(parts) == 3 and parts[2] == "map_odom":
        return (parts[1], "backend") if parts[0] == "backend" else (parts[0], parts[1])
    return None


def evaluate(bag: Path, sim_dir: Path) -> dict[tuple[str, str], dict[str, tuple[float, float, int]]]:
    """Per (user, source): the errors of the module doc. Sources: ``/tf`` (future-dated; a correction
    expires at its /tf stamp) and each estimator's TransformStamped topic (``pf``, ``pdr_kf``, ``backend``:
    its own stamp, held until the next)."""
    from indoor_loc.bag import read_bag
    from indoor_loc.commands.eval import truth_from_import
    from msg_adapters.odom import odom_from_msg
    from msg_adapters.tf import transform_from_msg

    truths = truth_from_import(sim_dir)
    odom: dict[str, OdomTrack] = {}
    found: dict[tuple[str, str], list[tuple[int, tuple[float, float, float]]]] = {}
    for m in read_bag([bag]):
        if m.topic.endswith("/pdr/odom"):
            user = m.topic.split("/")[1]
            od = odom_from_msg(m.msg)
            odom.setdefault(user, OdomTrack(maxlen=10**7)).add(od.stamp_ns, (od.x, od.y, od.yaw), od.frame_id)
        elif m.topic == "/tf":
            for t in m.msg.transforms:
                stamp, parent, child, c = transform_from_msg(t)
                found.setdefault((child.split("/")[0], "/tf"), []).append((stamp, c))
        elif (src := _source(m.topic)) is not None:
            stamp, _, _, c = transform_from_msg(m.msg)
            found.setdefault(src, []).append((stamp, c))
    out: dict[tuple[str, str], dict[str, tuple[float, float, int]]] = {}
    for (user, source), cs in sorted(found.items()):
        truth, track = truths.get(user), odom.get(user)
        if truth is None or track is None or not cs:
            continue
        cs.sort(key=lambda c: c[0])
        stamps = np.array([c[0] for c in cs], np.int64)
        shift = 0
        if source == "/tf":                 # the future-dating: /tf stamps less pf/map_odom's
            mine = np.array(sorted(s for s, _ in found.get((user, "pf"), [])), np.int64)
            n = min(len(mine), len(stamps))
            shift = int(np.median(stamps[-n:] - mine[-n:])) if n else 0

        def err(t: int, pose, truth=truth) -> float:
            xy = np.array([np.interp(t, truth.scan_ns, truth.scan_xy[:, k]) for k in (0, 1)])
            return float(np.hypot(*(np.array(pose[:2]) - xy)))

        def inside(t: int, truth=truth) -> bool:
            return bool(truth.scan_ns[0] <= t <= truth.scan_ns[-1])

        at_corr = [err(s - shift, compose(c, track.at(s - shift))) for s, c in cs if inside(s - shift)]
        lookups, alone = [], []
        for t, pose in zip(track.stamps, track.poses):
            i = int(np.searchsorted(stamps - shift, t, side="right")) - 1   # newest correction made by t
            if i < 0 or not inside(t) or (shift and stamps[i] < t):         # none yet, or expired on /tf
                continue
            lookups.append(err(t, compose(cs[i][1], pose)))
            alone.append(err(t, compose(cs[0][1], pose)))

        def stats(v: list[float]) -> tuple[float, float, int]:
            return (float(np.mean(v)), float(np.percentile(v, 95)), len(v)) if v else (float("nan"),) * 2 + (0,)
        out[(user, source)] = {"at corrections": stats(at_corr), "tf lookups": stats(lookups),
                               "odometry alone": stats(alone)}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a demo's output directory (live.mcap, sim/)")
    a = ap.parse_args(argv)
    res = evaluate(a.run / "live.mcap", a.run / "sim")
    if not res:
        print("no /tf corrections with odometry and ground truth in this run", file=sys.stderr)
        return 1
    print("| user | source | chain at the corrections' stamps | lookups at odometry stamps | odometry alone | "
          "n lookups |")
    print("|---|---|---|---|---|---|")
    for (user, source), r in res.items():
        c, lk, al = r["at corrections"], r["tf lookups"], r["odometry alone"]
        print(f"| {user} | {source} | {c[0]:.2f} / {c[1]:.2f} | {lk[0]:.2f} / {lk[1]:.2f} | {al[0]:.2f} / {al[1]:.2f} "
              f"| {lk[2]} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
