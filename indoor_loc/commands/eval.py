"""``indoor-loc eval``: score trajectories against ground truth, per walk and pooled.

Trajectories: MCAP bags (``--topic``, default ``wifi/fix``; the namespace of each matching topic
is the user, e.g. ``/walk07/wifi/fix`` -> ``walk07``) and/or ``--csv-dir`` (``<user>.csv``, format
in :mod:`indoor_loc.eval.trajectory`). Truth: ``--truth IMPORT_DIR`` (the imported bags'
``ground_truth`` Path and ``ground_truth/route`` LINE_LIST markers) or ``--dataset PUTMC_DIR``.

Examples::

    indoor-loc eval run.mcap --truth import/ --topic wifi/fix --plot plots/ --json scores.json
    indoor-loc eval --csv-dir trajs/ --dataset ../shared/datasets/putmc

Metrics (see :mod:`indoor_loc.eval.metrics`): Nowicki & Skrzypczyński 2019 convention (squared units),
the route distance in metres, and the scan-time error in metres.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from indoor_loc.contract import namespace_of_topic
from indoor_loc.errors import ConfigError, DatasetError
from indoor_loc.eval.metrics import WalkErrors, WalkScore, interpolate_xy, pool, score, walk_errors
from indoor_loc.eval.trajectory import Trajectory, Truth, read_csv_dir, truth_from_putmc, write_csv

ROUTE_TOPIC = "ground_truth/route"
SCAN_TOPIC = "wifi/scan"
LINE_LIST = 5          # visualization_msgs/Marker.LINE_LIST


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bags", nargs="*", type=Path, help="MCAP bags (or bag directories) with trajectories")
    parser.add_argument("--topic", default="wifi/fix",
                        help="relative topic of the trajectory: nav_msgs/Path (last message), "
                             "PoseWithCovarianceStamped or Odometry (accumulated); default wifi/fix; "
                             "'{user}' marks the user in a multi-user node's topics (backend/{user}/path)")
    parser.add_argument("--csv-dir", type=Path, help="directory of <user>.csv trajectories")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--truth", type=Path,
                     help="import directory: its bags (or those one level down, as `import ms-indoor` writes "
                          "them per floor) with ground_truth (+ ground_truth/route; without it the ground_truth "
                          "path's own segments are the route)")
    src.add_argument("--dataset", type=Path, help="the PUTMC dataset directory (truth read from the files)")
    parser.add_argument("--user", default="walk01", help="user name for a topic without namespace (default walk01)")
    parser.add_argument("--json", type=Path, help="write the scores as JSON here")
    parser.add_argument("--plot", type=Path, help="write one PNG per walk into this directory")
    parser.add_argument("--write-csv", type=Path, help="also write the trajectories read as <user>.csv here")
    parser.add_argument("--keep-stale", action="store_true", help="with --dataset: keep stale samples' scans")
    parser.add_argument("--at-scans", action="store_true",
                        help="with --truth: score the scan-time error at every wifi/scan of the imported bags "
                             "inside the truth's time span, against the truth interpolated there (linear between "
                             "ground_truth samples, as the Microsoft traces' waypoints are), instead of at the "
                             "ground_truth samples themselves")


# ---------------------------------------------------------------------------------------------
# reading bags (plumbing: this module may use the bag reader and the message adapters)
# ---------------------------------------------------------------------------------------------
def _user_pattern(rel: str):
    """``backend/{user}/path`` -> a regex whose group ``user`` is the user (per-user topics of a
    multi-user node in the root namespace)."""
    import re
    head, _, tail = rel.strip("/").partition("{user}")
    return re.compile("^/" + re.escape(head) + "(?P<user>.+)" + re.escape(tail) + "$")


def _matching_topics(paths: list[Path], rel: str) -> dict[str, str]:
    from indoor_loc.bag import bag_topics
    if "{user}" in rel:
        pat = _user_pattern(rel)
        return {t: ty for t, (ty, _) in bag_topics(paths).items() if pat.match(t)}
    return {t: ty for t, (ty, _) in bag_topics(paths).items()
            if namespace_of_topic(t, rel) is not None}


def _user_of(topic: str, rel: str, default: str) -> str:
    if "{user}" in rel:
        m = _user_pattern(rel).match(topic)
        return m.group("user") if m else default
    ns = namespace_of_topic(topic, rel)
    return (ns or "").strip("/") or default


#: Message types a trajectory is read from (Path: its last message; the others: every message).
TRAJECTORY_TYPES = ("nav_msgs/msg/Path", "geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry")


def trajectories_from_bags(paths: list[Path], topic: str, *, default_user: str = "walk01",
                           frames: dict[str, set[str]] | None = None) -> dict[str, Trajectory]:
    """Trajectories per user from the bags' ``topic`` (Path: last message; poses/odometry: all).
    ``frames``, when given, receives each user's ``header.frame_id`` values."""
    from indoor_loc.bag import read_bag
    from msg_adapters.odom import odom_from_msg
    from msg_adapters.path import path_from_msg
    from msg_adapters.pose import pose_from_msg

    topics = _matching_topics(paths, topic)
    if not topics:
        from indoor_loc.bag import bag_topics
        usable = sorted(t for t, (ty, _) in bag_topics(paths).items() if ty in TRAJECTORY_TYPES)
        raise DatasetError(f"no topic named */{topic} in {[str(p) for p in paths]}; trajectory topics there: "
                           + (", ".join(usable) if usable else "none (is this an output of `indoor-loc run`?)"))
    acc: dict[str, list] = {}
    last_path: dict[str, tuple] = {}
    for m in read_bag(paths, topics=list(topics)):
        user = _user_of(m.topic, topic, default_user)
        if frames is not None:
            frames.setdefault(user, set()).add(str(getattr(getattr(m.msg, "header", None), "frame_id", "")))
        if m.type == "nav_msgs/msg/Path":
            last_path[user] = path_from_msg(m.msg)
        elif m.type == "geometry_msgs/msg/PoseWithCovarianceStamped":
            s = pose_from_msg(m.msg)
            yaw = s.yaw if m.msg.pose.covariance[35] < 1e5 else math.nan   # fixes carry no heading
            acc.setdefault(user, []).append((s.stamp_ns, s.xy[0], s.xy[1], yaw))
        elif m.type == "nav_msgs/msg/Odometry":
            s = odom_from_msg(m.msg)
            acc.setdefault(user, []).append((s.stamp_ns, s.x, s.y, s.yaw))
        else:
            raise DatasetError(f"topic {m.topic}: cannot read a trajectory from {m.type}")
    out: dict[str, Trajectory] = {}
    for user, (t, xy, yaw) in last_path.items():
        out[user] = Trajectory.make(user, t, xy, yaw)
    for user, rows in acc.items():
        a = np.array(rows, dtype=object)
        out[user] = Trajectory.make(user, np.array(a[:, 0], dtype=np.int64), np.array(a[:, 1:3], dtype=float),
                                    np.array(a[:, 3], dtype=float))
    return out


