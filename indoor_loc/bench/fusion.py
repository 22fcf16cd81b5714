"""``indoor-loc bench fusion --dataset ms_site2 --data DATASETS`` (or ``--site DIR``): does fusion pay
on a real multi-floor site?

The user's documented path, per test walk: ``indoor-loc import ms-indoor SITE OUT`` once, then one
``indoor-loc run WALK --params OUT/params.yaml --nodes imu,wifi,pdr_kf,pf,backend`` per test walk of
the interleaved split (in this process, :func:`indoor_loc.pipeline.offline.run_offline`). Every
estimator, causal and smoothed (``wifi/fix``, ``pdr_kf/pose``, ``pdr_kf/path``, ``pf/pose``,
``pf/path``, ``backend/<u>/pose``, ``backend/<u>/path``), is scored per floor and pooled:

- **at the scans**: every ``wifi/scan`` stamp of the test walk inside its waypoint span, the truth
  interpolated linearly between the waypoints there (the issue's table);
- **at the waypoints**: the waypoints themselves (exact truth), each estimate interpolated there;

mean / median / p95 (m) over the instants the estimate spans (coverage = that share of the
instants; outside its span an estimate is not scored), with the ratio of the means to the
project's own ``wifi/fix`` and to plain WKNN (k 4, RMS over shared APs, > ½ shared both ways; the
``bench wifi --dataset ms_site2`` baseline) on the same scans and the import's radio map, its
fixes held as a track like ``wifi/fix``'s. Time per walk: the run's wall and CPU seconds.

Caching (CPU is scarce): the import goes to ``WORK/import`` (reused when its ``params.yaml`` is
there), each walk's run to ``WORK/runs/<key>/<floor>/<walk>.mcap`` with its timing beside it, where
``key`` hashes the effective params file and the nodes — ``--set node.key=value`` (repeatable)
overrides a parameter of every namespace's node, so variants never mix. A finished walk is never
run again; two benches on one work directory only duplicate work (every file is written to a
temporary name and renamed). A variant that sets only parameters of ``pdr_kf_node``, ``tll_pf`` or
``backend_node`` replays the base run's ``pdr/odom`` and ``wifi/fix`` (and the walk's scans) through
the nodes it sets parameters of alone (the other back nodes' outputs copied from the base run), so it
costs their time only. ``--floors B1,F7`` and ``--walks-per-floor N`` (the first N test walks
of each floor) make the subsets for development.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

#: (topic, kind) in the table's order
ESTIMATORS: tuple[tuple[str, str], ...] = (
    ("wifi/fix", "causal"), ("pdr_kf/pose", "causal"), ("pdr_kf/path", "smoothed"), ("pf/pose", "causal"),
    ("pf/path", "smoothed"), ("backend/{user}/pose", "causal"), ("backend/{user}/path", "smoothed"))
WKNN = "plain WKNN"
NODES = "imu,wifi,pdr_kf,pf,backend"
#: the estimators after the front end: a variant that changes only these (``--set`` on their nodes)
#: replays the base run's pdr/odom and wifi/fix through them instead of the whole walk
BACK_NODES = {"pdr_kf_node": "pdr_kf", "tll_pf": "pf", "backend_node": "backend"}
#: the topics each back node publishes (a back-only variant copies those of the nodes it does not vary)
BACK_TOPICS = {"pdr_kf": ("pdr_kf/pose", "pdr_kf/path"), "pf": ("pf/pose", "pf/path"), "backend": ()}
#: plain WKNN (the ms_site2 WiFi bench's baseline)
PLAIN = {"k": 4, "shared_threshold": 0.5, "shared_strict": True, "min_signal_dbm": -100.0, "error_type": "rms"}
#: floors the fusion choices were made on (the rest are checked once)
DEVELOPED_ON = ("B1", "F7")


@dataclass
class WalkScore:
    floor: str
    walk: str
    scans: dict[str, np.ndarray] = field(default_factory=dict)      # estimator -> error per instant (nan: not covered)
    waypoints: dict[str, np.ndarray] = field(default_factory=dict)
    wall_s: float = 0.0
    cpu_s: float = 0.0
    walk_s: float = 0.0


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def _set_value(text: str) -> tuple[str, str, Any]:
    node, _, rest = text.partition(".")
    key, eq, value = rest.partition("=")
    if not (node and key and eq):
        raise SystemExit(f"--set: expected NODE.KEY=VALUE, got {text!r}")
    return node, key, yaml.safe_load(value)


def effective_params(import_dir: Path, sets: list[str], work: Path) -> tuple[Path, str]:
    """The import's params.yaml with the ``--set`` overrides applied to every key of their node, written
    to ``WORK/params/<key>.yaml``; returns (path, key)."""
    text = (import_dir / "params.yaml").read_text()
    doc = yaml.safe_load(text)
    for node, key, value in (_set_value(s) for s in sets):
        keys = [k for k in doc if k.rstrip("/").endswith("/" + node)] or [f"/**/{node}"]
        for k in keys:
            doc.setdefault(k, {"ros__parameters": {}})["ros__parameters"]
            cur: dict = doc[k]["ros__parameters"]
            parts = key.split(".")
            for p in parts[:-1]:
                cur = cur.setdefault(p, {})
            cur[parts[-1]] = value
    body = yaml.safe_dump(doc, sort_keys=True)
    digest = hashlib.sha256((body + NODES).encode()).hexdigest()[:12]
    out = work / "params" / f"{digest}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    if not out.exists():
        _atomic_write(out, body)
    return out, digest


def ensure_import(site: Path, work: Path) -> Path:
    """``WORK/import``: the site imported once (all floors, the documented split)."""
    from indoor_loc.commands.import_ms_indoor import import_ms_indoor
    out = work / "import"
    if (out / "params.yaml").exists() and (out / "split.yaml").exists():
        return out
    print(f"importing {site} -> {out} (once)", file=sys.stderr)
    import_ms_indoor(argparse.Namespace(dataset_dir=site, out_dir=out, floors="", walks="", survey_walks="",
                                        storey_height_m=5.0, overwrite=True, metadata=None, floor_levels=""))
    return out


def run_walk(bags: list[Path], out: Path, params: Path, nodes: str,
             copy: tuple[str, ...] = ("ground_truth",)) -> dict[str, float]:
    """One ``indoor-loc run`` of one walk (cached with its timing in ``<out>.json``)."""
    from indoor_loc.pipeline.offline import run_offline
    meta = out.with_suffix(".json")
    if out.exists() and meta.exists():
        return dict(json.loads(meta.read_text()))
    out.parent.mkdir(parents=True, exist_ok=True)
    s = run_offline(bags, out, nodes=nodes.split(","), params=params, progress=False, overwrite=True, copy=copy)
    t = {"wall_s": s.wall_s, "cpu_s": s.cpu_s, "walk_s": s.bag_span_s}
    _atomic_write(meta, json.dumps(t))
    return t


def _truth(bag: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(waypoint stamps, waypoint xy, stamps of the scans inside the waypoint span) of an imported walk."""
    from indoor_loc.bag import read_bag
    from msg_adapters.path import path_from_msg
    from msg_adapters.time import stamp_to_ns
    t = np.zeros(0, np.int64)
    xy = np.zeros((0, 2))
    scans: list[int] = []
    for m in read_bag([bag]):
        if m.topic.endswith("/ground_truth") and m.type == "nav_msgs/msg/Path":
            t, xy, _ = path_from_msg(m.msg)
        elif m.topic.endswith("/wifi/scan"):
            scans.append(stamp_to_ns(m.msg.header.stamp))
    s = np.sort(np.asarray(scans, np.int64))
    if len(t) >= 2:
        s = s[(s >= t[0]) & (s <= t[-1])]
    return np.asarray(t, np.int64), np.asarray(xy, float)[:, :2], s


