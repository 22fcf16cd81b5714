"""``indoor-loc bench backend``: the multi-user graph back-end on PUTMC, side by side with the paper.

Nowicki & Skrzypczyński, "A Multi-user Personal Indoor Localization System Employing Graph-based
Optimization", Sensors 2019 (GPLv3 dataset). All 24 walks go through the same front end as
``imu_node`` (FFT stepometer, the phone's heading) into :class:`MultiUserGraph`, one walk after
another (1…24, as the paper's joint run: each walk may match the survey and every earlier walk's
scans), optimised once at the end with 15 iterations, like the authors' C++ (batch mode); the live
mode (a window optimisation at every scan, then the final optimisation) is timed beside it.

Scoring at the paper's pose sampling: a pose per 1.28 s stepometer window plus one per scan, from a
walk's first to its last localised scan (the reference's trajectories span the same interval);
"paper" = the published convention (squared route distance, e < 100, see
``../shared/datasets/README.md``), "true" = the same distances in metres, "scan" = the trajectory
interpolated at each scan's stamp against its surveyed position. Reference figures: the authors'
C++ rebuilt and run on the same data (``putmc/REFERENCE.md``, ``datasets/README.md``).

Sections: Table 2 side by side (pooled and per sequence), the importer's default configuration
(the paper's graph with information from measured noise and a Huber kernel, see
``PUTMC_GRAPH_PARAMS``) on the odd walks its parameters were chosen on and on the held-out even ones,
estimated step length per sequence, the reduced-map experiment (survey kept at 90…50 %, seeded
draws), wall and CPU time and peak memory, in this process and (each configuration from scratch) in
fresh processes (:mod:`indoor_loc.bench.backend_run`), each from scratch with one process and with
the walks' front ends in worker processes (one per core). ``python -m indoor_loc.bench.backend``
prints only the timing tables.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import tempfile
import tracemalloc
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from indoor_loc.backend.graph import GraphParams, MultiUserGraph
from indoor_loc.bench.backend_run import (DEFAULT, READING, STEPS, Putmc, configs, from_scratch, load,
                                          run_graph, run_graph_timed, scratch)
from indoor_loc.eval.metrics import paper_score, point_segment_distance, scan_time_errors
from indoor_loc.wifi.types import RadioMap

__all__ = ["CONFIGS", "DEFAULT", "READING", "STEPS", "Putmc", "load", "run", "run_graph", "run_graph_timed"]

#: walks whose errors chose DEFAULT's parameters (the odd ones); the even ones are held out
TUNING_WALKS = tuple(range(1, 25, 2))
#: the paper's four configurations (users separate/joint x step length off/on) and the default
CONFIGS: dict[str, GraphParams] = configs()
#: reference C++ (paper Table 2 as rebuilt): paper RMSE, paper mean, true RMSE, true mean, scan mean, scan p95
REFERENCE = {
    "separate, no step-length est.": (6.24, 2.42, 1.555, 1.123, 2.86, 7.97),
    "separate, step-length est.": (5.19, 2.21, 1.487, 1.092, 2.86, 7.97),
    "joint, no step-length est.": (4.77, 2.16, 1.469, 1.088, 2.78, 6.87),
    "joint, step-length est.": (4.65, 2.11, 1.452, 1.076, 2.78, 6.87),
}
REF_KEYS = {"separate, no step-length est.": "iUC_false_sLE_false", "separate, step-length est.": "iUC_false_sLE_true",
            "joint, no step-length est.": "iUC_true_sLE_false", "joint, step-length est.": "iUC_true_sLE_true"}
REF_TIME_S = {"separate": (0.6, 0.95), "joint": (1.0, 1.6)}
REF_MEMORY_MB = (15, 18)
#: worker processes of the parallel front end timed beside one process: the cores this process may use
#: (at least 2, so that the rows show what workers cost where there is no second core)
JOBS = max(2, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))
#: the configurations timed in fresh processes with ``--quick`` (all of them otherwise)
QUICK_FRESH = ("separate, no step-length est.", "joint, step-length est.")


def errors(data: Putmc, g: MultiUserGraph) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per walk: route distances of the poses at the paper's sampling, scan-time errors."""
    out = {}
    for n in data.walks:
        st, x = g.trajectory(data.events[n].name)
        scan_t, scan_xy = data.truth[n]
        if len(st) == 0:
            out[n] = (np.zeros(0), np.full(len(scan_t), np.nan))
            continue
        tr = g.users[data.events[n].name]
        wifi_poses = set(g.wifi.view("pose")[np.isin(g.wifi.view("pose"), tr.poses)].tolist())
        loc = [int(g.poses.stamp[i]) for i in tr.poses if i in wifi_poses]
        inside = (st >= min(loc)) & (st <= max(loc)) if loc else np.ones(len(st), bool)
        out[n] = (point_segment_distance(x[inside, :2], data.segments[n]),
                  scan_time_errors(st, x[:, :2], scan_t, scan_xy)[0])
    return out


