"""TyRex attitude benchmark for smartphones: readers, time alignment and the benchmark's scoring.

Data: Michel, Genevès, Fourati, Layaïda, "On Attitude Estimation with Smartphones", PerCom 2017
(tyrex-team/benchmarks-attitude-smartphones, CeCILL 2.1). One folder per trial,
``<Person>_Nexus5_<Dist|NoDist>_<Motion>/`` with gzip text files (phone seconds) and the Qualisys
truth ``qualisys/<trial>.mat`` (body→room rotation matrices, 60 Hz, room frame ENU with true north).

- :func:`load_trial` reads one trial: gyroscope stamps (int ns, phone clock) with the accelerometer
  linearly interpolated onto them (what an ``imu/data_raw`` driver publishes), the magnetometer on its
  own stamps, Android's rotation vector, and the truth on the phone clock after the time alignment.
- Time alignment: ``timeAlignment.txt`` (reference = phone + offset) comes from an accelerometer-norm
  fit that is late by about 20 ms; :func:`refine_offset` refines it per trial by matching the
  gyroscope's rate magnitude to the truth's body-rate magnitude (independent of any filter).
- :func:`score` is the benchmark's protocol: reference time 5…120 s, truth slerped to each
  estimate's stamp, samples next to a tracking gap and the authors' flagged intervals dropped, then
  the BROAD error metric (Laidig et al., "BROAD — A Benchmark for Robust Inertial Orientation
  Estimation", Data 6(7), 2021): heading and inclination RMSE of ``q_est ⊗ q_ref⁻¹``.
- Filters run in the magnetic frame; the room frame has true north. :func:`to_true_north` turns an
  estimate by the declination at the lab, +1.475° E (WMM2015 at 45.1878 N, 5.7269 E, 2016-05-31).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from indoor_loc.errors import ConfigError
from indoor_loc.imu.quaternion import heading_inclination_error, qconj, qmul

DECLINATION_RAD = math.radians(1.475)
TRUTH_RATE_HZ = 60.0
SCORE_SPAN_S = (5.0, 120.0)
#: the benchmark authors' flagged intervals, reference seconds
FLAGGED_S: dict[str, list[tuple[float, float]]] = {
    "Guillaume_Nexus5_NoDist_AR": [(64.0, 120.0)],
    "Jakob_Nexus5_Dist_Phoning": [(4.7, 5.6), (91.95, 93.2)],
    "Jakob_Nexus5_Dist_Swinging": [(96.2, 97.5)],
    "Thibaud_Nexus5_Dist_FrontPocket": [(40.0, 52.6)],
    "Thibaud_Nexus5_NoDist_Swinging": [(36.8, 37.2)],
}


@dataclass
class TyrexTrial:
    """One trial. Stamps are int ns on the phone clock; ``offset_ns`` maps them to reference time
    (reference = phone + offset). Arrays: ``gyr`` rad/s and ``acc`` m/s² (N, 3) on ``t_ns`` (N,);
    ``mag`` µT (M, 3) on ``mag_t_ns`` (M,) (calibrated by Android); ``mag_raw`` (M, 3) uncalibrated
    and ``mag_bias_android`` (3,) Android's hard-iron estimate; ``rv_t_ns``/``rv_quat`` (K, 4)
    Android's rotation vector (w x y z, device→ENU magnetic... as Android defines it, true north
    when the phone has a location fix); truth ``ref_t_ns`` (phone clock) and ``ref_quat`` (w x y z,
    body→room, NaN where tracking dropped)."""

    name: str
    t_ns: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag_t_ns: np.ndarray
    mag: np.ndarray
    mag_raw: np.ndarray
    mag_bias_android: np.ndarray
    rv_t_ns: np.ndarray
    rv_quat: np.ndarray
    ref_t_ns: np.ndarray
    ref_quat: np.ndarray
    offset_ns: int
    file_offset_ns: int

    @property
    def person(self) -> str:
        return self.name.split("_")[0]

    @property
    def disturbed(self) -> bool:
        return "_Dist_" in self.name


def trial_dirs(data_dir: Path) -> list[Path]:
    """Trial folders under ``data_dir/tyrex_dev`` (or ``data_dir`` itself), sorted by name."""
    data_dir = Path(data_dir)
    d = data_dir / "tyrex_dev" if (data_dir / "tyrex_dev").is_dir() else data_dir
    return sorted(p for p in d.glob("*_Nexus5_*") if (p / "accelerometer.txt.gz").is_file())


def _load(path: Path) -> np.ndarray:
    try:
        return np.atleast_2d(np.loadtxt(path))
    except (OSError, ValueError) as err:
        raise ConfigError(f"cannot read TyRex file {path}: {err}") from err


def _strictly_increasing(t: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    keep = np.concatenate([[True], np.diff(t) > 0])
    return (t[keep],) + tuple(a[keep] for a in arrays)


def _truth(mat_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_s (F,) reference seconds, quat (F, 4) w x y z body→room, NaN rows where tracking dropped)."""
    import scipy.io
    from scipy.spatial.transform import Rotation

    m = scipy.io.loadmat(mat_path)
    key = next(k for k in m if not k.startswith("_"))
    s = m[key]
    rot = np.asarray(s["RigidBodies"][0, 0]["Rotations"][0, 0], dtype=float)   # (bodies, 9, F)
    rate = float(np.asarray(s["FrameRate"][0, 0]).ravel()[0]) if "FrameRate" in s.dtype.names else TRUTH_RATE_HZ
    r9 = rot[0]                                                                   # (9, F)
    f = r9.shape[1]
    ok = np.isfinite(r9).all(axis=0)
    quat = np.full((f, 4), np.nan)
    if ok.any():
        mats = r9[:, ok].T.reshape(-1, 3, 3).transpose(0, 2, 1)                    # column-major 3×3
        xyzw = Rotation.from_matrix(mats).as_quat()
        quat[ok] = xyzw[:, [3, 0, 1, 2]]
    return np.arange(f) / rate, quat