def frame_warnings(frames: dict[str, set[str]], truth_frame: str = "map") -> list[str]:
    """A warning per user whose track is not in the truth's frame (``<user>/odom``: PDR odometry
    starts at the origin with an arbitrary heading, so its distance to map truth means nothing)."""
    out = []
    for user, fs in sorted(frames.items()):
        other = sorted(f for f in fs if f and f != truth_frame)
        if other:
            out.append(f"WARNING: {user}: the track is in frame {', '.join(other)} but the ground truth is in "
                       f"{truth_frame!r}; the frames are not aligned (odometry starts at its own origin and "
                       f"heading), so these errors are not localisation errors. Score a {truth_frame}-frame "
                       f"topic (pdr_kf/path, pdr_kf/pose, wifi/fix, pf/path) instead.")
    return out


def truth_from_import(import_dir: Path, *, at_scans: bool = False) -> dict[str, Truth]:
    """Truth per user from imported bags: ``ground_truth`` (time-stamped true positions: PUTMC's
    scan positions, the simulator's samples, the Microsoft traces' waypoints) and the LINE_LIST
    markers of ``ground_truth/route`` (consecutive point pairs = segments). A user without route
    markers (``import ms-indoor``: the walk is linear between its waypoints) gets the segments
    between consecutive ``ground_truth`` points as its route. The bags are ``import_dir/*.mcap`` or,
    when there are none, ``import_dir/*/*.mcap`` (``import ms-indoor``'s ``OUT/<floor>/``).

    ``at_scans``: the scored instants are the user's ``wifi/scan`` stamps inside the ``ground_truth``
    span, each with the truth interpolated linearly there (see :func:`truth_at`), instead of the
    ``ground_truth`` samples. A user with neither route markers nor two ``ground_truth`` points is left
    out (a warning on stderr; the caller reports it as not scored), so the other users are still scored."""
    from indoor_loc.bag import read_bag
    from msg_adapters.markers import marker_points
    from msg_adapters.path import path_from_msg
    from msg_adapters.time import stamp_to_ns

    if not Path(import_dir).is_dir():
        raise DatasetError(f"--truth {import_dir} is not a directory (give the output directory of "
                           "`indoor-loc import` or `indoor-loc sim`)")
    bags = sorted(Path(import_dir).glob("*.mcap")) or sorted(Path(import_dir).glob("*/*.mcap"))
    if not bags:
        raise DatasetError(f"{import_dir}: no .mcap bags (run `indoor-loc import` first)")
    from indoor_loc.bag import bag_topics
    ends = ("/" + ROUTE_TOPIC, "/ground_truth") + (("/" + SCAN_TOPIC,) if at_scans else ())
    wanted = [t for t in bag_topics(bags) if t.endswith(ends)]
    gt: dict[str, tuple] = {}
    segs: dict[str, np.ndarray] = {}
    scans: dict[str, list[int]] = {}
    for m in read_bag(bags, topics=wanted):
        if m.topic.endswith("/" + SCAN_TOPIC):
            scans.setdefault(_user_of(m.topic, SCAN_TOPIC, ""), []).append(stamp_to_ns(m.msg.header.stamp))
        elif m.topic.endswith("/" + ROUTE_TOPIC):
            user = _user_of(m.topic, ROUTE_TOPIC, "")
            pts = [marker_points(mk)[:, :2] for mk in m.msg.markers if mk.type == LINE_LIST and mk.points]
            if pts:
                p = np.concatenate(pts)
                segs[user] = p.reshape(-1, 2, 2)
        elif m.topic.endswith("/ground_truth") and m.type == "nav_msgs/msg/Path":
            user = _user_of(m.topic, "ground_truth", "")
            t, xy, _ = path_from_msg(m.msg)
            gt[user] = (t, xy)
    out = {}
    for user in sorted(set(gt) | set(segs)):
        t, xy = gt.get(user, (np.zeros(0, dtype=np.int64), np.zeros((0, 2))))
        if user not in segs:
            if len(xy) < 2:
                print(f"WARNING: {import_dir}: {user} has no {ROUTE_TOPIC} markers and fewer than two ground_truth "
                      "points to draw its route from: not scored", file=sys.stderr)
                continue
            segs[user] = np.stack([xy[:-1], xy[1:]], axis=1)
        if at_scans:
            t, xy = truth_at(t, xy, np.asarray(scans.get(user, []), np.int64))
        out[user] = Truth(user, segs[user], t, xy)
    return out