def summary(errs: list[tuple[np.ndarray, np.ndarray]]) -> tuple[float, ...]:
    d = np.concatenate([e[0] for e in errs])
    s = np.concatenate([e[1] for e in errs])
    ps = paper_score(d)
    k = d[d * d < 100]
    return (ps.rmse, ps.mean, float(np.sqrt(np.mean(k * k))), float(np.mean(k)), float(np.nanmean(s)),
            float(np.nanpercentile(s, 95)), len(d))


def reference_per_sequence(data_dir: Path) -> dict[int, dict[str, tuple[float, float, float]]]:
    """REFERENCE.md: per sequence and configuration (paper RMSE, paper mean, true mean d)."""
    path = Path(data_dir) / "putmc" / "REFERENCE.md"
    out: dict[int, dict[str, tuple[float, float, float]]] = {}
    if not path.is_file():
        return out
    keys = list(REF_KEYS.values())
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 6 and cells[0].isdigit():
            vals = {}
            for key, cell in zip(keys, cells[2:6]):
                nums = [float(v) for v in re.findall(r"[\d.]+", cell)]
                vals[key] = tuple(nums[:3])
            out[int(cells[0])] = vals
    return out


def _fmt(v: float, nd: int = 2) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def _load() -> str:
    return "load average " + " / ".join(f"{v:.2f}" for v in os.getloadavg()) + " (1 / 5 / 15 min)"


def in_process(data_dir: Path, runs: int, jobs: int = JOBS, walks: Sequence[int] | None = None,
               names: Sequence[str] = tuple(CONFIGS)) -> dict[str, dict[int, tuple[float, float]]]:
    """Each configuration from scratch (:func:`from_scratch`: front end + graph) in this process with
    1 and ``jobs`` processes, alternating, ``runs`` times each; per configuration and jobs the least
    wall time and the least CPU time (all processes) of the runs. Checks that both give the same poses
    and step lengths. ``walks``: only these (default: all)."""
    out: dict[str, dict[int, tuple[float, float]]] = {}
    for name in names:
        params = CONFIGS[name]
        best: dict[int, tuple[float, float]] = {1: (np.inf, np.inf), jobs: (np.inf, np.inf)}
        poses = {}
        for _ in range(runs):
            for j in (1, jobs):
                sc = from_scratch(data_dir, params, walks, jobs=j)
                best[j] = (min(best[j][0], sc.wall_s), min(best[j][1], sc.cpu_s))
                poses[j] = sc.graph.poses.view("x").tobytes() + sc.graph.step_len.tobytes()
        if poses[1] != poses[jobs]:
            raise RuntimeError(f"{name}: {jobs} processes gave other poses than one")
        out[name] = best
    return out