def load_trial(folder: Path, *, refine: bool = True) -> TyrexTrial:
    """Read one trial folder (see :class:`TyrexTrial`)."""
    folder = Path(folder)
    name = folder.name
    g = _load(folder / "gyroscope-calibrated.txt.gz")
    a = _load(folder / "accelerometer.txt.gz")
    mc = _load(folder / "magnetometer-calibrated.txt.gz")
    mu = _load(folder / "magnetometer.txt.gz")
    rv = _load(folder / "rotation-vector.txt.gz")
    off_s = float(np.loadtxt(folder / "timeAlignment.txt"))
    gt, gyr = _strictly_increasing(np.round(g[:, 0] * 1e9).astype(np.int64), g[:, 1:4])
    at, acc = _strictly_increasing(np.round(a[:, 0] * 1e9).astype(np.int64), a[:, 1:4])
    # the accelerometer onto the gyroscope's stamps (most stamps are shared; the rest interpolate)
    inside = (gt >= at[0]) & (gt <= at[-1])
    gt, gyr = gt[inside], gyr[inside]
    acc_i = np.stack([np.interp(gt, at, acc[:, k]) for k in range(3)], axis=1)
    mt, mag = _strictly_increasing(np.round(mc[:, 0] * 1e9).astype(np.int64), mc[:, 1:4])
    mut, mag_raw, mag_b = _strictly_increasing(np.round(mu[:, 0] * 1e9).astype(np.int64), mu[:, 1:4], mu[:, 4:7])
    rt, rvq = _strictly_increasing(np.round(rv[:, 0] * 1e9).astype(np.int64), rv[:, 1:5])
    rv_wxyz = rvq[:, [3, 0, 1, 2]]
    ref_s, ref_q = _truth(folder.parent / "qualisys" / f"{name}.mat")
    off_ns = int(round(off_s * 1e9))
    tr = TyrexTrial(name=name, t_ns=gt, gyr=gyr, acc=acc_i, mag_t_ns=mt, mag=mag, mag_raw=mag_raw,
                    mag_bias_android=np.median(mag_b, axis=0), rv_t_ns=rt, rv_quat=rv_wxyz,
                    ref_t_ns=np.round(ref_s * 1e9).astype(np.int64) - off_ns, ref_quat=ref_q,
                    offset_ns=off_ns, file_offset_ns=off_ns)
    if refine:
        d = refine_offset(tr)
        tr.offset_ns += d
        tr.ref_t_ns = tr.ref_t_ns - d
    return tr


def _truth_rate_norm(tr: TyrexTrial) -> tuple[np.ndarray, np.ndarray]:
    """|body rate| of the truth between consecutive frames (rad/s) at the frames' mid-times (phone ns
    under the file's offset); NaN across tracking gaps."""
    q = tr.ref_quat
    e = qmul(qconj(q[:-1]), q[1:])
    ang = 2.0 * np.arctan2(np.linalg.norm(e[:, 1:], axis=1), np.abs(e[:, 0]))
    dt = np.diff(tr.ref_t_ns) * 1e-9
    mid = (tr.ref_t_ns[:-1] + tr.ref_t_ns[1:]) // 2
    return mid, ang / dt


