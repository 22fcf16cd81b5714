"""Plausibility at the boundary: the physical bounds of :data:`indoor_loc.contract.BOUNDS` applied to
values already known finite (``msg_adapters.time.require_finite``), so a finite but absurd value
(x = 1e308, a frequency of 1e308 MHz, a negative variance) is rejected by its reason before any
stage state is touched.

Scalars and 3-vectors are checked on Python floats (an IMU message at 200 Hz cannot afford numpy on
three numbers); covariances with :func:`cov_rows_ok`, one vectorised test shared by the
per-message adapters (a batch of one) and the bulk decoder (:mod:`indoor_loc.bag.bulk`), so both
reject exactly the same messages.
"""
from __future__ import annotations

import numpy as np

from indoor_loc.contract import BOUNDS, COV_RTOL, Bound
from indoor_loc.errors import InvalidMessageError


def _fail(what: str, value: float, b: Bound) -> InvalidMessageError:
    return InvalidMessageError(b.reason, f"{what} = {value:.6g} {b.unit} outside [{b.lo:g}, {b.hi:g}] ({b.name}: "
                                         f"{b.why})")


def check(what: str, value: float, bound: str) -> None:
    """Raise ``BOUNDS[bound].reason`` (``out_of_range`` unless the table says otherwise) when the
    finite ``value`` is outside the bound."""
    b = BOUNDS[bound]
    if not b.lo <= value <= b.hi:
        raise _fail(what, value, b)


def check_xyz(what: str, x: float, y: float, z: float, bound: str) -> None:
    """:func:`check` per axis of a 3-vector of floats (``what.x`` names the offending axis)."""
    b = BOUNDS[bound]
    lo, hi = b.lo, b.hi
    if lo <= x <= hi and lo <= y <= hi and lo <= z <= hi:
        return
    for axis, v in (("x", x), ("y", y), ("z", z)):
        if not lo <= v <= hi:
            raise _fail(f"{what}.{axis}", v, b)


def rows_within(a: np.ndarray, bound: str) -> np.ndarray:
    """(N,) bool: every element of row ``i`` of the (N, k) array ``a`` is within the bound (the
    vectorised :func:`check_xyz`)."""
    b = BOUNDS[bound]
    return ((a >= b.lo) & (a <= b.hi)).all(axis=1)


def _var_bounds(var_bounds: str | tuple[str, ...], n: int) -> tuple[np.ndarray, np.ndarray]:
    names = (var_bounds,) * n if isinstance(var_bounds, str) else var_bounds
    return (np.array([BOUNDS[k].lo for k in names]), np.array([BOUNDS[k].hi for k in names]))


def cov_rows_ok(cov: np.ndarray, var_bounds: str | tuple[str, ...]) -> np.ndarray:
    """(N,) bool for finite covariances ``cov`` (N, n, n): symmetric and positive semi-definite within
    :data:`~indoor_loc.contract.COV_RTOL`, variance ``i`` (diagonal) within ``BOUNDS[var_bounds[i]]``
    (one name: every variance)."""
    c = np.asarray(cov, dtype=np.float64)
    m, n = c.shape[0], c.shape[-1]
    scale = np.maximum(1.0, np.abs(c).reshape(m, -1).max(axis=1, initial=0.0))
    tol = COV_RTOL * scale
    ct = np.swapaxes(c, 1, 2)
    ok = np.abs(c - ct).reshape(m, -1).max(axis=1, initial=0.0) <= tol
    lo, hi = _var_bounds(var_bounds, n)
    diag = c[:, np.arange(n), np.arange(n)]
    ok &= ((diag >= lo) & (diag <= hi)).all(axis=1)
    if ok.any():
        with np.errstate(all="ignore"):
            lam = np.linalg.eigvalsh(0.5 * (c[ok] + ct[ok]))
        ok[ok] = lam[:, 0] >= -tol[ok]
    return ok


def check_cov(what: str, cov: np.ndarray, var_bounds: str | tuple[str, ...]) -> None:
    """Raise ``bad_covariance`` unless the finite (n, n) ``cov`` passes :func:`cov_rows_ok`; the detail
    says which test failed."""
    c = np.asarray(cov, dtype=np.float64)
    if cov_rows_ok(c[None], var_bounds)[0]:
        return
    tol = COV_RTOL * max(1.0, float(np.abs(c).max()))
    if float(np.abs(c - c.T).max()) > tol:
        raise InvalidMessageError("bad_covariance", f"{what} is not symmetric: {c.tolist()}")
    names = (var_bounds,) * len(c) if isinstance(var_bounds, str) else var_bounds
    for i, name in enumerate(names):
        b = BOUNDS[name]
        if not b.lo <= c[i, i] <= b.hi:
            raise InvalidMessageError("bad_covariance", f"{what} variance [{i}, {i}] = {c[i, i]:.6g} {b.unit} "
                                                        f"outside [{b.lo:g}, {b.hi:g}] ({b.name}: {b.why})")
    raise InvalidMessageError("bad_covariance", f"{what} is not positive semi-definite: {c.tolist()}")
