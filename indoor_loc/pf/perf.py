"""Cost per particle-filter step at several particle counts: ``python -m indoor_loc.pf.perf [GRAPH]``.

One step is what the ``tll_pf`` node does per PDR hop with a WiFi fix: the PDR prediction (walk
along the graph with guided link choices), the Gaussian fix update (with sensor resetting) and a
systematic resampling (forced every step, as the worst case). Without ``GRAPH`` a synthetic
corridor grid is used. CPU time of this process is reported next to the wall time (on a shared
machine the wall time also counts other processes); real-time factors are for one PDR hop per
``--hop-s`` seconds.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from indoor_loc.graph.model import BuildingGraph, build_graph
from indoor_loc.graph.tll import TransitionParams, transition_table
from indoor_loc.pf.filter import GraphParticleFilter, PfParams, systematic_resample


def grid_graph(side: int = 12, cell_m: float = 8.0) -> BuildingGraph:
    """A ``side`` × ``side`` grid of corridors ``cell_m`` apart."""
    ii, jj = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    ids = (ii * side + jj).ravel()
    links = [(a, a + 1) for a in ids if a % side != side - 1] + [(a, a + side) for a in ids if a < side * (side - 1)]
    return build_graph(ids, np.column_stack([jj.ravel(), ii.ravel()]).astype(float) * cell_m, links)


def step_cost(graph: BuildingGraph, n: int, reps: int, seed: int = 0) -> dict[str, float]:
    """Mean CPU and wall seconds per step phase over ``reps`` steps with ``n`` particles."""
    rng = np.random.default_rng(seed)
    pf = GraphParticleFilter(graph, transition_table(graph, TransitionParams()), PfParams(n_particles=n))
    centre = graph.node_xyz[:, :2].mean(axis=0)
    pf.init_gaussian(centre, np.eye(2) * 400.0, rng)
    cpu = np.zeros(3)
    wall = np.zeros(3)
    for k in range(reps):
        c0, w0 = time.process_time(), time.perf_counter()
        pf.predict_pdr(0.6, 0.3 * k, rng)
        c1, w1 = time.process_time(), time.perf_counter()
        pf.update_position(centre + rng.normal(0, 3, 2), np.eye(2) * 9.0, rng)
        c2, w2 = time.process_time(), time.perf_counter()
        p = pf.p
        assert p is not None
        pf.p = p.take(systematic_resample(p.weights, rng))
        pf.p.log_w[:] = -np.log(n)
        c3, w3 = time.process_time(), time.perf_counter()
        cpu += (c1 - c0, c2 - c1, c3 - c2)
        wall += (w1 - w0, w2 - w1, w3 - w2)
    return {"predict_cpu": cpu[0] / reps, "update_cpu": cpu[1] / reps, "resample_cpu": cpu[2] / reps,
            "cpu": cpu.sum() / reps, "wall": wall.sum() / reps}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m indoor_loc.pf.perf", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("graph", nargs="?", type=Path, help="graph file (indoor_loc.graph v1); default a synthetic grid")
    ap.add_argument("--counts", default="400,4000,40000", help="particle counts (comma-separated)")
    ap.add_argument("--reps", type=int, default=0, help="steps per count (default: about 400 000 particle-steps, 5..2000)")
    ap.add_argument("--hop-s", type=float, default=0.32, help="PDR hop period for the real-time factor (s)")
    args = ap.parse_args(argv)
    if args.graph is not None:
        from indoor_loc.graph.io import load_graph
        graph = load_graph(args.graph)
    else:
        graph = grid_graph()
    print(f"graph: {graph.n_nodes} nodes, {graph.n_links} links; one PDR hop per {args.hop_s} s\n")
    print("| particles | predict | WiFi update | resample | step CPU | × real time (CPU) | step wall |")
    print("|---|---|---|---|---|---|---|")
    for n in (int(c) for c in args.counts.split(",")):
        r = step_cost(graph, n, reps=args.reps or min(2000, max(5, 400_000 // n)))
        print(f"| {n} | {1e3 * r['predict_cpu']:.2f} ms | {1e3 * r['update_cpu']:.2f} ms | "
              f"{1e3 * r['resample_cpu']:.2f} ms | {1e3 * r['cpu']:.2f} ms | {args.hop_s / r['cpu']:.0f}× | "
              f"{1e3 * r['wall']:.2f} ms |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