def refine_offset(tr: TyrexTrial, *, search_s: float = 0.1, step_s: float = 0.001) -> int:
    """Correction (ns) to add to ``tr.offset_ns``: the lag in ±``search_s`` that best matches the
    gyroscope's |ω| (boxcar-averaged over one truth frame) to the truth's |ω| in the least-squares
    sense over the scored span. Filter-independent."""
    mid, wref = _truth_rate_norm(tr)
    ok = np.isfinite(wref)
    t_ref = tr.offset_ns + mid                       # reference ns
    ok &= (t_ref >= SCORE_SPAN_S[0] * 1e9) & (t_ref <= SCORE_SPAN_S[1] * 1e9)
    mid, wref = mid[ok], wref[ok]
    # gyro rotation angle integrated; mean |ω| over a frame interval ≈ |Δ(integrated ω)| / Δt
    t = tr.t_ns
    dt = np.diff(t) * 1e-9
    dt = np.minimum(dt, 0.05)
    cum = np.concatenate([np.zeros((1, 3)), np.cumsum(tr.gyr[:-1] * dt[:, None], axis=0)])
    half = int(round(0.5e9 / TRUTH_RATE_HZ))
    best, best_lag = math.inf, 0
    for lag in np.arange(-search_s, search_s + 0.5 * step_s, step_s):
        c = mid + int(round(lag * 1e9))
        lo = np.stack([np.interp(c - half, t, cum[:, k]) for k in range(3)], axis=1)
        hi = np.stack([np.interp(c + half, t, cum[:, k]) for k in range(3)], axis=1)
        w = np.linalg.norm(hi - lo, axis=1) / (2 * half * 1e-9)
        cost = float(np.mean((w - wref) ** 2))
        if cost < best:
            best, best_lag = cost, int(round(lag * 1e9))
    # truth at phone time t_phone + offset: a gyro lag of +L means reference = phone + offset − L
    return -best_lag


def to_true_north(q_wxyz: np.ndarray, declination_rad: float = DECLINATION_RAD) -> np.ndarray:
    """Turn device→ENU(magnetic) quaternions into device→ENU(true north): a heading measured from
    magnetic north lies ``declination`` east of true north, i.e. a rotation by −declination about
    up. Shape (…, 4)."""
    h = -0.5 * declination_rad
    return qmul(np.array([math.cos(h), 0.0, 0.0, math.sin(h)]), q_wxyz)


def _slerp_truth(tr: TyrexTrial, t_ns: np.ndarray) -> np.ndarray:
    """Truth slerped to ``t_ns`` (phone ns), NaN outside the truth or next to a tracking gap (either
    bracketing frame missing)."""
    from scipy.spatial.transform import Rotation, Slerp

    out = np.full((len(t_ns), 4), np.nan)
    rt = tr.ref_t_ns
    idx = np.searchsorted(rt, t_ns, side="right") - 1
    inside = (idx >= 0) & (idx < len(rt) - 1)
    good = np.isfinite(tr.ref_quat).all(axis=1)
    ok = inside.copy()
    ok[inside] = good[idx[inside]] & good[idx[inside] + 1]
    if not ok.any():
        return out
    gi = np.flatnonzero(good)
    # slerp across the good frames only; samples whose bracket has a gap were excluded above
    slerp = Slerp(rt[gi] * 1e-9, Rotation.from_quat(tr.ref_quat[gi][:, [1, 2, 3, 0]]))
    x = slerp(t_ns[ok] * 1e-9).as_quat()
    out[ok] = x[:, [3, 0, 1, 2]]
    return out


def score_mask(tr: TyrexTrial, t_ns: np.ndarray) -> np.ndarray:
    """Samples (phone ns) that the protocol scores: reference time in 5…120 s and outside the
    authors' flagged intervals (tracking gaps are removed by the NaN truth)."""
    ref_s = (np.asarray(t_ns) + tr.offset_ns) * 1e-9
    m = (ref_s >= SCORE_SPAN_S[0]) & (ref_s <= SCORE_SPAN_S[1])
    for lo, hi in FLAGGED_S.get(tr.name, []):
        m &= ~((ref_s >= lo) & (ref_s <= hi))
    return m


def score(tr: TyrexTrial, t_ns: np.ndarray, q_est_mag: np.ndarray, *, true_north: bool = False
          ) -> tuple[float, float, int]:
    """(heading RMSE °, inclination RMSE °, samples) of estimates ``q_est_mag`` (N, 4) w x y z
    device→ENU at stamps ``t_ns`` (phone ns). Estimates are in the magnetic frame and turned by the
    declination unless ``true_north`` (Android's rotation vector with a location fix)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    q = np.asarray(q_est_mag, dtype=float)
    if not true_north:
        q = to_true_north(q)
    ref = _slerp_truth(tr, t_ns)
    m = score_mask(tr, t_ns) & np.isfinite(ref).all(axis=1) & np.isfinite(q).all(axis=1)
    if not m.any():
        return float("nan"), float("nan"), 0
    he, ie = heading_inclination_error(q[m], ref[m])
    return (math.degrees(math.sqrt(float(np.mean(he ** 2)))),
            math.degrees(math.sqrt(float(np.mean(ie ** 2)))), int(m.sum()))