def truth_at(t: np.ndarray, xy: np.ndarray, at_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The instants of ``at_ns`` inside [t[0], t[-1]] (sorted) and the truth there, linear between the
    samples ``t`` (K,) ns, ``xy`` (K, 2) m (none without two samples)."""
    at = np.sort(np.asarray(at_ns, np.int64))
    if len(t) < 2:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    at = at[(at >= t[0]) & (at <= t[-1])]
    est, _ = interpolate_xy(t, xy, at)
    return at, est


# ---------------------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------------------
def format_table(scores: list[WalkScore]) -> str:
    """Plain-text table: paper convention ("RMSE"/"mean" in m², as published), route distance and
    scan-time error in metres."""
    w = max([8, *(len(s.name) for s in scores)])        # long user names (ms-indoor trace ids) stay aligned
    head = (f"{'walk':{w}s} {'poses':>5s} {'cut':>3s} | {'pRMSE':>6s} {'pmean':>6s} | {'rRMSE':>6s} {'rmean':>6s} "
            f"{'rmed':>5s} {'rp95':>5s} {'rmax':>5s} | {'at':>5s} {'smean':>6s} {'smed':>5s} {'sp95':>5s} "
            f"{'smax':>5s} {'sRMSE':>6s}")
    sub = ("paper: e=d² (m²) over poses with e<100 ('cut' = poses dropped) | route distance (m), same poses | "
           "error at the truth's instants (m), 'at' of them: the trajectory interpolated at every true position "
           "(PUTMC: its WiFi scans; an import or a simulation: its ground_truth samples, or with --at-scans its "
           "wifi/scan stamps), held before/after its ends")
    lines = [sub, head, "-" * len(head)]
    for s in scores:
        r, c, p = s.route_m, s.scan_m, s.paper
        lines.append(f"{s.name:{w}s} {s.n_poses:5d} {p.n_cut:3d} | {p.rmse:6.2f} {p.mean:6.2f} | {r.rmse:6.3f} "
                     f"{r.mean:6.3f} {r.median:5.2f} {r.p95:5.2f} {r.max:5.2f} | {c.n:5d} {c.mean:6.3f} "
                     f"{c.median:5.2f} {c.p95:5.2f} {c.max:5.2f} {c.rmse:6.3f}")
    return "\n".join(lines)


def evaluate(trajs: dict[str, Trajectory], truths: dict[str, Truth]) -> tuple[list[WalkScore], list[WalkErrors]]:
    """Per-user scores (users with both a trajectory and a truth, sorted) plus the pooled score last."""
    users = sorted(set(trajs) & set(truths))
    if not users:
        raise ConfigError(f"no user has both a trajectory ({sorted(trajs)}) and a ground truth ({sorted(truths)})")
    errs = []
    for u in users:
        tr, gt = trajs[u], truths[u]
        if len(tr) == 0:
            continue
        errs.append(walk_errors(u, tr.stamps_ns, tr.xy, gt.segments, gt.scan_ns, gt.scan_xy))
    scores = [score(e) for e in errs] + [score(pool(errs))]
    return scores, errs


def main(args: argparse.Namespace) -> int:
    if args.at_scans and not args.truth:
        raise ConfigError("--at-scans needs --truth (an import's bags: their wifi/scan stamps are the instants "
                          "scored); with --dataset the truth is PUTMC's scan positions already")
    trajs: dict[str, Trajectory] = {}
    frames: dict[str, set[str]] = {}
    if args.bags:
        trajs.update(trajectories_from_bags(list(args.bags), args.topic, default_user=args.user, frames=frames))
        for w in frame_warnings(frames):
            print(w, file=sys.stderr)
    if args.csv_dir:
        trajs.update(read_csv_dir(args.csv_dir))
    if not trajs:
        raise ConfigError("nothing to score: give bags (with --topic) and/or --csv-dir")
    if args.truth:
        truths = truth_from_import(args.truth, at_scans=args.at_scans)
    else:
        walks = sorted(int(u[4:]) for u in trajs if u.startswith("walk") and u[4:].isdigit())
        truths = truth_from_putmc(args.dataset, walks or None, keep_stale=args.keep_stale)
    missing = sorted(set(trajs) - set(truths))
    if missing:
        print(f"no ground truth for {missing}: not scored")
    scores, _ = evaluate(trajs, truths)
    print(format_table(scores))
    if args.write_csv:
        Path(args.write_csv).mkdir(parents=True, exist_ok=True)
        for u, tr in trajs.items():
            write_csv(Path(args.write_csv) / f"{u}.csv", tr)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        doc = {"topic": args.topic if args.bags else None, "walks": [s.as_dict() for s in scores[:-1]],
               "pooled": scores[-1].as_dict()}
        Path(args.json).write_text(json.dumps(_nan_to_none(doc), indent=2, allow_nan=False))
        print(f"scores: {args.json}")
    if args.plot:
        _plots(args, trajs, truths, scores)
    return 0


def _nan_to_none(obj):
    """NaN (no value, e.g. no scans scored) -> null, so the JSON file is standard JSON."""
    if isinstance(obj, float) and math.isnan(obj):
        return None
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_nan_to_none(v) for v in obj]
    return obj


def _plots(args, trajs, truths, scores) -> None:
    from indoor_loc.datasets.putmc import map_extent
    from indoor_loc.eval.plot import plot_walk

    floor_plan = None
    for cand in ([args.dataset] if args.dataset else []) + [Path(__file__).resolve().parents[3] / "shared" /
                                                             "datasets" / "putmc"]:
        if cand is not None and (Path(cand) / "map.png").exists():
            floor_plan = Path(cand) / "map.png"
            break
    by_name = {s.name: s for s in scores}
    for u in sorted(set(trajs) & set(truths)):
        s = by_name.get(u)
        src = args.topic if args.bags else "csv"
        title = u if s is None else (f"{u}: {src}  scan-time mean {s.scan_m.mean:.2f} m, "
                                     f"route mean {s.route_m.mean:.2f} m, paper RMSE {s.paper.rmse:.2f}")
        out = plot_walk(Path(args.plot) / f"{u}.png", truths[u], trajs[u], floor_plan=floor_plan,
                        extent=map_extent(), title=title)
        print(f"plot: {out}")
