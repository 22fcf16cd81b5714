"""``indoor-loc bench heading``: orientation on walking phones (TyRex) and on BROAD, side by side.

Every filter runs on the same samples in one run:

- ``aekf (stage)`` and ``vqf (stage)``: ``imu_node``'s stage (:class:`ImuStage`, the code the live node
  and ``indoor-loc run`` drive) with ``heading_source: aekf`` / ``vqf``, fed ``imu/data_raw`` and
  ``imu/mag`` messages in stamp order, the magnetometer at its own rate and stamps; scored on the
  ``imu/data`` it publishes.
- ``vqf (offline)``: ``vqf.VQF.updateBatch`` at the median sampling time with the magnetometer
  linearly interpolated onto the IMU stamps — VQF as one runs it offline.
- ``madgwick``: ``ahrs.filters.Madgwick`` (gain 0.1, as in the BROAD bench), same interpolated
  magnetometer; its NWU output turned into ENU.
- ``android``: Android's rotation vector from the file (TyRex only; true north).

TyRex (Michel et al., "On Attitude Estimation with Smartphones", PerCom 2017): the benchmark's
protocol (:mod:`indoor_loc.datasets.tyrex`). Development split, by person: parameters were decided on
Guillaume's and Jakob's trials (8, every motion); Thibaud's 4 trials are reported apart as held out.
BROAD (Laidig et al., Data 6(7), 2021): the six trials here, the benchmark's metric.
Throughput: samples/s of each filter over the whole run (stage rows include message conversion and
the stepometer, as live).
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from indoor_loc.bench import broad
from indoor_loc.datasets import tyrex

MADGWICK_BETA = broad.MADGWICK_BETA
TUNE_PERSONS = ("Guillaume", "Jakob")
FILTERS = ("aekf (stage)", "vqf (stage)", "vqf (offline)", "madgwick", "android")


# ------------------------------------------------------------------------------------------------
# runners: each returns (t_ns (K,), quat (K, 4) w x y z device→ENU)
# ------------------------------------------------------------------------------------------------
def run_stage(t_ns, gyr, acc, mag_t_ns, mag_ut, heading_source: str, **overrides) -> tuple[np.ndarray, np.ndarray]:
    """Drive :class:`ImuStage` with messages in stamp order (magnetometer after the IMU sample of the
    same stamp); returns the stamps and quaternions of the ``imu/data`` it publishes."""
    from msg_adapters.imu import imu_to_msg, mag_to_msg
    from indoor_loc.params import params_from_dict
    from indoor_loc.pipeline.imu_stage import ImuStage, ImuStageParams

    st = ImuStage(params_from_dict(ImuStageParams, {"heading_source": heading_source, **overrides}),
                  namespace="/bench")
    out_t: list[int] = []
    out_q: list[tuple] = []

    def collect(outs):
        for topic, msg in outs:
            if topic == "imu/data":
                o = msg.orientation
                out_t.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
                out_q.append((o.w, o.x, o.y, o.z))

    t_ns = np.asarray(t_ns, dtype=np.int64)
    mt = np.asarray(mag_t_ns, dtype=np.int64) if mag_t_ns is not None else np.zeros(0, np.int64)
    j = 0
    for i in range(len(t_ns)):
        ns = int(t_ns[i])
        while j < len(mt) and mt[j] < ns:          # stamp order (a tie: the IMU sample first)
            mns = int(mt[j])
            collect(st.process("imu/mag", mag_to_msg(mns, "imu_link", mag_ut[j] * 1e-6), mns))
            j += 1
        collect(st.process("imu/data_raw", imu_to_msg(ns, "imu_link", acc[i], gyr[i]), ns))
    while j < len(mt):
        mns = int(mt[j])
        collect(st.process("imu/mag", mag_to_msg(mns, "imu_link", mag_ut[j] * 1e-6), mns))
        j += 1
    collect(st.finish())
    rejected = sum(st.diag.rejected.values())
    if rejected:
        print(f"  note: stage {heading_source} rejected {rejected} messages: {dict(st.diag.rejected)}")
    return np.array(out_t, dtype=np.int64), np.array(out_q, dtype=float).reshape(-1, 4)


def _interp_mag(t_ns, mag_t_ns, mag) -> np.ndarray:
    return np.stack([np.interp(t_ns, mag_t_ns, mag[:, k]) for k in range(3)], axis=1)


def run_vqf_offline(t_ns, gyr, acc, mag_t_ns, mag) -> np.ndarray:
    from vqf import VQF

    ts = float(np.median(np.diff(t_ns))) * 1e-9
    m = _interp_mag(t_ns, mag_t_ns, mag)
    out = VQF(ts).updateBatch(np.ascontiguousarray(gyr, dtype=float), np.ascontiguousarray(acc, dtype=float),
                              np.ascontiguousarray(m))
    return np.asarray(out["quat9D"])


def run_madgwick(t_ns, gyr, acc, mag_t_ns, mag) -> np.ndarray:
    rate = 1e9 / float(np.median(np.diff(t_ns)))
    tr = {"gyr": np.asarray(gyr, float), "acc": np.asarray(acc, float), "mag": _interp_mag(t_ns, mag_t_ns, mag),
          "rate_hz": rate}
    return broad.run_madgwick(tr, True, MADGWICK_BETA)


# ------------------------------------------------------------------------------------------------
# data sets
# ------------------------------------------------------------------------------------------------
def _timed(fn: Callable[[], Any], n: int, rates: dict, name: str) -> Any:
    t0 = time.perf_counter()
    r = fn()
    el = time.perf_counter() - t0
    a = rates.setdefault(name, [0, 0.0])
    a[0] += n
    a[1] += el
    return r


def tyrex_rows(data_dir: Path, *, quick: bool = False, rates: dict | None = None,
               filters: tuple[str, ...] = FILTERS, stage_overrides: dict | None = None) -> list[dict]:
    """One row per (trial, filter): heading and inclination RMSE (°), samples. ``quick``: 3 trials."""
    rates = rates if rates is not None else {}
    ov = stage_overrides or {}
    rows = []
    dirs = tyrex.trial_dirs(data_dir)
    if quick:
        dirs = dirs[::4]
    for d in dirs:
        tr = tyrex.load_trial(d)
        n = len(tr.t_ns)
        args = (tr.t_ns, tr.gyr, tr.acc, tr.mag_t_ns, tr.mag)
        ests: dict[str, tuple[np.ndarray, np.ndarray, bool]] = {}
        if "aekf (stage)" in filters:
            t, q = _timed(lambda a=args: run_stage(*a, "aekf", **ov), n, rates, "aekf (stage)")
            ests["aekf (stage)"] = (t, q, False)
        if "vqf (stage)" in filters:
            t, q = _timed(lambda a=args: run_stage(*a, "vqf", **ov), n, rates, "vqf (stage)")
            ests["vqf (stage)"] = (t, q, False)
        if "vqf (offline)" in filters:
            ests["vqf (offline)"] = (tr.t_ns, _timed(lambda a=args: run_vqf_offline(*a), n, rates, "vqf (offline)"), False)
        if "madgwick" in filters and not quick:
            ests["madgwick"] = (tr.t_ns, _timed(lambda a=args: run_madgwick(*a), n, rates, "madgwick"), False)
        if "android" in filters:
            ests["android"] = (tr.rv_t_ns, tr.rv_quat, True)
        for name, (t, q, true_north) in ests.items():
            h, i, k = tyrex.score(tr, t, q, true_north=true_north)
            rows.append({"set": "tyrex", "trial": tr.name, "person": tr.person, "disturbed": tr.disturbed,
                         "filter": name, "heading_rmse_deg": h, "inclination_rmse_deg": i, "samples": k})
    return rows


def broad_rows(data_dir: Path, *, quick: bool = False, rates: dict | None = None,
               filters: tuple[str, ...] = FILTERS, stage_overrides: dict | None = None) -> list[dict]:
    rates = rates if rates is not None else {}
    ov = stage_overrides or {}
    rows = []
    for path in broad.broad_files(data_dir):
        tr = broad.load_trial(path, broad.QUICK_SECONDS if quick else None)
        n = len(tr["t_ns"])
        t = tr["t_ns"]
        args = (t, tr["gyr"], tr["acc"], t, tr["mag"])
        ests: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for name, src in (("aekf (stage)", "aekf"), ("vqf (stage)", "vqf")):
            if name in filters:
                ests[name] = _timed(lambda a=args, s=src: run_stage(*a, s, **ov), n, rates, name)
        if "vqf (offline)" in filters:
            ests["vqf (offline)"] = (t, _timed(lambda a=args: run_vqf_offline(*a), n, rates, "vqf (offline)"))
        if "madgwick" in filters and not quick:
            ests["madgwick"] = (t, _timed(lambda a=args: run_madgwick(*a), n, rates, "madgwick"))
        for name, (te, q) in ests.items():
            # the stage publishes one imu/data per IMU sample once initialised: align by stamp
            full = np.full((n, 4), np.nan)
            idx = np.searchsorted(t, te)
            full[idx] = q
            h, i, k = broad.errors_deg(full, tr)
            rows.append({"set": "broad", "trial": tr["name"], "person": "", "disturbed": False, "filter": name,
                         "heading_rmse_deg": h, "inclination_rmse_deg": i, "samples": k})
    return rows


# ------------------------------------------------------------------------------------------------
# tables
# ------------------------------------------------------------------------------------------------
def _mean(rows, filt, key, pred=lambda r: True) -> float:
    v = [r[key] for r in rows if r["filter"] == filt and pred(r) and math.isfinite(r[key])]
    return float(np.mean(v)) if v else float("nan")


def summary(rows: list[dict], ref: str = "vqf (offline)") -> dict:
    """Means per filter over groups, and the issue's acceptance ratios against ``ref``."""
    out: dict[str, Any] = {}
    filters = list(dict.fromkeys(r["filter"] for r in rows))
    groups = {
        "tyrex all 12": lambda r: r["set"] == "tyrex",
        "tyrex tuned-on (Guillaume, Jakob)": lambda r: r["set"] == "tyrex" and r["person"] in TUNE_PERSONS,
        "tyrex held-out (Thibaud)": lambda r: r["set"] == "tyrex" and r["person"] not in TUNE_PERSONS,
        "tyrex undisturbed": lambda r: r["set"] == "tyrex" and not r["disturbed"],
        "tyrex disturbed": lambda r: r["set"] == "tyrex" and r["disturbed"],
        "broad": lambda r: r["set"] == "broad",
    }
    for g, pred in groups.items():
        if not any(pred(r) for r in rows):
            continue
        out[g] = {f: (_mean(rows, f, "heading_rmse_deg", pred), _mean(rows, f, "inclination_rmse_deg", pred))
                  for f in filters if any(pred(r) and r["filter"] == f for r in rows)}
    # per-trial ratios of each filter to the reference
    ratios: dict[str, dict] = {}
    for s in ("tyrex", "broad"):
        for f in filters:
            if f == ref:
                continue
            hr, ir = [], []
            for r in rows:
                if r["set"] != s or r["filter"] != f:
                    continue
                b = next((x for x in rows if x["set"] == s and x["trial"] == r["trial"] and x["filter"] == ref), None)
                if b is None:
                    continue
                hr.append(r["heading_rmse_deg"] / b["heading_rmse_deg"])
                ir.append(r["inclination_rmse_deg"] / b["inclination_rmse_deg"])
            if hr:
                ratios[f"{s}: {f} / {ref}"] = {"max_heading_ratio": float(np.max(hr)),
                                               "mean_heading_ratio": float(np.mean(hr)),
                                               "trials_better": int(np.sum(np.array(hr) <= 1.0)),
                                               "trials": len(hr)}
    out["ratios"] = ratios
    return out


