"""BROAD benchmark: heading/inclination RMSE of the AEKF against VQF and Madgwick, and throughput.

Data: ``datasets/broad/*.hdf5`` (Laidig et al., "BROAD — A Benchmark for Robust Inertial
Orientation Estimation", Data 6(7), 2021). ``opt_quat`` is sensor→reference (w x y z), the reference
frame aligned with the IMU's magnetic-north ENU frame for 9-D evaluation. Metric (the benchmark's):
``q_err = q_est ⊗ q_ref⁻¹``; heading error ``2·atan(|z/w|)``; inclination error
``2·acos(clip(sqrt(w² + z²), 0, 1))``; RMSE over samples with ``movement`` true and a finite
reference.

Frames, verified on the data (VQF 9-D gives ~1° heading RMSE with the formula as is):
- AEKF and VQF output sensor→ENU: used as they are.
- ``imufusion`` is run with its ENU convention (gyro in °/s, acc in g): used as is.
- ``ahrs.filters.Madgwick`` estimates sensor→NWU (Madgwick's x-north earth frame): its output is
  re-expressed in ENU by ``q_enu = q_z(+90°) ⊗ q_nwu`` — the same fixed frame change for every sample
  and trial, nothing fitted.
- 6-D (no magnetometer): the initial heading is each filter's own convention, so for every filter
  alike one constant heading offset per trial (the circular mean of its signed heading error over
  the evaluated samples) is removed before the RMSE; the 6-D heading RMSE thus measures drift.

Run: ``python -m indoor_loc.bench.broad --data ../shared/datasets [--quick]``.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from indoor_loc.imu.aekf import AekfParams, aekf_batch
from indoor_loc.imu.quaternion import heading_inclination_error, qconj, qmul, quat_from_rotvec

MADGWICK_BETA = 0.1          # ahrs Madgwick gain; beats ahrs' default 0.041 on all 4 undisturbed trials here
QUICK_SECONDS = 60.0         # --quick: first 60 s of each trial
_Z90 = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])


def broad_files(data_dir: Path) -> list[Path]:
    """The trial files under ``data_dir/broad`` (or ``data_dir`` itself), sorted by name."""
    data_dir = Path(data_dir)
    d = data_dir / "broad" if (data_dir / "broad").is_dir() else data_dir
    return sorted(d.glob("*.hdf5"))


def load_trial(path: Path, max_s: float | None = None) -> dict:
    """Arrays of one trial: ``t_ns`` (N,), ``gyr`` rad/s, ``acc`` m/s², ``mag`` µT (N, 3),
    ``quat_ref`` (N, 4) w x y z sensor→ENU (NaN gaps), ``movement`` (N,) bool, ``rate_hz``."""
    import h5py  # benchmark-only dependency

    with h5py.File(path, "r") as h:
        rate = float(h.attrs["sampling_rate"])
        n = len(h["imu_acc"])
        if max_s is not None:
            n = min(n, int(max_s * rate))
        out = {
            "name": path.stem,
            "rate_hz": rate,
            "gyr": np.ascontiguousarray(h["imu_gyr"][:n], dtype=float),
            "acc": np.ascontiguousarray(h["imu_acc"][:n], dtype=float),
            "mag": np.ascontiguousarray(h["imu_mag"][:n], dtype=float),
            "quat_ref": np.asarray(h["opt_quat"][:n], dtype=float),
            "movement": np.asarray(h["movement"][:n]).astype(bool),
        }
    out["t_ns"] = np.round(np.arange(n) * (1e9 / rate)).astype(np.int64)
    return out


# ------------------------------------------------------------------------------------------------
# filters: each returns (N, 4) w x y z sensor→ENU
# ------------------------------------------------------------------------------------------------
def run_aekf(tr: dict, nine_d: bool, params: AekfParams | None = None) -> np.ndarray:
    q, _ = aekf_batch(tr["t_ns"], tr["gyr"], tr["acc"], tr["mag"] if nine_d else None, params)
    return q


def run_vqf(tr: dict) -> tuple[np.ndarray, np.ndarray]:
    """VQF (C++ ``vqf.VQF``, default parameters): (quat9D, quat6D)."""
    from vqf import VQF

    out = VQF(1.0 / tr["rate_hz"]).updateBatch(tr["gyr"], tr["acc"], tr["mag"])
    return np.asarray(out["quat9D"]), np.asarray(out["quat6D"])


def run_fusion(tr: dict, nine_d: bool) -> np.ndarray:
    """x-io Fusion (``imufusion``; Madgwick's revised AHRS) with the settings its README uses:
    gain 0.5, gyroscope range 2000 °/s, acceleration/magnetic rejection 10°, rejection timeout
    5 s; ENU convention."""
    import imufusion

    rate = tr["rate_hz"]
    ahrs = imufusion.Ahrs()
    s = imufusion.AhrsSettings()
    s.convention = imufusion.CONVENTION_ENU
    s.gain = 0.5
    s.gyroscope_range = 2000.0
    s.acceleration_rejection = 10.0
    s.magnetic_rejection = 10.0
    s.rejection_timeout = int(5 * rate)
    s.sample_rate = rate
    ahrs.set_settings(s)
    ahrs.set_sample_period(1.0 / rate)
    gd = np.degrees(tr["gyr"])
    ag = tr["acc"] / 9.81
    mag = tr["mag"]
    n = len(gd)
    out = np.empty((n, 4))
    if nine_d:
        for i in range(n):
            ahrs.update(gd[i], ag[i], mag[i])
            out[i] = ahrs.get_quaternion()
    else:
        for i in range(n):
            ahrs.update_no_magnetometer(gd[i], ag[i])
            out[i] = ahrs.get_quaternion()
    return out


def run_madgwick(tr: dict, nine_d: bool, beta: float = MADGWICK_BETA) -> np.ndarray:
    """Madgwick's gradient-descent filter (``ahrs.filters.Madgwick``), gain ``beta``; its NWU
    output re-expressed in ENU."""
    from ahrs.filters import Madgwick

    kw = dict(gyr=tr["gyr"], acc=tr["acc"], frequency=tr["rate_hz"], gain=beta)
    if nine_d:
        kw["mag"] = tr["mag"]
    q = np.asarray(Madgwick(**kw).Q)
    return qmul(_Z90, q)


def errors_deg(q_est: np.ndarray, tr: dict, *, align_heading: bool = False) -> tuple[float, float, int]:
    """(heading RMSE °, inclination RMSE °, samples used) with the BROAD metric. With
    ``align_heading`` (6-D, where the initial heading is a convention) one constant heading offset,
    the circular mean of the signed heading error over the evaluated samples, is removed first."""
    q_est = np.asarray(q_est, dtype=float)
    he, ie = heading_inclination_error(q_est, tr["quat_ref"])
    ok = tr["movement"] & np.isfinite(he) & np.isfinite(ie)
    if not ok.any():
        return float("nan"), float("nan"), 0
    if align_heading:
        e = qmul(q_est[ok], qconj(tr["quat_ref"][ok]))
        signed = 2.0 * np.arctan2(e[:, 3], e[:, 0])
        off = math.atan2(float(np.mean(np.sin(signed))), float(np.mean(np.cos(signed))))
        q_est = qmul(quat_from_rotvec(np.array([0.0, 0.0, -off])), q_est)
        he, ie = heading_inclination_error(q_est, tr["quat_ref"])
    return (math.degrees(math.sqrt(float(np.mean(he[ok] ** 2)))),
            math.degrees(math.sqrt(float(np.mean(ie[ok] ** 2)))), int(ok.sum()))


def broad_rows(data_dir: Path, quick: bool = False, *, six_d: bool = True,
               with_ahrs: bool | None = None) -> list[dict]:
    """One row per (trial, filter, mode): ``trial``, ``filter`` (aekf | vqf | fusion | madgwick),
    ``mode`` (9d | 6d), ``heading_rmse_deg``, ``inclination_rmse_deg``, ``samples``; plus rows with
    ``trial = "mean"`` (mean of the per-trial RMSEs). ``quick`` uses the first 60 s of each trial and
    leaves out the slow pure-Python ``ahrs`` Madgwick (unless ``with_ahrs``). Empty if no data."""
    with_ahrs = (not quick) if with_ahrs is None else with_ahrs
    rows: list[dict] = []
    for path in broad_files(data_dir):
        tr = load_trial(path, QUICK_SECONDS if quick else None)
        ests: list[tuple[str, str, np.ndarray]] = []
        ests.append(("aekf", "9d", run_aekf(tr, True)))
        v9, v6 = run_vqf(tr)
        ests.append(("vqf", "9d", v9))
        ests.append(("fusion", "9d", run_fusion(tr, True)))
        if with_ahrs:
            ests.append(("madgwick", "9d", run_madgwick(tr, True)))
        if six_d:
            ests.append(("aekf", "6d", run_aekf(tr, False)))
            ests.append(("vqf", "6d", v6))
            ests.append(("fusion", "6d", run_fusion(tr, False)))
            if with_ahrs:
                ests.append(("madgwick", "6d", run_madgwick(tr, False)))
        for filt, mode, q in ests:
            h, i, n = errors_deg(q, tr, align_heading=(mode == "6d"))
            rows.append({"trial": tr["name"], "filter": filt, "mode": mode,
                         "heading_rmse_deg": h, "inclination_rmse_deg": i, "samples": n})
    keys = sorted({(r["filter"], r["mode"]) for r in rows})
    for filt, mode in keys:
        sel = [r for r in rows if r["filter"] == filt and r["mode"] == mode]
        rows.append({"trial": "mean", "filter": filt, "mode": mode,
                     "heading_rmse_deg": float(np.mean([r["heading_rmse_deg"] for r in sel])),
                     "inclination_rmse_deg": float(np.mean([r["inclination_rmse_deg"] for r in sel])),
                     "samples": int(sum(r["samples"] for r in sel))})
    return rows


def _rate(fn, n: int, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def throughput_rows(data_dir: Path, quick: bool = False) -> list[dict]:
    """Samples/s (best of a few runs, wall clock, one core) and × real time (at the trial's
    286 Hz) of: AEKF batch 9-D/6-D and online ``update``; VQF C++ batch; ``PyVQF`` (pure Python,
    shorter slice); Fusion; ahrs Madgwick. Rows: ``filter``, ``implementation``, ``mode``,
    ``samples``, ``samples_per_s``, ``x_realtime``."""
    from indoor_loc.imu.aekf import Aekf

    files = broad_files(data_dir)
    if not files:
        return []
    n = 5000 if quick else 20000
    tr = load_trial(files[0], None)
    for k in ("t_ns", "gyr", "acc", "mag", "quat_ref", "movement"):
        tr[k] = tr[k][:n]
    n = len(tr["t_ns"])
    rate = tr["rate_hz"]
    rep = 1 if quick else 3
    rows = []

    def add(filt, impl, mode, fn, m=n, r=rep):
        sps = _rate(fn, m, r)
        rows.append({"filter": filt, "implementation": impl, "mode": mode, "samples": m,
                     "samples_per_s": sps, "x_realtime": sps / rate})

    add("aekf", "python aekf_batch", "9d", lambda: run_aekf(tr, True))
    add("aekf", "python aekf_batch", "6d", lambda: run_aekf(tr, False))

    def online():
        f = Aekf()
        t, g, a, mg = tr["t_ns"], tr["gyr"], tr["acc"], tr["mag"]
        for i in range(n):
            f.update(int(t[i]), g[i], a[i], mg[i])
    add("aekf", "python Aekf.update", "9d", online, r=1)
    from vqf import VQF
    add("vqf", "C++ VQF.updateBatch", "9d", lambda: VQF(1.0 / rate).updateBatch(tr["gyr"], tr["acc"], tr["mag"]))
    try:
        from vqf import PyVQF
    except ImportError:  # older vqf without the pure-Python port
        PyVQF = None
    if PyVQF is not None:
        m = min(n, 2000)
        sl = {k: tr[k][:m] for k in ("gyr", "acc", "mag")}
        add("vqf", "python PyVQF.updateBatch", "9d",
            lambda: PyVQF(1.0 / rate).updateBatch(sl["gyr"], sl["acc"], sl["mag"]), m=m, r=1)
    add("fusion", "C imufusion (Python loop)", "9d", lambda: run_fusion(tr, True), r=1)
    m = min(n, 3000)
    small = dict(tr, gyr=tr["gyr"][:m], acc=tr["acc"][:m], mag=tr["mag"][:m])
    add("madgwick", "python ahrs", "9d", lambda: run_madgwick(small, True), m=m, r=1)
    return rows


def print_table(data_dir: Path = Path("../shared/datasets"), quick: bool = False) -> tuple[list, list]:
    """Print the BROAD accuracy and throughput tables; return their rows."""
    rows = broad_rows(data_dir, quick)
    if not rows:
        print(f"no BROAD trials under {data_dir}")
        return [], []
    filters = [k for k in ("aekf", "vqf", "fusion", "madgwick") if any(r["filter"] == k for r in rows)]
    for mode in ("9d", "6d"):
        cols = [f for f in filters if any(r["filter"] == f and r["mode"] == mode for r in rows)]
        if not cols:
            continue
        print(f"\nBROAD {mode.upper()}  heading / inclination RMSE [deg]"
              f"{' (first %.0f s of each trial)' % QUICK_SECONDS if quick else ''}")
        print(f"{'trial':34s}" + "".join(f"{c:>16s}" for c in cols))
        trials = list(dict.fromkeys(r["trial"] for r in rows))
        for t in trials:
            cells = []
            for c in cols:
                r = next((r for r in rows if r["trial"] == t and r["filter"] == c and r["mode"] == mode), None)
                cells.append(f"{r['heading_rmse_deg']:7.2f}/{r['inclination_rmse_deg']:<6.2f}" if r else "-")
            print(f"{t:34s}" + "".join(f"{x:>16s}" for x in cells))
    tp = throughput_rows(data_dir, quick)
    print("\nThroughput (one core, wall clock)")
    print(f"{'filter':10s}{'implementation':30s}{'mode':>5s}{'samples':>9s}{'samples/s':>12s}{'x real time':>13s}")
    for r in tp:
        print(f"{r['filter']:10s}{r['implementation']:30s}{r['mode']:>5s}{r['samples']:9d}"
              f"{r['samples_per_s']:12.0f}{r['x_realtime']:13.1f}")
    return rows, tp


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets"))
    ap.add_argument("--quick", action="store_true", help="first 60 s per trial, no ahrs Madgwick")
    args = ap.parse_args(argv)
    print_table(args.data, args.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
