"""``indoor-loc bench pf``: the graph particle filter on all PUTMC walks, side by side with its
rules and baselines, several seeded Monte Carlo runs; then its cost per step and the TLL
precomputation.

Inputs are made once with the package's own pipeline (cached in ``--work``): the PUTMC import
(bags + the floor's building graph from ``map.png``) replayed through ``imu,wifi,pdr_kf``; the
PF variants then run on the decoded ``pdr/odom`` and ``wifi/fix`` of every walk through the same
:class:`~indoor_loc.pf.tracker.GraphTracker` the ``tll_pf`` node uses.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from indoor_loc.errors import DatasetError

INTERVALS_S = (0.0, 5.0, 10.0, 20.0)
RULES = ("tll", "uniform", "angle")
#: The reference's pose sampling for the route metric: one pose every 256 accelerometer samples
#: (~1.29 s) plus one at every WiFi scan (PUTMC README: sampling density changes the score).
ROUTE_SAMPLE_S = 256 / 199.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=Path("../shared/datasets"), help="datasets directory")
    parser.add_argument("--work", type=Path, default=Path("out/bench_pf"), help="cache for the import and the replay")
    parser.add_argument("--runs", type=int, default=3, help="Monte Carlo runs (seeds 0..runs-1)")
    parser.add_argument("--particles", type=int, default=1000, help="particles per filter")
    parser.add_argument("--walks", default="all", help="comma-separated walk numbers (default all 24)")
    parser.add_argument("--quick", action="store_true", help="one run, PDR rows and the 10 s WiFi-only rows only")
    parser.add_argument("--no-perf", action="store_true", help="skip the performance section")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON here")
    parser.add_argument("--learn", action="store_true",
                        help="also learn the transitions (Dirichlet) from the odd walks' smoothed tracks and "
                             "score them on the even walks")


# ----------------------------------------------------------------------------------------------
def prepare(data: Path, work: Path, walks: str = "all") -> Path:
    """Import PUTMC and replay it through imu,wifi,pdr_kf once; returns the replay bag."""
    from indoor_loc.cli import main as cli_main
    from indoor_loc.pipeline.offline import run_offline

    putmc = data / "putmc"
    if not (putmc / "PUTMC_Floor3_Xperia_trajs").is_dir():
        raise DatasetError(f"PUTMC not found at {putmc}")
    imp = work / "import"
    if not (imp / "params.yaml").exists():
        rc = cli_main(["import", "putmc", str(putmc), str(imp)])
        if rc:
            raise DatasetError("PUTMC import failed")
    run = work / "run.mcap"
    if not run.exists():
        bags = sorted(imp.glob("walk*.mcap"))
        run_offline(bags, run, nodes=["imu", "wifi", "pdr_kf"], params=imp / "params.yaml")
    return run


def load_inputs(run: Path) -> dict[str, dict]:
    """Per walk: odom (T,) stamps + (T, 2) xy; fixes (K,) stamps, (K, 2) xy, (K, 2, 2) cov."""
    from indoor_loc.bag import read_bag
    from msg_adapters.odom import odom_from_msg
    from msg_adapters.pose import fix_from_msg

    out: dict[str, dict] = {}
    for m in read_bag([run]):
        parts = m.topic.strip("/").split("/", 1)
        if len(parts) != 2 or parts[1] not in ("pdr/odom", "wifi/fix"):
            continue
        d = out.setdefault(parts[0], {"odom": [], "fix": []})
        if parts[1] == "pdr/odom":
            o = odom_from_msg(m.msg)
            d["odom"].append((o.stamp_ns, o.x, o.y))
        else:
            f = fix_from_msg(m.msg)
            d["fix"].append((f.stamp_ns, f.xy, f.cov))
    for d in out.values():
        d["odom"].sort(key=lambda r: r[0])
        d["fix"].sort(key=lambda r: r[0])
    return out


def decimate(fixes: list, interval_s: float) -> list:
    """Keep a fix only when at least ``interval_s`` after the last kept one."""
    kept, last = [], None
    for f in fixes:
        if last is None or f[0] - last >= interval_s * 1e9:
            kept.append(f)
            last = f[0]
    return kept


def run_walk(graph, transitions, pf_params, inp: dict, *, seed: int, pdr: bool, interval_s: float = 0.0,
             smooth: bool = False, smooth_samples: int = 50):
    """One walk through a GraphTracker. Returns (filtered stamps, xy), (smoothed stamps, xy) or None."""
    from indoor_loc.pf.tracker import GraphTracker

    tr = GraphTracker(graph, transitions, pf_params, rng=np.random.default_rng(seed), keep_history=smooth)
    fixes = decimate(inp["fix"], interval_s)
    kept = {f[0] for f in fixes}
    events = [(f[0], 1, f) for f in inp["fix"]]
    if pdr:
        events += [(o[0], 0, o) for o in inp["odom"]]
    events.sort(key=lambda e: (e[0], e[1]))
    for stamp, kind, e in events:
        if kind == 0:
            tr.odom(stamp, e[1], e[2])
        elif stamp in kept:
            tr.fix(stamp, e[1], e[2], use_speed_model=not pdr)
        elif tr.initialised and not pdr:
            tr.elapse(stamp)                                 # a skipped scan: predict-only estimate
            tr._record(stamp, 0.0, np.nan, 0.0)
    est = tr.estimates
    filt = (np.array([e.stamp_ns for e in est], np.int64), np.array([e.xy for e in est]).reshape(-1, 2))
    sm = None
    if smooth:
        s = tr.smooth(smooth_samples)
        sm = (np.array([e.stamp_ns for e in s], np.int64), np.array([e.xy for e in s]).reshape(-1, 2))
    return filt, sm


def kf_wifi_only(inp: dict, interval_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Constant-velocity linear KF on the decimated fixes (the WiFi-only KF of the TLL paper's
    comparison), filtered and RTS-smoothed, estimates at every scan time."""
    from indoor_loc.fusion.linear_pdr import LinearPdrParams, filter_batch, fixes_to_arrays, rts_smooth
    from indoor_loc.measurements import Fix

    fixes = inp["fix"]
    kept = {f[0] for f in decimate(fixes, interval_s)}
    stamps = np.array([f[0] for f in fixes], np.int64)
    dt = np.diff(stamps, prepend=stamps[0]) * 1e-9
    fl = [Fix(stamp_ns=f[0], xy=f[1], cov=f[2]) if f[0] in kept else None for f in fixes]
    params = LinearPdrParams(step_length_m=1.0, sigma_dtheta_rad=0.3, sigma_ds_m=0.3, gate=False)
    z, R = fixes_to_arrays(fl[1:])
    track = filter_batch(params, dt[1:], np.zeros(len(dt) - 1), z, R, xy0=fixes[0][1], pos_cov0=fixes[0][2])
    xs, _ = rts_smooth(track)
    # epoch 0 is the first fix itself (the initial state), epochs 1.. the remaining scans
    t = stamps[1:]
    return t, track.x_filt[:, :2], t, xs[:, :2]


