"""``indoor-loc bench imu``: IMU front end on real data, side by side with peers in one run.

Sections (one table each):
1. Oxford step counter validation walks (CC BY 4.0): step-count error per trace and overall for the
   FFT stepometer online (sample by sample, causal) and in batch, the stepometer with the paper's
   1.28 s window and a single harmonic (ablation), the same input at half rate (every second
   sample, ~50 Hz), the plain peak-detection baseline
   (:mod:`indoor_loc.bench.steps_baseline`) and the phone app's own ``algo_steps``.
2. PUTMC (Nowicki & Skrzypczyński 2019, GPLv3): distance walked with the default 0.65 m step
   vs the ground-truth route length (sum of the GT graph's segments) per walk.
3. BROAD orientation and AEKF/VQF throughput, from :mod:`indoor_loc.bench.broad` when present.
4. Stepometer throughput (samples/s and × real time).
"""
from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any

import numpy as np

from indoor_loc.bench import broad
from indoor_loc.bench.steps_baseline import peak_steps
from indoor_loc.imu.stepometer import Stepometer, stepometer_batch, total_steps
from indoor_loc.imu.stepometer_types import StepometerParams

PAPER_WINDOW = StepometerParams(window_s=1.28, hop_s=1.28, harmonics=1, min_autocorr=-1.0,
                                min_std_m_s2=0.0, search_margin=1.0)
STEP_LENGTH_M = 0.65


# ----------------------------------------------------------------------------------------------
# dataset readers
# ----------------------------------------------------------------------------------------------
def load_oxford(path: Path) -> dict[str, np.ndarray]:
    """One Oxford CSV: stamps_ns (N,), acc (N, 3) m/s², algo/gt cumulative steps (N,). All-zero
    rows (the first row of some files) are dropped."""
    d = np.loadtxt(path, delimiter=",", dtype=float)
    t = np.loadtxt(path, delimiter=",", usecols=0, dtype=np.int64)
    keep = np.any(d[:, 1:4] != 0, axis=1)
    return {"stamps_ns": t[keep], "acc": d[keep, 1:4], "algo": d[keep, 4], "gt": d[keep, 5]}


def oxford_traces(data_dir: Path) -> list[Path]:
    return sorted((Path(data_dir) / "oxford_steps" / "validation").glob("*.csv"))


def putmc_walks(data_dir: Path) -> list[tuple[int, Path]]:
    root = Path(data_dir) / "putmc" / "PUTMC_Floor3_Xperia_trajs"
    out = []
    for p in root.glob("xperia_traj*"):
        m = re.match(r"xperia_traj(\d+)", p.name)
        if m and (p / "acc.map").is_file():
            out.append((int(m.group(1)), p))
    return sorted(out)


