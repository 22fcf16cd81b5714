"""``indoor-loc map from-image|from-geojson|draw|learn``: make building-graph files, look at them,
learn their link-choice probabilities.

- ``indoor-loc map from-image PLAN.png --px-per-m S -o GRAPH.yaml [--grid CELL_M] [--seeds XY.csv]``:
  the free space's skeleton of a floor-plan bitmap as a link graph, or the grid of free cells
  (:mod:`indoor_loc.graph.from_image`; ``--origin X Y`` places the image's bottom-left corner).
- ``indoor-loc map from-geojson FLOOR.geojson -o GRAPH.yaml``: the simulator's building file gives
  its own authored graph (all floors, stairs as vertical links) unless ``--from-walls``; any other
  GeoJSON (wall lines, or a floor outline with obstacle polygons, in metres or longitude/latitude)
  is rasterised (:mod:`indoor_loc.graph.from_geojson`) and skeletonised like a plan.
- ``indoor-loc map draw GRAPH.yaml -o OUT.png [--plan PLAN.png --px-per-m S] [--truth IMPORT_DIR]``:
  an overlay of the graph on the plan, with the true routes of an imported dataset, and the
  distance of every true route point (sampled every 0.25 m) and true scan position to the graph.
- ``indoor-loc map learn GRAPH.yaml BAG... -o LEARNED.npz [--topic pf/path] [--a 10]``: the
  Dirichlet update (Koivisto et al. 2014, eq. 8–9) of the graph's TLL table from the link choices
  of recorded tracks — the smoothed ``pf/path`` of each namespace, snapped to the graph — written
  for that graph file (:func:`indoor_loc.graph.tll.save_transitions`).

Every graph output is a versioned graph file (:mod:`indoor_loc.graph.io`), validated before it is
written; an existing output is refused unless ``--overwrite``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from indoor_loc.errors import ConfigError, MapError


def _plan_options(p: argparse.ArgumentParser) -> None:
    from indoor_loc.graph.from_image import PlanParams
    d = PlanParams()
    p.add_argument("--wall-threshold", type=int, default=d.wall_threshold,
                   help=f"grey level below which a pixel is a wall (default {d.wall_threshold})")
    p.add_argument("--clearance-m", type=float, default=d.clearance_m,
                   help=f"keep this distance from walls, m (default {d.clearance_m})")
    p.add_argument("--min-spur-m", type=float, default=d.min_spur_m,
                   help=f"prune dead-end links shorter than this, m (default {d.min_spur_m})")
    p.add_argument("--simplify-m", type=float, default=d.simplify_m,
                   help=f"straighten skeleton chains within this tolerance, m (default {d.simplify_m})")
    p.add_argument("--envelope-gap-m", type=float, default=d.envelope_gap_m,
                   help=f"outer-wall gaps up to twice this are closed to find the inside, m; 0 = off "
                        f"(default {d.envelope_gap_m})")
    p.add_argument("--grid", type=float, metavar="CELL_M", help="a grid of free cells of this side instead of the skeleton")
    p.add_argument("--seeds", type=Path, help="CSV/whitespace file of x y map points: keep the free space containing them")
    p.add_argument("-o", "--out", type=Path, required=True, help="graph file to write (.yaml)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    a = sub.add_parser("from-image", help="floor-plan bitmap -> graph file")
    a.add_argument("plan", type=Path, help="floor plan image (PNG, ...): dark walls on a light background")
    a.add_argument("--px-per-m", type=float, required=True, help="image scale, pixels per metre")
    a.add_argument("--origin", type=float, nargs=2, default=(0.0, 0.0), metavar=("X", "Y"),
                   help="map position (m) of the image's bottom-left corner (default 0 0)")
    _plan_options(a)
    g = sub.add_parser("from-geojson", help="GeoJSON floor shapes (or the simulator's building file) -> graph file")
    g.add_argument("geojson", type=Path)
    g.add_argument("--resolution-m", type=float, default=0.05, help="raster cell size, m (default 0.05)")
    g.add_argument("--floor", type=int, help="use only features with this 'floor' property")
    g.add_argument("--extent", type=float, nargs=2, metavar=("W", "H"),
                   help="stretch the shapes' bounding box onto [0, W] x [0, H] m (e.g. a floor_info.json's size)")
    g.add_argument("--from-walls", action="store_true",
                   help="simulator building file: skeletonise its walls instead of taking its authored graph")
    _plan_options(g)
    d = sub.add_parser("draw", help="overlay a graph on its plan (and an imported dataset's true routes)")
    d.add_argument("graph", type=Path)
    d.add_argument("-o", "--out", type=Path, required=True, help="PNG to write")
    d.add_argument("--plan", type=Path, help="floor plan drawn underneath: an image (with --px-per-m, --origin) or "
                                              "a nav2 map_server YAML (its own scale and origin: OUT/sim/floor_plans/"
                                              "floor0.yaml)")
    d.add_argument("--px-per-m", type=float, help="plan scale, pixels per metre (with --plan)")
    d.add_argument("--origin", type=float, nargs=2, default=(0.0, 0.0), metavar=("X", "Y"))
    d.add_argument("--truth", type=Path, help="import directory (bags with ground_truth): draw and score its routes")
    d.add_argument("--width-in", type=float, default=14.0, help="figure width, inches (default 14)")
    d.add_argument("--dpi", type=int, default=80)
    le = sub.add_parser("learn", help="learn link-choice probabilities from recorded tracks (Dirichlet update)")
    le.add_argument("graph", type=Path)
    le.add_argument("bags", nargs="+", type=Path, help="bags with the tracks (every namespace's --topic)")
    le.add_argument("--topic", default="pf/path", help="relative topic of the tracks (default pf/path)")
    le.add_argument("--a", type=float, default=10.0, help="prior weight: pseudo-counts of the TLL prior per row (default 10)")
    le.add_argument("--rule", default="tll", choices=("tll", "uniform", "angle"), help="prior rule (default tll)")
    le.add_argument("--max-off-m", type=float, default=1.0,
                    help="drop track poses farther than this from the graph, m (default 1)")
    le.add_argument("-o", "--out", type=Path, required=True, help="table to write (.npz)")
    le.add_argument("--overwrite", action="store_true")


def _params(args: argparse.Namespace, **extra):
    from indoor_loc.graph.from_image import PlanParams
    p = PlanParams(wall_threshold=args.wall_threshold, clearance_m=args.clearance_m, min_spur_m=args.min_spur_m,
                   simplify_m=args.simplify_m, envelope_gap_m=args.envelope_gap_m, **extra)
    p.validate()
    return p


def read_points(path: Path) -> np.ndarray:
    """(N, 2) x y from a text file: comma or whitespace separated, '#' comments, an optional header."""
    rows = []
    try:
        text = path.read_text()
    except OSError as err:
        raise ConfigError(f"cannot read {path}: {err}") from err
    for k, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].replace(",", " ").split()
        if not line:
            continue
        try:
            rows.append((float(line[0]), float(line[1])))
        except (ValueError, IndexError):
            if rows:
                raise ConfigError(f"{path}:{k}: expected 'x y', got {' '.join(line)!r}") from None
    if not rows:
        raise ConfigError(f"{path}: no 'x y' points")
    return np.array(rows)


def _check_out(args: argparse.Namespace) -> None:
    if args.out.exists() and not args.overwrite:
        raise ConfigError(f"{args.out} exists; pass --overwrite to replace it")


def _build(grey: np.ndarray, p, args: argparse.Namespace):
    from indoor_loc.graph.from_image import grid_graph, skeleton_graph
    seeds = read_points(args.seeds) if args.seeds else None
    if args.grid is not None:
        return grid_graph(grey, p, args.grid, seeds_xy=seeds)
    return skeleton_graph(grey, p, seeds_xy=seeds)


def _write(g, args: argparse.Namespace, source: dict) -> int:
    from indoor_loc.graph.io import load_graph, save_graph
    tmp = args.out.with_name(args.out.name + ".partial")
    save_graph(g, tmp, source=source)
    load_graph(tmp)                     # the written file validates
    tmp.replace(args.out)
    print(f"{args.out}: {g.n_nodes} nodes, {g.n_links} links, {g.link_len.sum():.0f} m, "
          f"{len(g.floors)} floor(s)")
    return 0


def from_image(args: argparse.Namespace) -> int:
    from indoor_loc.graph.from_image import read_plan
    _check_out(args)
    p = _params(args, px_per_m=args.px_per_m, origin_x_m=args.origin[0], origin_y_m=args.origin[1])
    g = _build(read_plan(args.plan), p, args)
    src = {"tool": "indoor-loc map from-image", "image": args.plan.name, "px_per_m": args.px_per_m,
           "origin_m": list(args.origin), "wall_threshold": p.wall_threshold, "clearance_m": p.clearance_m,
           "envelope_gap_m": p.envelope_gap_m, "method": f"grid {args.grid} m" if args.grid else "skeleton"}
    return _write(g, args, src)


def from_geojson(args: argparse.Namespace) -> int:
    from indoor_loc.graph.from_geojson import rasterise
    _check_out(args)
    try:
        data = json.loads(args.geojson.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise MapError(f"cannot read GeoJSON {args.geojson}: {err}") from err
    src = {"tool": "indoor-loc map from-geojson", "geojson": args.geojson.name}
    if isinstance(data, dict) and "indoor_loc" in data and not args.from_walls:
        from indoor_loc.sim.building import building_from_geojson, building_graph
        g = building_graph(building_from_geojson(data, str(args.geojson)))
        return _write(g, args, {**src, "method": "authored graph of the building file"})
    floor = args.floor
    if floor is None and isinstance(data, dict) and "indoor_loc" in data:
        floor = 0
    plan = rasterise(data, resolution_m=args.resolution_m, floor=floor,
                     extent_m=tuple(args.extent) if args.extent else None, where=str(args.geojson))
    p = plan.plan_params(_params(args))
    g = _build(plan.grey, p, args)
    src.update({"method": f"grid {args.grid} m" if args.grid else "skeleton", "resolution_m": args.resolution_m,
                "floor": floor, "lonlat": plan.lonlat, "extent_m": list(args.extent) if args.extent else None,
                "walls": plan.n_walls, "areas": plan.n_areas})
    return _write(g, args, src)


def route_points(segments: np.ndarray, step_m: float = 0.25) -> np.ndarray:
    """Points every ``step_m`` along segments (L, 2, 2), both ends included."""
    out = []
    for a, b in np.asarray(segments, float):
        k = max(2, int(np.linalg.norm(b - a) / step_m) + 1)
        out.append(a + np.linspace(0.0, 1.0, k)[:, None] * (b - a))
    return np.vstack(out) if out else np.zeros((0, 2))


def draw(args: argparse.Namespace) -> int:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    from indoor_loc.graph.io import load_graph
    g = load_graph(args.graph)
    fig_w = args.width_in
    xy = g.node_xyz[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    extent = None
    grey = None
    if args.plan is not None:
        from indoor_loc.graph.nav2_map import is_nav2_yaml, read_nav2_map
        if is_nav2_yaml(args.plan):
            nav2 = read_nav2_map(args.plan)
            grey, px_per_m, origin = nav2.grey, nav2.px_per_m, nav2.origin[:2]
        else:
            if not args.px_per_m:
                raise ConfigError("--plan needs --px-per-m (or give the plan's nav2 map_server YAML)")
            from indoor_loc.graph.from_image import read_plan
            grey, px_per_m, origin = read_plan(args.plan), args.px_per_m, tuple(args.origin)
        h, w = grey.shape
        extent = (origin[0], origin[0] + w / px_per_m, origin[1], origin[1] + h / px_per_m)
        lo = np.minimum(lo, [extent[0], extent[2]])
        hi = np.maximum(hi, [extent[1], extent[3]])
    aspect = (hi[1] - lo[1]) / max(hi[0] - lo[0], 1e-9)
    fig, ax = plt.subplots(figsize=(fig_w, max(2.0, fig_w * aspect) + 0.6), dpi=args.dpi)
    if grey is not None:
        ax.imshow(grey, cmap="gray", extent=extent, vmin=0, vmax=255, alpha=0.55, interpolation="antialiased")
    summary = []
    if args.truth is not None:
        from indoor_loc.commands.eval import truth_from_import
        truths = truth_from_import(args.truth)
        segs = np.concatenate([t.segments for t in truths.values()])
        ax.add_collection(LineCollection(segs, colors="tab:green", linewidths=3.0, alpha=0.35,
                                         label=f"true routes ({len(truths)} walks)"))
        pts = route_points(segs)
        d = g.project(pts)[2]
        scans = np.concatenate([t.scan_xy for t in truths.values() if len(t.scan_xy)] or [np.zeros((0, 2))])
        ds = g.project(scans)[2] if len(scans) else np.zeros(0)
        far = d > 1.5
        if far.any():
            ax.plot(pts[far, 0], pts[far, 1], ".", color="tab:blue", ms=3, label="route > 1.5 m from the graph")
        summary.append(f"route points ({len(d)}, every 0.25 m) to the graph: mean {d.mean():.2f} m, "
                       f"p95 {np.percentile(d, 95):.2f} m, max {d.max():.2f} m")
        if len(ds):
            summary.append(f"true scan positions ({len(ds)}) to the graph: mean {ds.mean():.2f} m, "
                           f"p95 {np.percentile(ds, 95):.2f} m, max {ds.max():.2f} m")
        per = sorted(((float(g.project(route_points(t.segments))[2].max()), u) for u, t in truths.items()), reverse=True)
        summary.append("farthest per walk: " + ", ".join(f"{u} {v:.1f} m" for v, u in per[:5]))
    hor = ~g.link_vertical
    ax.add_collection(LineCollection(g.node_xyz[g.link_nodes[hor]][:, :, :2], colors="tab:red", linewidths=1.0,
                                     label=f"graph ({g.n_nodes} nodes, {g.n_links} links)"))
    ax.plot(xy[:, 0], xy[:, 1], ".", color="tab:red", ms=2)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="lower left", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out)
    plt.close(fig)
    for line in summary:
        print(line)
    print(f"wrote {args.out}")
    return 0


def learn(args: argparse.Namespace) -> int:
    from indoor_loc.commands.eval import trajectories_from_bags
    from indoor_loc.graph.io import load_graph
    from indoor_loc.graph.tll import (TransitionParams, count_choices, learn_transitions, link_sequence,
                                      save_transitions, transition_table)
    _check_out(args)
    g = load_graph(args.graph)
    trajs = trajectories_from_bags(list(args.bags), args.topic)
    seqs = []
    dropped = 0
    for tr in trajs.values():
        d = g.project(tr.xy)[2] if len(tr.xy) else np.zeros(0)
        on = d <= args.max_off_m
        dropped += int((~on).sum())
        seqs.append(link_sequence(g, tr.xy[on]))
    prior = transition_table(g, TransitionParams(rule=args.rule))
    counts = count_choices(g, seqs)
    post = learn_transitions(g, prior, seqs, a=args.a)
    save_transitions(post, args.out, args.graph,
                     note=f"{args.rule} prior, a={args.a}, {len(trajs)} tracks from {args.topic}")
    changed = np.abs(post.probs - prior.probs).sum(axis=1) / 2
    print(f"{args.out}: {len(trajs)} tracks, {int(counts.sum())} observed link choices at "
          f"{int((counts.sum(axis=1) > 0).sum())} of {len(counts)} arrivals ({dropped} poses > {args.max_off_m} m "
          f"off the graph dropped); largest change of a row {changed.max():.2f}, mean over observed rows "
          f"{changed[counts.sum(axis=1) > 0].mean() if counts.sum() else 0.0:.2f}")
    return 0


def main(args: argparse.Namespace) -> int:
    return {"from-image": from_image, "from-geojson": from_geojson, "draw": draw, "learn": learn}[args.action](args)