def fresh_processes(data_dir: Path, runs: int, names: Sequence[str] = tuple(CONFIGS),
                    jobs: int = JOBS) -> dict[str, dict]:
    """Each configuration of ``names`` from scratch in fresh processes that import only what the work
    needs (:mod:`indoor_loc.bench.backend_run`), with 1 and ``jobs`` processes sharing the front end,
    alternating, ``runs`` times each, the package's modules compiled once beforehand (as an installed
    package's are); prints a table (least times of the runs, largest peak memory) and returns the runs."""
    print(f"\nEach configuration from scratch in a fresh process (`python -m indoor_loc.bench.backend_run`, "
          f"{runs} run{'s' if runs > 1 else ''} each with 1 and {jobs} processes, alternating; least of the runs), "
          "importing only the PUTMC reader, the stepometer and the graph (numpy, scipy.signal/.sparse/.optimize, "
          "PyYAML; no ROS, no plotting), with byte code compiled by a first, untimed run (a `PYTHONPYCACHEPREFIX` "
          "in a temporary directory, as an installed package has its .pyc): the work (front end + graph), the "
          "whole process (interpreter start-up, imports and exit included; wall timed around the process) and "
          f"its peak resident memory. CPU: all the processes'. The reference's figures are wall times of one "
          f"single-threaded C++ process each. {_load()} before.\n")
    print("| configuration | processes | work s wall / CPU | whole process s wall / CPU (of which start-up + "
          "imports, CPU) | peak RSS MB (after imports; largest worker) | reference C++ s wall, MB |")
    print("|---|---|---|---|---|---|")
    out: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="indoor_loc_pyc_") as pyc:
        scratch(data_dir, names[0], 1, walks=[1], pycache=pyc)          # compiles; not timed
        for name in names:
            rs: dict[int, list[dict]] = {1: [], jobs: []}
            for _ in range(runs):
                for j in (1, jobs):
                    rs[j] += scratch(data_dir, name, 1, jobs=j, pycache=pyc)
            ref = REF_TIME_S["joint" if "joint" in name else "separate"] if name in REFERENCE else None
            for j in (1, jobs):
                r = rs[j]
                work_w, work_c = min(x["wall_work_s"] for x in r), min(x["cpu_work_s"] for x in r)
                proc_w, proc_c = min(x["wall_process_s"] for x in r), min(x["cpu_process_s"] for x in r)
                imp = min(x["cpu_process_s"] - x["cpu_work_s"] for x in r)
                reftxt = f"{ref[0]}–{ref[1]} s, {REF_MEMORY_MB[0]}–{REF_MEMORY_MB[1]} MB" if ref else "–"
                workers = f"; {max(x['rss_workers_peak_mb'] for x in r):.0f}" if j > 1 else ""
                procs = "1" if j == 1 else f"1 + {j} workers"
                print(f"| {name} | {procs} | **{work_w:.2f}** / {work_c:.2f} | **{proc_w:.2f}** / {proc_c:.2f} ({imp:.2f}) "
                      f"| {max(x['rss_peak_mb'] for x in r):.0f} ({max(x['rss_imports_mb'] for x in r):.0f}{workers}) "
                      f"| {reftxt if j == 1 else ''} |")
                out[name if j == 1 else f"{name} (jobs {j})"] = {"runs": r}
    print(f"\n{_load()} after.")
    return out