def _errors(est_t: np.ndarray, est_xy: np.ndarray, at: np.ndarray, truth_xy: np.ndarray) -> np.ndarray:
    """Error per instant of the estimate interpolated there; nan outside the estimate's span."""
    from indoor_loc.eval.metrics import interpolate_xy
    if len(at) == 0:
        return np.zeros(0)
    if len(est_t) == 0:
        return np.full(len(at), np.nan)
    order = np.argsort(est_t, kind="stable")
    p, inside = interpolate_xy(est_t[order], est_xy[order], at)
    e = np.linalg.norm(p - truth_xy, axis=1)
    e[~inside] = np.nan
    return e


def score_walk(floor: str, walk: str, bag: Path, run: Path, timing: dict[str, float], wknn) -> WalkScore:
    from indoor_loc.commands.eval import trajectories_from_bags
    from indoor_loc.eval.metrics import interpolate_xy
    from indoor_loc.errors import DatasetError
    wt, wxy, scan_t = _truth(bag)
    sc = WalkScore(floor, walk, wall_s=timing["wall_s"], cpu_s=timing["cpu_s"], walk_s=timing["walk_s"])
    if len(wt) < 2:
        return sc
    scan_truth, _ = interpolate_xy(wt, wxy, scan_t)
    for topic, _kind in ESTIMATORS:
        try:
            trajs = trajectories_from_bags([run], topic)
        except DatasetError:
            trajs = {}
        tr = next(iter(trajs.values()), None)
        et = np.asarray(tr.stamps_ns, np.int64) if tr is not None else np.zeros(0, np.int64)
        exy = np.asarray(tr.xy, float) if tr is not None else np.zeros((0, 2))
        sc.scans[topic] = _errors(et, exy, scan_t, scan_truth)
        sc.waypoints[topic] = _errors(et, exy, wt, wxy)
    kt, kxy = wknn
    sc.scans[WKNN] = _errors(kt, kxy, scan_t, scan_truth)
    sc.waypoints[WKNN] = _errors(kt, kxy, wt, wxy)
    return sc


