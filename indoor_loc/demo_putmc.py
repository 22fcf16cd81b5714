"""``indoor-loc demo --dataset putmc``: the pipeline on the real PUTMC dataset, end to end (offline replay).

1. import the PUTMC walks into MCAP bags + radio map + params.yaml (once; cached in OUT/import);
2. replay them offline through the nodes ``imu`` (FFT stepometer + PDR from the phone's
   orientation), ``wifi`` (WKNN fixes against the 114-scan survey map) and ``pdr_kf`` (Raitoharju et al. 2015
   linear PDR Kalman filter + RTS smoother), exactly as the live nodes would run -> OUT/run.mcap;
3. score WiFi-only, filtered and smoothed trajectories against the ground truth (Nowicki & Skrzypczyński 2019
   convention and true metres, route and scan-time errors), beside the published reference;
4. plot one walk on the floor plan -> OUT/walkNN.png, and write every trajectory as CSV.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from indoor_loc.errors import DatasetError

NODES = ["imu", "wifi", "pdr_kf"]
# (label, topic) scored from the run bag
ESTIMATES = [("WiFi only, WKNN (wifi/fix)", "wifi/fix"),
             ("PDR + WiFi linear KF, filtered (pdr_kf/pose)", "pdr_kf/pose"),
             ("PDR + WiFi linear KF, RTS-smoothed (pdr_kf/path)", "pdr_kf/path")]
# Published / reference figures on the same 24 walks (../shared/datasets/README.md):
REFERENCE = [("reference C++: separate graph, no step-length est.", 6.24, 2.42, 1.123, 2.86, 2.20, 7.97),
             ("reference C++: joint graph + step-length est.", 4.65, 2.11, 1.076, 2.78, 2.10, 6.87)]


def main(args: argparse.Namespace) -> int:
    from indoor_loc.cli import main as cli_main
    from indoor_loc.commands.eval import evaluate, trajectories_from_bags, truth_from_import
    from indoor_loc.eval.trajectory import write_csv
    from indoor_loc.pipeline.offline import run_offline

    putmc = Path(args.data) / "putmc"
    if not (putmc / "PUTMC_Floor3_Xperia_trajs").is_dir():
        raise DatasetError(f"PUTMC dataset not found at {putmc}: run from the repository root with ../shared beside "
                           f"it, or pass --data DATASETS_DIR")
    out = Path(args.out)
    imp = out / "import"
    t0 = time.perf_counter()
    params = imp / "params.yaml"
    # params files from before /**/ keys configure no namespaced node: import again
    if args.reimport or not params.exists() or "/**/" not in params.read_text():
        print(f"== 1/4 import PUTMC -> {imp}")
        argv = (["import", "putmc", str(putmc), str(imp), "--overwrite"]
                + ([] if args.walks == "all" else ["--walks", args.walks]))
        rc = cli_main(argv)
        if rc:
            return rc
    else:
        print(f"== 1/4 import: using {imp} (--reimport to redo)")
    bags = sorted(imp.glob("walk*.mcap"))
    if args.walks != "all":
        keep = {f"walk{int(w):02d}.mcap" for w in args.walks.split(",")}
        bags = [b for b in bags if b.name in keep]
    run = out / "run.mcap"
    print(f"== 2/4 replay {len(bags)} bags through nodes {','.join(NODES)} -> {run}")
    summary = run_offline(bags, run, nodes=NODES, params=imp / "params.yaml", overwrite=True)
    print(f"   {summary.messages_in} messages in, {summary.messages_out} out, {summary.bag_span_s:.0f} s of "
          f"recordings in {summary.wall_s:.1f} s")
    for name, kv in summary.per_stage.items():
        if kv.get("rejected.total", "0") != "0":
            print(f"   {name}: rejected " + ", ".join(f"{k[9:]}={v}" for k, v in kv.items()
                                                     if k.startswith("rejected.") and k != "rejected.total"))

    print("== 3/4 score against ground truth")
    truths = truth_from_import(imp)
    rows, trajs_by_topic = [], {}
    for label, topic in ESTIMATES:
        trajs = trajectories_from_bags([run], topic)
        trajs_by_topic[topic] = trajs
        scores, _ = evaluate(trajs, truths)
        p = scores[-1]
        rows.append((label, p.paper.rmse, p.paper.mean, p.route_m.mean, p.scan_m.mean, p.scan_m.median, p.scan_m.p95))
        (out / "trajectories" / topic.replace("/", "_")).mkdir(parents=True, exist_ok=True)
        for u, tr in trajs.items():
            write_csv(out / "trajectories" / topic.replace("/", "_") / f"{u}.csv", tr)
    print(_table(rows, len(bags)))

    print("== 4/4 plot")
    walk = f"walk{args.plot_walk:02d}"
    smooth = trajs_by_topic["pdr_kf/path"]
    if walk in smooth and walk in truths:
        from indoor_loc.datasets.putmc import map_extent
        from indoor_loc.eval.plot import plot_walk
        scores, _ = evaluate({walk: smooth[walk]}, {walk: truths[walk]})
        s = scores[0]
        png = plot_walk(out / f"{walk}.png", truths[walk], smooth[walk], floor_plan=putmc / "map.png",
                        extent=map_extent(), title=f"{walk}: PDR + WiFi, RTS-smoothed — scan-time mean "
                        f"{s.scan_m.mean:.2f} m, route mean {s.route_m.mean:.2f} m")
        print(f"   {png}")
    else:
        print(f"   {walk} not in this run; pass --plot-walk N")
    print(f"trajectories (CSV): {out / 'trajectories'}; bags: {run}; done in {time.perf_counter() - t0:.0f} s")
    return 0


def _table(rows, n_walks: int) -> str:
    head = (f"{'estimate (' + str(n_walks) + ' walks, pooled)':52s} | {'paper RMSE':>10s} {'paper mean':>10s} | "
            f"{'route mean':>10s} | {'scan mean':>9s} {'median':>6s} {'p95':>6s}")
    units = f"{'':52s} | {'(m², as published)':>21s} | {'(m)':>10s} | {'scan-time error (m)':>23s}"
    lines = [head, units, "-" * len(head)]
    for label, prmse, pmean, rmean, smean, smed, sp95 in rows:
        lines.append(f"{label:52s} | {prmse:10.2f} {pmean:10.2f} | {rmean:10.3f} | {smean:9.2f} {smed:6.2f} {sp95:6.2f}")
    lines.append("-" * len(head))
    for label, prmse, pmean, rmean, smean, smed, sp95 in REFERENCE:
        lines.append(f"{label:52s} | {prmse:10.2f} {pmean:10.2f} | {rmean:10.3f} | {smean:9.2f} {smed:6.2f} {sp95:6.2f}")
    lines.append("(reference rows: Nowicki & Skrzypczyński 2019's authors' C++ on all 24 walks, ../shared/datasets/README.md)")
    return "\n".join(lines)