def run(args: argparse.Namespace) -> int:
    data_dir = Path(args.data)
    quick = bool(getattr(args, "quick", False))
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0      # interpreter + imports
    print(f"# indoor-loc bench backend — PUTMC, 24 walks{' (quick)' if quick else ''}\n")
    first = load(data_dir)           # the first pass of this process: its times are the ones used below
    cold = replace(first, events={}, truth={}, segments={})      # (timing only; one dataset in memory)
    del first
    data = load(data_dir)            # the same work again (numpy's FFT plans warm): the data used below
    n_hops = sum(len(e.steps) for e in data.events.values())
    n_scans = sum(len(e.scans) for e in data.events.values())
    print(f"front end (load + stepometer + heading, all walks): {cold.load_s:.2f} s wall, {cold.load_cpu_s:.2f} s CPU; "
          f"{n_hops} hops, {n_scans} scans\n")

    results: dict[str, dict] = {}
    for name, params in CONFIGS.items():
        best, best_cpu = np.inf, np.inf
        for _ in range(1 if quick else 3):               # best of 3: the machine is shared and noisy
            g, wall, cpu = run_graph_timed(data, params)
            best, best_cpu = min(best, wall), min(best_cpu, cpu)
        errs = errors(data, g)
        results[name] = {"graph": g, "wall_s": best, "cpu_s": best_cpu, "errs": errs,
                         "pooled": summary(list(errs.values()))}

    print("## Table 2 side by side (pooled over 24 walks; paper convention in squared units, as published)\n")
    print("| configuration | poses | paper RMSE / mean: ours | reference | true RMSE / mean (m): ours | reference "
          "| scan-time mean / p95 (m): ours | reference |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        p = r["pooled"]
        ref = REFERENCE.get(name)
        refs = (f"{ref[0]:.2f} / {ref[1]:.2f}", f"{ref[2]:.3f} / {ref[3]:.3f}", f"{ref[4]:.2f} / {ref[5]:.2f}") \
            if ref else ("–", "–", "–")
        print(f"| {name} | {p[6]} | **{p[0]:.2f} / {p[1]:.2f}** | {refs[0]} | **{p[2]:.3f} / {p[3]:.3f}** | {refs[1]} "
              f"| **{p[4]:.2f} / {p[5]:.2f}** | {refs[2]} |")
    print("\nReference: the authors' C++ on the same walks, 1314 poses; WKNN alone scores 2.86 / 7.59 m "
          "at the scan times, the RTS-smoothed KF (pdr_kf/path) 2.19 / 4.80 m.\n")

    print("## Tuning (odd walks, chose the default's parameters) vs held out (even walks)\n")
    print("| configuration | walks | scan-time mean / p95 (m) | true RMSE / mean (m) |")
    print("|---|---|---|---|")
    for name in ("joint, step-length est.", DEFAULT):
        for label, walks in (("odd (tuning)", [n for n in data.walks if n in TUNING_WALKS]),
                             ("even (held out)", [n for n in data.walks if n not in TUNING_WALKS])):
            p = summary([results[name]["errs"][n] for n in walks])
            print(f"| {name} | {label} | {p[4]:.2f} / {p[5]:.2f} | {p[2]:.3f} / {p[3]:.3f} |")
    print()

    ref_seq = reference_per_sequence(data_dir)
    print("## Per sequence: paper RMSE / mean, true mean distance m — ours, then the reference\n")
    heads = list(REF_KEYS)
    short = {"separate, no step-length est.": "sep", "separate, step-length est.": "sep+SLE",
             "joint, no step-length est.": "joint", "joint, step-length est.": "joint+SLE"}
    print("| seq | " + " | ".join(f"{short[h]} ours | {short[h]} ref" for h in heads) + " |")
    print("|---|" + "---|" * (2 * len(heads)))
    for n in data.walks:
        cells = []
        for name in heads:
            d = results[name]["errs"][n][0]
            ps = paper_score(d)
            k = d[d * d < 100]
            ref = ref_seq.get(n, {}).get(REF_KEYS[name])
            rtxt = f"{ref[0]:.2f} / {ref[1]:.2f}, {ref[2]:.2f}" if ref else "–"
            cells.append(f"{_fmt(ps.rmse)} / {_fmt(ps.mean)}, {_fmt(float(np.mean(k)) if len(k) else np.nan)} | {rtxt}")
        print(f"| {n} | " + " | ".join(cells) + " |")

    print("\n## Estimated step length per sequence (m; paper: 0.53–0.78, the taller walker's walks 6–10 longer)\n")
    print("| seq | separate + SLE | joint + SLE | default |")
    print("|---|---|---|---|")
    gs = [results[k]["graph"] for k in ("separate, step-length est.", "joint, step-length est.",
                                          DEFAULT)]
    for n in data.walks:
        name = data.events[n].name
        print(f"| {n}{' (JW)' if 6 <= n <= 10 else ''} | " + " | ".join(
            f"{g.step_len[g.users[name].index]:.3f}" for g in gs) + " |")
    sl = gs[1].step_len
    jw = [gs[1].step_len[gs[1].users[data.events[n].name].index] for n in data.walks if 6 <= n <= 10]
    other = [gs[1].step_len[gs[1].users[data.events[n].name].index] for n in data.walks if not 6 <= n <= 10]
    print(f"\njoint + SLE: range {sl.min():.3f}–{sl.max():.3f} m; walks 6–10 mean {np.mean(jw):.3f} m, "
          f"others {np.mean(other):.3f} m")

    # reduced map
    draws = 5 if quick else 50
    print(f"\n## Reduced map: survey kept at 90…50 % ({draws} seeded draws each), step-length est.; "
          "paper RMSE increase over the full map (paper: 50 % -> +3.34 separate, +2.17 joint)\n")
    print("| kept | separate: paper RMSE (mean of draws) | increase | joint: paper RMSE | increase | "
          "separate true mean m | joint true mean m |")
    print("|---|---|---|---|---|---|---|")
    base = {k: results[k]["pooled"] for k in ("separate, step-length est.", "joint, step-length est.")}
    rng = np.random.default_rng(20190817)
    reduced = {}
    for frac in (0.9, 0.8, 0.7, 0.6, 0.5):
        vals = {k: [] for k in base}
        for _ in range(draws):
            m = data.survey.n_scans
            keep = np.sort(rng.choice(m, int(round(frac * m)), replace=False))
            sub = RadioMap(positions=data.survey.positions[keep], bssids=list(data.survey.bssids),
                           rssi_dbm=data.survey.rssi_dbm[keep], freq_mhz=data.survey.freq_mhz,
                           ssids=list(data.survey.ssids), scan_ids=np.asarray(data.survey.scan_ids)[keep],
                           stamps_ns=np.asarray(data.survey.stamps_ns)[keep],
                           source=[data.survey.source[i] for i in keep])
            for k in base:
                g, _ = run_graph(data, CONFIGS[k], survey=sub)
                vals[k].append(summary(list(errors(data, g).values())))
        sep = np.mean([v[0] for v in vals["separate, step-length est."]])
        jnt = np.mean([v[0] for v in vals["joint, step-length est."]])
        sep_t = np.mean([v[3] for v in vals["separate, step-length est."]])
        jnt_t = np.mean([v[3] for v in vals["joint, step-length est."]])
        reduced[frac] = (sep, jnt, sep_t, jnt_t)
        print(f"| {int(frac * 100)} % | {sep:.2f} | +{sep - base['separate, step-length est.'][0]:.2f} | {jnt:.2f} | "
              f"+{jnt - base['joint, step-length est.'][0]:.2f} | {sep_t:.3f} | {jnt_t:.3f} |")

    # time and memory
    print("\n## Time (all 24 walks: graph building incl. WKNN + 15 iterations; best of runs) and memory\n")
    print("Wall time, then CPU time of this process (on a shared machine the wall time includes waiting "
          "for a core; the CPU time does not).\n")
    print("Front end, all 24 walks (first pass in this process: used below; second pass: the same work "
          "with numpy's FFT plans and the files in the page cache):\n")
    print("| part | first pass s wall / CPU | second pass s wall / CPU |")
    print("|---|---|---|")
    for part in (READING, STEPS):
        print(f"| {part} | {cold.parts[part][0]:.2f} / {cold.parts[part][1]:.2f} | "
              f"{data.parts[part][0]:.2f} / {data.parts[part][1]:.2f} |")
    print(f"| **front end** | {cold.load_s:.2f} / {cold.load_cpu_s:.2f} | {data.load_s:.2f} / {data.load_cpu_s:.2f} |\n")
    runs = 1 if quick else 3
    print(f"Per configuration from scratch (front end + graph, as the reference times each configuration), in this "
          f"process: the sum of the first pass's front end and the graph's best run, then `from_scratch` run with "
          f"1 and with {JOBS} processes (the walks' front ends in {JOBS} forked workers while this process puts "
          f"each walk into the graph as it arrives; the same poses), alternating, least of {runs} run"
          f"{'s' if runs > 1 else ''}, CPU of all the processes; {_load()} before:\n")
    scratch_rows = in_process(data_dir, runs)
    print(f"| configuration | graph s wall / CPU | front end + graph s wall / CPU | from scratch, 1 process: "
          f"s wall / CPU | from scratch, 1 + {JOBS} workers: s wall / CPU (all processes) | reference C++ s wall "
          "(loading, stepometer, WKNN, 15 LM its; 1 thread) |")
    print("|---|---|---|---|---|---|")
    for name, r in results.items():
        ref = REF_TIME_S["joint" if "joint" in name else "separate"]
        one, par = scratch_rows[name][1], scratch_rows[name][JOBS]
        print(f"| {name} | {r['wall_s']:.2f} / {r['cpu_s']:.2f} | {r['wall_s'] + cold.load_s:.2f} / "
              f"{r['cpu_s'] + cold.load_cpu_s:.2f} | {one[0]:.2f} / **{one[1]:.2f}** | **{par[0]:.2f}** / {par[1]:.2f} "
              f"| {ref[0]}–{ref[1]} |")
    live = replace(CONFIGS[DEFAULT], window_poses=30)
    g_live, wall_live, cpu_live = run_graph_timed(data, live)
    p_live = summary(list(errors(data, g_live).values()))
    print(f"| default, live mode (window of 30 poses optimised at every scan, then the final optimisation) "
          f"| {wall_live:.2f} / {cpu_live:.2f} | {wall_live + cold.load_s:.2f} / {cpu_live + cold.load_cpu_s:.2f} "
          "| – | – | – |")
    print(f"\n{_load()} after.")
    paper = [r for name, r in results.items() if name in REFERENCE]
    shared_wall = cold.load_s + sum(r["wall_s"] for r in paper)
    shared_cpu = cold.load_cpu_s + sum(r["cpu_s"] for r in paper)
    ref_sum = tuple(sum(REF_TIME_S["joint" if "joint" in name else "separate"][i] for name in REFERENCE)
                    for i in (0, 1))
    print(f"\nShared front end: the paper's {len(paper)} configurations in one run, the front end computed once "
          f"(the reference reloads it for each): {shared_wall:.2f} s wall / **{shared_cpu:.2f} s CPU** in all, "
          f"{shared_wall / len(paper):.2f} / **{shared_cpu / len(paper):.2f}** per configuration; the reference's "
          f"four runs {ref_sum[0]:.1f}–{ref_sum[1]:.1f} s wall in all.")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0    # before tracemalloc's own overhead
    tracemalloc.start()
    run_graph(data, CONFIGS["joint, step-length est."])
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    print(f"\nlive mode accuracy: paper {p_live[0]:.2f} / {p_live[1]:.2f}, true {p_live[2]:.3f} / {p_live[3]:.3f}, "
          f"scan {p_live[4]:.2f} / {p_live[5]:.2f}")
    print(f"memory: peak Python heap of one joint run {peak / 2**20:.1f} MB (tracemalloc); peak RSS of this process "
          f"{rss:.0f} MB, of which {rss0:.0f} MB before any data was read (interpreter, numpy, scipy, the package); "
          f"reference C++ {REF_MEMORY_MB[0]}–{REF_MEMORY_MB[1]} MB")
    fresh = fresh_processes(data_dir, 1, QUICK_FRESH) if quick else fresh_processes(data_dir, 3)
    if getattr(args, "live", False):
        from indoor_loc.bench import backend_live
        backend_live.run(data, rates=(10.0,) if quick else (1.0, 10.0))
    if getattr(args, "json", None):
        out = {name: {"pooled": r["pooled"][:6], "wall_s": r["wall_s"], "cpu_s": r["cpu_s"]}
               for name, r in results.items()}
        out["reduced_map"] = {str(k): v for k, v in reduced.items()}
        out["front_end_s"] = cold.load_s
        out["front_end_cpu_s"] = cold.load_cpu_s
        out["front_end_parts"] = {"first pass": cold.parts, "second pass": data.parts}
        out["shared_front_end"] = {"wall_s": shared_wall, "cpu_s": shared_cpu, "configurations": len(paper)}
        out["rss_mb"] = {"peak": rss, "before_data": rss0}
        out["fresh_process"] = fresh
        out["from_scratch_in_process"] = {name: {str(j): v for j, v in r.items()} for name, r in scratch_rows.items()}
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


def time_only(data_dir: Path, runs: int, names: Sequence[str] = tuple(CONFIGS), jobs: int = JOBS) -> dict:
    """Only the bench's timing of each configuration from scratch, with 1 and ``jobs`` processes,
    alternating, least of ``runs``: in this process (:func:`in_process`) and in fresh processes
    (:func:`fresh_processes`). Prints both tables; returns their figures."""
    print(f"# indoor-loc bench backend, time only — PUTMC, 24 walks, {runs} runs each\n")
    print(f"In this process (after the imports; one untimed run first), {_load()} before:\n")
    from_scratch(data_dir, CONFIGS[names[0]], jobs=jobs)           # files in the page cache, workers forked once
    rows = in_process(data_dir, runs, jobs, names=names)
    print(f"| configuration | 1 process: s wall / CPU | 1 + {jobs} workers: s wall / CPU (all processes) "
          "| reference C++ s wall (1 thread) |")
    print("|---|---|---|---|")
    for name in names:
        one, par = rows[name][1], rows[name][jobs]
        ref = REF_TIME_S["joint" if "joint" in name else "separate"] if name in REFERENCE else None
        print(f"| {name} | {one[0]:.2f} / {one[1]:.2f} | **{par[0]:.2f}** / {par[1]:.2f} | "
              f"{f'{ref[0]}–{ref[1]}' if ref else '–'} |")
    print(f"\n{_load()} after.")
    fresh = fresh_processes(data_dir, runs, names, jobs)
    return {"in_process": {name: {str(j): v for j, v in r.items()} for name, r in rows.items()}, "fresh_process": fresh}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m indoor_loc.bench.backend",
                                 description="Only the timing tables of `indoor-loc bench backend`: each configuration "
                                             "from scratch with 1 and N processes, in this process and in fresh ones.")
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets"), help="datasets directory (holding putmc/)")
    ap.add_argument("--runs", type=int, default=5, help="runs of each configuration and process count (least taken)")
    ap.add_argument("--configs", default="", help="semicolon-separated configurations (default: all)")
    ap.add_argument("--json", type=Path, help="also write the figures as JSON here")
    args = ap.parse_args(argv)
    names = [c.strip() for c in args.configs.split(";") if c.strip()] or list(CONFIGS)
    unknown = [c for c in names if c not in CONFIGS]
    if unknown or args.runs < 1:
        ap.error(f"unknown configuration(s) {unknown}; one of {list(CONFIGS)}" if unknown else "--runs must be >= 1")
    out = time_only(args.data, args.runs, names)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