def wknn_track(bag: Path, pos) -> tuple[np.ndarray, np.ndarray]:
    """Plain WKNN's fixes of the walk's scans as a track (the scans it cannot locate left out)."""
    from indoor_loc.bag import read_bag
    from msg_adapters.wifi_scan import scan_from_msg
    t, xy = [], []
    for m in read_bag([bag]):
        if m.topic.endswith("/wifi/scan"):
            s = scan_from_msg(m.msg)
            f = pos.locate(s)
            if f.ok:
                t.append(s.stamp_ns)
                xy.append(np.asarray(f.xy, float)[:2])
    return np.asarray(t, np.int64), np.asarray(xy, float).reshape(-1, 2)


def summarise(scores: list[WalkScore], where: str) -> dict[str, dict[str, float]]:
    """Per estimator: mean / median / p95 / coverage at ``where`` (``scans`` or ``waypoints``)."""
    out: dict[str, dict[str, float]] = {}
    for name in [t for t, _ in ESTIMATORS] + [WKNN]:
        e = np.concatenate([getattr(s, where).get(name, np.zeros(0)) for s in scores] or [np.zeros(0)])
        ok = e[np.isfinite(e)]
        out[name] = {"n": int(len(e)), "covered": int(len(ok)),
                     "coverage": float(len(ok) / len(e)) if len(e) else float("nan"),
                     "mean": float(np.mean(ok)) if len(ok) else float("nan"),
                     "median": float(np.median(ok)) if len(ok) else float("nan"),
                     "p95": float(np.percentile(ok, 95)) if len(ok) else float("nan")}
    return out


def _label(topic: str) -> str:
    return topic.replace("{user}", "<u>")


def table(scores: list[WalkScore], title: str) -> tuple[str, dict[str, Any]]:
    sc, wp = summarise(scores, "scans"), summarise(scores, "waypoints")
    n_walks = len(scores)
    lines = [f"### {title}: {n_walks} test walks, {sc[WKNN]['n']} scans, {wp[WKNN]['n']} waypoints", "",
             "| estimator | kind | at scans: mean / median / p95 (m) | × wifi/fix | × WKNN | coverage | "
             "at waypoints: mean / median / p95 (m) | × wifi/fix | × WKNN | coverage |", "|---|---|---|---|---|---|---|---|---|---|"]
    kinds = dict(ESTIMATORS)
    best: dict[str, tuple[str, float]] = {}
    for name in [t for t, _ in ESTIMATORS] + [WKNN]:
        cells = []
        for d in (sc, wp):
            r = d[name]
            cells += [f"{r['mean']:.2f} / {r['median']:.2f} / {r['p95']:.2f}", f"{r['mean'] / d['wifi/fix']['mean']:.2f}",
                      f"{r['mean'] / d[WKNN]['mean']:.2f}", f"{100 * r['coverage']:.1f} %"]
        kind = kinds.get(name, "WiFi only")
        lines.append(f"| `{_label(name)}` | {kind} | " + " | ".join(cells) + " |")
        if kind in ("causal", "smoothed") and name != "wifi/fix" and sc[name]["coverage"] >= 0.99:
            if kind not in best or sc[name]["mean"] < best[kind][1]:
                best[kind] = (name, sc[name]["mean"])
    fix = sc["wifi/fix"]["mean"]
    for kind in ("causal", "smoothed"):
        if kind in best:
            name, m = best[kind]
            lines.append(f"\nbest {kind} (coverage ≥ 99 %): `{_label(name)}` {m:.2f} m = {m / fix:.2f} × wifi/fix "
                         f"at the scans, {wp[name]['mean'] / wp['wifi/fix']['mean']:.2f} × at the waypoints")
    wall = [s.wall_s for s in scores]
    cpu = [s.cpu_s for s in scores]
    walk = [s.walk_s for s in scores]
    if scores:
        lines.append(f"\ntime per walk: wall {np.mean(wall):.1f} s mean (max {np.max(wall):.1f}), CPU {np.mean(cpu):.1f} s "
                     f"mean, for {np.mean(walk):.0f} s of walking mean")
    return "\n".join(lines) + "\n", {"scans": sc, "waypoints": wp, "walks": n_walks,
                                      "wall_s_mean": float(np.mean(wall)) if wall else None,
                                      "cpu_s_mean": float(np.mean(cpu)) if cpu else None}