def print_tables(rows: list[dict], rates: dict) -> None:
    filters = list(dict.fromkeys(r["filter"] for r in rows))
    for s, title in (("tyrex", "TyRex walking phones (tyrex_dev, 12 trials)"), ("broad", "BROAD (6 trials)")):
        sel = [r for r in rows if r["set"] == s]
        if not sel:
            continue
        cols = [f for f in filters if any(r["filter"] == f for r in sel)]
        print(f"\n{title}: heading / inclination RMSE [deg]")
        print(f"{'trial':38s}" + "".join(f"{c:>16s}" for c in cols))
        for t in dict.fromkeys(r["trial"] for r in sel):
            cells = []
            for c in cols:
                r = next((r for r in sel if r["trial"] == t and r["filter"] == c), None)
                cells.append(f"{r['heading_rmse_deg']:6.2f}/{r['inclination_rmse_deg']:<5.2f}" if r else "-")
            print(f"{t:38s}" + "".join(f"{x:>16s}" for x in cells))
    sm = summary(rows)
    print("\nMeans over trials: heading / inclination RMSE [deg]")
    for g, vals in sm.items():
        if g == "ratios":
            continue
        print(f"{g:38s}" + "".join(f"{f:>16s}" for f in vals))
        print(f"{'':38s}" + "".join(f"{h:7.2f}/{i:<6.2f}  " for h, i in vals.values()))
    print("\nPer-trial heading ratios to VQF offline")
    for k, v in sm["ratios"].items():
        print(f"{k:46s} max {v['max_heading_ratio']:5.2f}  mean {v['mean_heading_ratio']:5.2f}  "
              f"better on {v['trials_better']}/{v['trials']}")
    print("\nThroughput (wall clock, one core; stage rows include messages and the stepometer)")
    for name, (n, el) in rates.items():
        print(f"{name:20s} {n / el:12.0f} samples/s")


def run(args) -> int:
    data = Path(args.data)
    quick = bool(getattr(args, "quick", False))
    rates: dict = {}
    rows: list[dict] = []
    if tyrex.trial_dirs(data):
        rows += tyrex_rows(data, quick=quick, rates=rates)
    else:
        print(f"tyrex_dev not found under {data}: skipped")
    if broad.broad_files(data):
        rows += broad_rows(data, quick=quick, rates=rates)
    else:
        print(f"BROAD not found under {data}/broad: skipped")
    print_tables(rows, rates)
    if getattr(args, "json", None):
        Path(args.json).write_text(json.dumps({"rows": rows, "summary": summary(rows),
                                               "samples_per_s": {k: n / el for k, (n, el) in rates.items()}},
                                              indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets"))
    ap.add_argument("--quick", action="store_true", help="3 TyRex trials, first 60 s of BROAD, no Madgwick")
    ap.add_argument("--json", type=Path)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