# ----------------------------------------------------------------------------------------------
def paper_sampling(stamps_ns: np.ndarray, xy: np.ndarray, scan_ns: np.ndarray, *,
                   scan_span: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The trajectory at the reference's sampling (a pose every :data:`ROUTE_SAMPLE_S` from its
    first stamp, plus every scan stamp inside it), each the latest estimate at or before that time
    (sample and hold: what a causal estimator had published). ``scan_span``: only from the first
    to the last WiFi scan, where the reference has its poses (1 314 on the 24 PUTMC walks; this
    gives 1 374, against 1 575 over the whole trajectory): the true route ends at the last scan
    while the recording and the PDR may go on."""
    t = np.asarray(stamps_ns, np.int64)
    sc = np.asarray(scan_ns, np.int64)
    lo, hi = int(t[0]), int(t[-1])
    if scan_span and len(sc):
        lo, hi = max(lo, int(sc[0])), min(hi, int(sc[-1]))
    grid = np.arange(lo, hi + 1, int(ROUTE_SAMPLE_S * 1e9), dtype=np.int64)
    q = np.unique(np.concatenate([grid, sc[(sc >= lo) & (sc <= hi)]]))
    idx = np.searchsorted(t, q, side="right") - 1
    return q, np.asarray(xy)[np.clip(idx, 0, len(t) - 1)]


def _score(trajs: dict, truths: dict, users: list[str] | None = None) -> dict:
    """Pooled scores: scan-time errors on the estimates as given; route distance (metres, and the
    paper's squared units) at the reference's sampling (:func:`paper_sampling`)."""
    from indoor_loc.commands.eval import evaluate
    from indoor_loc.eval.trajectory import Trajectory
    users = [u for u in (users or sorted(trajs)) if u in trajs and len(trajs[u][0])]
    tj = {u: Trajectory.make(u, *trajs[u]) for u in users}
    scores, _ = evaluate(tj, truths)
    p = scores[-1]
    tr = {u: Trajectory.make(u, *paper_sampling(*trajs[u], truths[u].scan_ns, scan_span=True)) for u in users}
    rs, _ = evaluate(tr, truths)
    r = rs[-1]
    return {"scan_mean": p.scan_m.mean, "scan_med": p.scan_m.median, "scan_p95": p.scan_m.p95,
            "route_mean": r.route_m.mean, "route_rmse": r.route_m.rmse,
            "paper_rmse": r.paper.rmse, "paper_mean": r.paper.mean}


ODD, EVEN = "odd walks (tuned on)", "even walks (held out)"
KEYS = ("scan_mean", "scan_med", "scan_p95", "route_mean", "route_rmse", "paper_rmse", "paper_mean")


def _fmt_runs(rows: list[dict], keys: tuple[str, ...] = KEYS) -> str:
    cells = []
    for k in keys:
        v = np.array([r[k] for r in rows])
        cells.append(f"{v.mean():.2f}" + (f" ± {v.std(ddof=1):.2f}" if len(v) > 1 else ""))
    return " | ".join(cells)


def off_graph(graph, trajs: dict) -> float:
    """Largest distance of any pose to the graph (m)."""
    worst = 0.0
    for _t, xy in trajs.values():
        if len(xy):
            worst = max(worst, float(graph.project(xy)[2].max()))
    return worst


def run(args: argparse.Namespace) -> int:
    """Entry point of ``indoor-loc bench pf`` (options missing from the shared bench CLI default)."""
    for name, default in (("work", Path("out/bench_pf")), ("runs", 3), ("particles", 1000), ("walks", "all"),
                          ("no_perf", False), ("quick", False), ("json", None), ("learn", False)):
        if not hasattr(args, name):
            setattr(args, name, default)
    return main(args)


def main(args: argparse.Namespace) -> int:
    from indoor_loc.commands.eval import trajectories_from_bags, truth_from_import
    from indoor_loc.graph.io import load_graph
    from indoor_loc.graph.tll import TransitionParams, transition_table
    from indoor_loc.pf.filter import PfParams

    work = args.work
    run = prepare(args.data, work)
    graph_file = work / "import" / "graph.yaml"
    if not graph_file.exists():
        raise DatasetError(f"{graph_file} missing: re-import with this version (rm -r {work / 'import'})")
    graph = load_graph(graph_file)
    truths = truth_from_import(work / "import")
    inputs = load_inputs(run)
    users = sorted(set(inputs) & set(truths))
    if args.walks != "all":
        keep = {f"walk{int(w):02d}" for w in args.walks.split(",")}
        users = [u for u in users if u in keep]
    truths = {u: truths[u] for u in users}
    runs = 1 if args.quick else args.runs
    pf_params = PfParams(n_particles=args.particles)
    tables = {r: transition_table(graph, TransitionParams(rule=r)) for r in RULES}
    print(f"PUTMC: {len(users)} walks, {sum(len(inputs[u]['fix']) for u in users)} WiFi fixes; graph "
          f"{graph.n_nodes} nodes / {graph.n_links} links / {graph.link_len.sum():.0f} m; {args.particles} particles; "
          f"{runs} run(s), seeds 0..{runs - 1}")
    header = ("| estimate | scan-time mean | median | p95 | route mean | route RMSE | paper \"RMSE\" (m²) | "
              "paper \"mean\" (m²) |\n|---|---|---|---|---|---|---|---|")
    lines = [header]
    figures: dict[str, list[dict]] = {}
    # the PF's parameters are tuned on the odd walks only; the even walks are held out
    halves = {ODD: [u for u in users if int(u[4:]) % 2 == 1], EVEN: [u for u in users if int(u[4:]) % 2 == 0]}
    split_rows: dict[str, dict[str, list[dict]]] = {}

    def keep(label: str, rows: list[dict], trajs_per_run: list[dict] | None = None) -> str:
        figures[label] = rows
        if trajs_per_run is not None:
            split_rows[label] = {h: [_score(tj, truths, us) for tj in trajs_per_run] for h, us in halves.items() if us}
        return f"| {label} | {_fmt_runs(rows)} |"

    # -- with PDR -----------------------------------------------------------------------------
    t_pf = 0.0
    walk_s = sum((inputs[u]["odom"][-1][0] - inputs[u]["odom"][0][0]) * 1e-9 for u in users if inputs[u]["odom"])
    smooth_off = 0.0
    tll_smoothed: list[dict] = []
    for rule in RULES:
        rows, srows = [], []
        f_runs, s_runs = [], []
        for r in range(runs):
            filt, sm = {}, {}
            t0 = time.process_time()
            for i, u in enumerate(users):
                f, s = run_walk(graph, tables[rule], pf_params, inputs[u], seed=1000 * r + i, pdr=True,
                                smooth=(rule == "tll"))
                filt[u] = f
                if s is not None:
                    sm[u] = s
            if rule == "tll":
                t_pf += time.process_time() - t0
            rows.append(_score(filt, truths))
            f_runs.append(filt)
            if sm:
                srows.append(_score(sm, truths))
                s_runs.append(sm)
                tll_smoothed.append(sm)
                smooth_off = max(smooth_off, off_graph(graph, sm))
        lines.append(keep(f"PF {rule} + PDR, causal", rows, f_runs if rule == "tll" else None))
        if srows:
            lines.append(keep(f"PF {rule} + PDR, backward-simulation smoothed", srows, s_runs))
    kf = trajectories_from_bags([run], "pdr_kf/pose")
    kfs = trajectories_from_bags([run], "pdr_kf/path")
    kf_t = {u: (kf[u].stamps_ns, kf[u].xy) for u in users}
    kfs_t = {u: (kfs[u].stamps_ns, kfs[u].xy) for u in users}
    lines.append(keep("linear KF + PDR, causal (`pdr_kf/pose`)", [_score(kf_t, truths)], [kf_t]))
    lines.append(keep("linear KF + PDR, RTS-smoothed (`pdr_kf/path`)", [_score(kfs_t, truths)], [kfs_t]))
    print("\nWith PDR (pdr/odom + wifi/fix). Scan-time error: estimate interpolated at each scan's stamp vs its true "
          "position. Route: distance to the true route at the reference's sampling (a pose every "
          f"{ROUTE_SAMPLE_S:.2f} s and at every scan, latest estimate held), in metres and in the paper's squared "
          "units (e = d², e < 100 kept).\n")
    print("\n".join(lines))
    print("\nThe same runs per half of the walks (scan-time mean / p95, route RMSE; m). The PF's parameters were "
          "tuned on the odd walks only; the even walks are held out:\n")
    print("| estimate | " + " | ".join(halves) + " |\n|---|" + "---|" * len(halves))
    for label, per in split_rows.items():
        print(f"| {label} | " + " | ".join(_fmt_runs(per[h], ("scan_mean", "scan_p95", "route_rmse")).replace(" | ", " / ")
                                          for h in halves if h in per) + " |")
    print(f"\nsmoothed poses: farthest from the graph {smooth_off:.3f} m; PF TLL + PDR + smoother ran "
          f"{walk_s * runs / max(t_pf, 1e-9):.1f}x real time (CPU time) ({walk_s:.0f} s of walks per run)")
    if args.learn:
        learned_rows(graph, tables["tll"], pf_params, inputs, truths, halves, tll_smoothed[0], runs)

    # -- WiFi only ----------------------------------------------------------------------------
    lines = [header]
    intervals = (10.0,) if args.quick else INTERVALS_S
    for iv in intervals:
        label = "every scan" if iv == 0 else f"≥ {iv:.0f} s"
        for rule in RULES:
            rows = []
            for r in range(runs):
                filt = {u: run_walk(graph, tables[rule], pf_params, inputs[u], seed=1000 * r + i, pdr=False,
                                    interval_s=iv)[0] for i, u in enumerate(users)}
                rows.append(_score(filt, truths))
            lines.append(keep(f"{label}: PF {rule}", rows))
        kff, kfsm = {}, {}
        for u in users:
            t, xf, t2, xs = kf_wifi_only(inputs[u], iv)
            kff[u], kfsm[u] = (t, xf), (t2, xs)
        lines.append(keep(f"{label}: KF constant velocity, filtered", [_score(kff, truths)]))
        lines.append(keep(f"{label}: KF constant velocity, RTS-smoothed", [_score(kfsm, truths)]))
    print("\nWiFi only (wifi/fix at the given minimum interval; scored at every scan time):\n")
    print("\n".join(lines))
    if not args.no_perf:
        perf(graph, graph_file)
    if args.json:
        import json
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"walks": users, "runs": runs, "particles": args.particles,
                                         "graph": {"nodes": graph.n_nodes, "links": graph.n_links},
                                         "rows": figures}, indent=1))
    return 0


def learned_rows(graph, prior, pf_params, inputs: dict, truths: dict, halves: dict, smoothed: dict,
                 runs: int, a: float = 10.0) -> None:
    """TLL prior vs its Dirichlet update learned from the odd walks' smoothed tracks (run 0),
    both scored on the even walks (held out from the learning)."""
    from indoor_loc.graph.tll import learn_transitions, link_sequence
    learn_on, test_on = halves[ODD], halves[EVEN]
    seqs = [link_sequence(graph, smoothed[u][1]) for u in learn_on if u in smoothed]
    learned = learn_transitions(graph, prior, seqs, a=a)
    print(f"\nLearned transitions (Dirichlet, a = {a:g}, from the smoothed tracks of {len(seqs)} odd walks), "
          f"scored on the {len(test_on)} even walks:\n")
    print("| estimate | scan-time mean | median | p95 | route mean | route RMSE | paper \"RMSE\" (m²) | "
          "paper \"mean\" (m²) |\n|---|---|---|---|---|---|---|---|")
    for label, table in (("TLL", prior), ("TLL + learned", learned)):
        for pdr, iv, what in ((True, 0.0, "+ PDR, causal"), (False, 10.0, "WiFi only ≥ 10 s")):
            rows = []
            for r in range(runs):
                tr = {u: run_walk(graph, table, pf_params, inputs[u], seed=1000 * r + i, pdr=pdr, interval_s=iv)[0]
                      for i, u in enumerate(test_on)}
                rows.append(_score(tr, truths))
            print(f"| PF {label} {what} | {_fmt_runs(rows)} |")


def perf(graph, graph_file: Path) -> None:
    """Cost per step (predict + update + resample) and TLL precomputation."""
    from indoor_loc.graph.model import build_graph
    from indoor_loc.graph.tll import TransitionParams, total_link_lengths, transition_table
    from indoor_loc.pf.filter import GraphParticleFilter, PfParams

    tables = transition_table(graph, TransitionParams())
    rng = np.random.default_rng(0)
    print("\nPerformance: CPU time of this process (one core; robust to other load on the machine, which wall-clock time is not):\n")
    print("| particles | predict (PDR hop) | WiFi update | resample | total per step |\n|---|---|---|---|---|")
    centre = graph.node_xyz[:, :2].mean(axis=0)
    for n in (400, 4_000, 40_000):
        pf = GraphParticleFilter(graph, tables, PfParams(n_particles=n))
        pf.init_gaussian(centre, np.eye(2) * 400.0, rng)
        reps = max(3, int(2_000 / max(1, n // 100)))
        t = [0.0, 0.0, 0.0]
        for k in range(reps):
            t0 = time.process_time()
            pf.predict_pdr(0.6, 0.3 * k, rng)
            t1 = time.process_time()
            pf.update_position(centre + rng.normal(0, 3, 2), np.eye(2) * 9.0, rng)
            t2 = time.process_time()
            pf.p.log_w = pf.p.log_w  # resample unconditionally to time it
            from indoor_loc.pf.filter import systematic_resample
            idx = systematic_resample(pf.p.weights, rng)
            pf.p = pf.p.take(idx)
            pf.p.log_w[:] = -np.log(n)
            t3 = time.process_time()
            t[0] += t1 - t0
            t[1] += t2 - t1
            t[2] += t3 - t2
        ms = [1e3 * x / reps for x in t]
        print(f"| {n} | {ms[0]:.2f} ms | {ms[1]:.2f} ms | {ms[2]:.2f} ms | {sum(ms):.2f} ms "
              f"({0.32e3 / sum(ms):.0f}x real time at one PDR hop per 0.32 s) |")
    t0 = time.process_time()
    total_link_lengths(graph, 40.0)
    t_putmc = time.process_time() - t0
    side = 72                                                     # 2 * 72 * 71 = 10 224 links
    ii, jj = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    ids = (ii * side + jj).ravel()
    links = [(a, a + 1) for a in ids if a % side != side - 1] + [(a, a + side) for a in ids if a < side * (side - 1)]
    g2 = build_graph(ids, np.column_stack([jj.ravel(), ii.ravel()]).astype(float) * 2.0, links)
    t0 = time.process_time()
    total_link_lengths(g2, 40.0)
    t_big = time.process_time() - t0
    print(f"\nTLL precomputation (l_MAX 40 m): PUTMC graph ({graph.n_links} links) {t_putmc:.2f} s; "
          f"synthetic 2 m grid ({g2.n_links} links) {t_big:.1f} s")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="indoor-loc bench pf", description=__doc__)
    add_arguments(ap)
    raise SystemExit(main(ap.parse_args()))