def per_walk_lines(scores: list[WalkScore]) -> str:
    """One line per walk: scans, and the mean at the scans of wifi/fix and of every other estimator."""
    names = [t for t, _ in ESTIMATORS] + [WKNN]
    lines = ["| floor | walk | scans | " + " | ".join(f"`{_label(n)}`" for n in names) + " |",
             "|---|---|---|" + "---|" * len(names)]
    for s in scores:
        cells = []
        for n in names:
            e = s.scans.get(n, np.zeros(0))
            cells.append(f"{np.nanmean(e):.1f}" if np.isfinite(e).any() else "–")
        lines.append(f"| {s.floor} | {s.walk[:8]} | {len(s.scans.get(WKNN, []))} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    from indoor_loc.wifi.methods import make_positioner
    from indoor_loc.wifi.radiomap import load_radiomap

    t0 = time.perf_counter()
    if getattr(args, "site", None):
        site = Path(args.site)
    else:
        ds = getattr(args, "dataset", "") or "ms_site2"
        site = Path(args.data) / ds
    if not site.is_dir():
        print(f"bench fusion: no site directory {site}", file=sys.stderr)
        return 2
    work = Path(getattr(args, "work", None) or Path("out/bench_fusion")) / site.name
    if str(work).endswith("bench_pf/" + site.name):          # the shared --work default is the pf bench's
        work = Path("out/bench_fusion") / site.name
    work.mkdir(parents=True, exist_ok=True)
    imp = ensure_import(site, work)
    sets = list(getattr(args, "set", None) or [])
    params, key = effective_params(imp, sets, work)
    base_params, base_key = effective_params(imp, [], work)
    back_only = bool(sets) and all(_set_value(x)[0] in BACK_NODES for x in sets)
    # the back nodes a back-only variant changes run again; the others' outputs are the base run's
    varied = [BACK_NODES[n] for n in BACK_NODES if any(_set_value(x)[0] == n for x in sets)]
    split = yaml.safe_load((imp / "split.yaml").read_text())
    floors = [f.strip() for f in (getattr(args, "floors", "") or "").split(",") if f.strip()] or list(split)
    per_floor = int(getattr(args, "walks_per_floor", 0) or 0)
    pos = make_positioner("wknn", dict(PLAIN)).fit(load_radiomap(imp / "radiomap"))
    scores: dict[str, list[WalkScore]] = {}
    for floor in floors:
        walks = split[floor]["test"][:per_floor] if per_floor else split[floor]["test"]
        for k, walk in enumerate(walks):
            bag = imp / floor / f"{walk}.mcap"
            out = work / "runs" / key / floor / f"{walk}.mcap"
            if back_only:       # the front end is the base run's: replay its pdr/odom and wifi/fix
                base = work / "runs" / base_key / floor / f"{walk}.mcap"
                run_walk([bag], base, base_params, NODES)
                timing = run_walk([bag, base], out, params, ",".join(varied),
                                  copy=("wifi/fix",) + tuple(t for n, ts in BACK_TOPICS.items() if n not in varied
                                                             for t in ts))
            else:
                timing = run_walk([bag], out, params, NODES)
            scores.setdefault(floor, []).append(score_walk(floor, walk, bag, out, timing, wknn_track(bag, pos)))
            print(f"\r{floor}: {k + 1}/{len(walks)} walks", end="", file=sys.stderr, flush=True)
        print(file=sys.stderr)
    report: dict[str, Any] = {"site": str(site), "params": str(params), "sets": list(getattr(args, "set", None) or []),
                              "floors": {}}
    print(f"# bench fusion: {site} (params {params}{', ' + ' '.join(sets) if sets else ''}; developed on "
          f"{', '.join(DEVELOPED_ON)}, the other floors checked once)\n")
    if back_only:
        print("(variant of the back-end nodes only: the base run's pdr/odom and wifi/fix replayed through "
              f"{', '.join(varied)}, the other estimators' outputs the base run's; the times below are theirs "
              "alone)\n")
    for floor, sc in scores.items():
        role = "developed on" if floor in DEVELOPED_ON else "held out"
        text, d = table(sc, f"{floor} ({role})")
        print(text)
        report["floors"][floor] = d
    if len(scores) > 1:
        text, d = table([s for v in scores.values() for s in v], "pooled")
        print(text)
        report["pooled"] = d
    if getattr(args, "per_walk", False):
        print(per_walk_lines([s for v in scores.values() for s in v]))
    print(f"bench time: {time.perf_counter() - t0:.0f} s wall")
    if getattr(args, "json", None):
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0