def load_putmc_acc(walk_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """``acc.map``: stamps_ns (N,), acc (N, 3) m/s² incl. gravity."""
    t = np.loadtxt(walk_dir / "acc.map", usecols=0, dtype=np.int64, ndmin=1)
    a = np.loadtxt(walk_dir / "acc.map", usecols=(1, 2, 3), dtype=float, ndmin=2)
    return t, a


def putmc_route_length(data_dir: Path, walk: int) -> float:
    """Length (m) of the ground-truth route graph ``GT/N/nodes.map`` (segments i<j, self-loops dropped)."""
    tokens = (Path(data_dir) / "putmc" / "GT" / str(walk) / "nodes.map").read_text().split()
    k = int(tokens[0])
    pos, nbrs, i = [], [], 1
    for _ in range(k):
        pos.append((float(tokens[i]), float(tokens[i + 1])))
        c = int(tokens[i + 2])
        nbrs.append([int(v) for v in tokens[i + 3: i + 3 + c]])
        i += 3 + c
    p = np.array(pos)
    return float(sum(np.linalg.norm(p[a] - p[b]) for a in range(k) for b in nbrs[a] if b > a))


# ----------------------------------------------------------------------------------------------
# sections
# ----------------------------------------------------------------------------------------------
def oxford_rows(data_dir: Path, quick: bool = False) -> tuple[list[dict], dict]:
    """Per-trace step counts and errors (%), plus timing of the online stepometer."""
    rows: list[dict] = []
    timing = {"online_s": 0.0, "batch_s": 0.0, "samples": 0, "rate_hz": []}
    for path in oxford_traces(data_dir):
        tr = load_oxford(path)
        t, a = tr["stamps_ns"], tr["acc"]
        gt = float(tr["gt"][-1] - tr["gt"][0])
        t0 = time.perf_counter()
        s = Stepometer()
        online = 0.0
        for i in range(len(t)):
            for h in s.update(int(t[i]), a[i]):
                online += h.steps
        online += total_steps(s.finish())
        t1 = time.perf_counter()
        batch = total_steps(stepometer_batch(t, a))
        t2 = time.perf_counter()
        timing["online_s"] += t1 - t0
        timing["batch_s"] += t2 - t1
        timing["samples"] += len(t)
        timing["rate_hz"].append(s.rate_hz)
        half_rate = total_steps(stepometer_batch(t[::2], a[::2]))
        paper = total_steps(stepometer_batch(t, a, PAPER_WINDOW))
        peaks = float(len(peak_steps(t, a)))
        algo = float(tr["algo"][-1] - tr["algo"][0])
        name = "_".join(path.stem.split("_")[:2])
        row = {"trace": name, "gt_steps": gt}
        for key, val in (("online", online), ("batch", batch), ("half_rate", half_rate), ("paper_1h", paper),
                         ("peaks", peaks),
                         ("algo_steps", algo)):
            row[key] = val
            row[key + "_err_pct"] = 100.0 * (val - gt) / gt
        rows.append(row)
    return rows, timing


def putmc_rows(data_dir: Path, quick: bool = False) -> list[dict]:
    rows = []
    walks = putmc_walks(data_dir)
    if quick:
        walks = walks[:6]
    for walk, path in walks:
        t, a = load_putmc_acc(path)
        hops = stepometer_batch(t, a)
        steps = total_steps(hops)
        walking_s = sum((h.t_end_ns - h.t_start_ns) * 1e-9 for h in hops if h.walking)
        gt_len = putmc_route_length(data_dir, walk)
        dist = STEP_LENGTH_M * steps
        peaks = float(len(peak_steps(t, a)))
        rows.append({"walk": walk, "walker": "JW" if path.name.endswith("_JW") else "-", "steps": steps,
                     "peak_steps": peaks,
                     "walking_s": walking_s, "distance_m": dist, "gt_route_m": gt_len,
                     "err_pct": 100.0 * (dist - gt_len) / gt_len,
                     "implied_step_m": gt_len / steps if steps > 0 else float("nan")})
    return rows


# ----------------------------------------------------------------------------------------------
# printing
# ----------------------------------------------------------------------------------------------
def _table(title: str, header: list[str], rows: list[list[Any]]) -> str:
    cells = [[str(c) for c in header]] + [[c if isinstance(c, str) else _fmt(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    line = "  ".join("-" * w for w in widths)
    out = [title, "  ".join(h.rjust(w) for h, w in zip(cells[0], widths)), line]
    out += ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells[1:]]
    return "\n".join(out) + "\n"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.2f}" if abs(v) < 1e5 else f"{v:.3g}"
    return str(v)


def _oxford_table(rows: list[dict]) -> str:
    keys = ["online", "batch", "half_rate", "paper_1h", "peaks", "algo_steps"]
    body = [[r["trace"], r["gt_steps"]] + [f"{r[k]:.1f} ({r[k + '_err_pct']:+.2f}%)" for k in keys] for r in rows]
    for label, fn in (("median |err| %", np.median), ("max |err| %", np.max), ("mean |err| %", np.mean)):
        body.append([label, ""] + [f"{fn(np.abs([r[k + '_err_pct'] for r in rows])):.2f}" for k in keys])
    return _table("Oxford step counter validation: steps (error vs ground truth)",
                  ["trace", "gt", "ours online", "ours batch", "ours ~50 Hz", "fft 1.28s 1-harm", "peak baseline",
                   "algo_steps"], body)


def _putmc_table(rows: list[dict]) -> str:
    body = [[r["walk"], r["walker"], r["steps"], r["peak_steps"], r["walking_s"], r["distance_m"],
             r["gt_route_m"], f"{r['err_pct']:+.1f}", r["implied_step_m"]] for r in rows]
    e = np.array([r["err_pct"] for r in rows])
    body.append(["all", "", sum(r["steps"] for r in rows), sum(r["peak_steps"] for r in rows),
                 sum(r["walking_s"] for r in rows),
                 sum(r["distance_m"] for r in rows), sum(r["gt_route_m"] for r in rows),
                 f"med|e| {np.median(np.abs(e)):.1f}", "" if not rows else
                 sum(r["gt_route_m"] for r in rows) / max(1e-9, sum(r["steps"] for r in rows))])
    return _table(f"PUTMC: distance walked with a {STEP_LENGTH_M} m step vs ground-truth route length",
                  ["walk", "walker", "steps", "peak baseline steps", "walking s", "distance m", "GT route m",
                   "err %", "implied step m"], body)


def _dict_table(title: str, rows: list[dict]) -> str:
    if not rows:
        return f"{title}: no rows\n"
    header = list(rows[0].keys())
    for r in rows[1:]:
        header += [k for k in r if k not in header]
    return _table(title, header, [[r.get(k, "") for k in header] for r in rows])


def run(args) -> int:
    data = Path(args.data)
    quick = bool(getattr(args, "quick", False))
    report: dict[str, Any] = {}
    if oxford_traces(data):
        rows, timing = oxford_rows(data, quick)
        report["oxford"] = rows
        print(_oxford_table(rows))
        rate = float(np.median(timing["rate_hz"]))
        thr = [{"estimator": "stepometer online (per sample)", "samples_per_s": timing["samples"] / timing["online_s"],
                "x_realtime_at_input_rate": timing["samples"] / timing["online_s"] / rate,
                "x_realtime_at_200Hz": timing["samples"] / timing["online_s"] / 200.0},
               {"estimator": "stepometer batch", "samples_per_s": timing["samples"] / timing["batch_s"],
                "x_realtime_at_input_rate": timing["samples"] / timing["batch_s"] / rate,
                "x_realtime_at_200Hz": timing["samples"] / timing["batch_s"] / 200.0}]
        report["stepometer_throughput"] = thr
    else:
        print(f"Oxford step data not found under {data}/oxford_steps/validation: skipped\n")
        thr = []
    if putmc_walks(data):
        prow = putmc_rows(data, quick)
        report["putmc"] = prow
        print(_putmc_table(prow))
    else:
        print(f"PUTMC not found under {data}/putmc: skipped\n")
    if not broad.broad_files(data):
        print(f"BROAD trials not found under {data}/broad: skipped\n")
    else:
        brows = broad.broad_rows(data, quick)
        report["broad"] = brows
        print(_dict_table("BROAD: heading / inclination RMSE per trial", brows))
        trows = broad.throughput_rows(data, quick)
        report["orientation_throughput"] = trows
        print(_dict_table("Orientation filters: throughput", trows))
    if thr:
        print(_dict_table(f"Stepometer throughput (Oxford, {timing['samples']} samples at ~{rate:.0f} Hz)", thr))
    if getattr(args, "json", None):
        Path(args.json).write_text(json.dumps(report, indent=1, default=float))
    return 0
