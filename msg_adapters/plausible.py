"""Plausibility at the boundary: the physical bounds of :data:`indoor_loc.contract.BOUNDS` applied to
values already known finite (``msg_adapters.time.require_finite``), so a finite but absurd value
(x = 1e308, a frequency of 1e308 MHz, a negative variance) is rejected by its reason before any
stage state is touched.

Scalars, 3-vectors and covariances are checked on Python floats (an IMU message at 200 Hz cannot
afford numpy on nine numbers); the bulk decoder (:mod:`indoor_loc.bag.bulk`) runs the same
arithmetic on columns (:func:`rows_within`, :func:`cov_rows_ok`), so both reject exactly the same
messages.
"""
from __future__ import annotations

from typing import Any

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


def _var_bounds(var_bounds: str | tuple[str, ...], n: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    names = (var_bounds,) * n if isinstance(var_bounds, str) else var_bounds
    return tuple(BOUNDS[k].lo for k in names), tuple(BOUNDS[k].hi for k in names)


def _cov_tests(c: list, lo: tuple[float, ...], hi: tuple[float, ...], mx: Any) -> list:
    """The covariance tests on the entries ``c[i][j]`` (floats, or (N,) arrays of them), as a list of
    booleans (or bool arrays) in the order :func:`check_cov` reports them: symmetric, each variance in
    bounds, each 2x2 principal minor and the 3x3 determinant not negative. Tolerances are relative
    (``COV_RTOL``) to the entries' own scale -- ``|c_ij - c_ji|`` to the largest of
    ``|c_ii|, |c_jj|, |c_ij|, |c_ji|``, a minor to the product of its variances -- so one test holds
    for a yaw variance of 1e6 beside a tilt variance of 1e-4. The same arithmetic on floats and on
    arrays (``mx``: ``max`` or ``np.maximum``), so a message and a bulk row give the same answer."""
    n = len(c)
    tol = COV_RTOL
    sym = True
    for i in range(n):
        for j in range(i + 1, n):
            scale = mx(mx(abs(c[i][i]), abs(c[j][j])), mx(abs(c[i][j]), abs(c[j][i])))
            sym = sym & (abs(c[i][j] - c[j][i]) <= tol * scale)
    var = [(c[i][i] >= lo[i]) & (c[i][i] <= hi[i]) for i in range(n)]
    m = [[c[i][j] if i == j else 0.5 * (c[i][j] + c[j][i]) for j in range(n)] for i in range(n)]
    minors = []
    for i in range(n):
        for j in range(i + 1, n):
            d = m[i][i] * m[j][j]
            minors.append(d - m[i][j] * m[i][j] >= -tol * d)
    if n == 3:
        det = (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[1][2]) - m[0][1] * (m[0][1] * m[2][2] - m[1][2] * m[0][2])
               + m[0][2] * (m[0][1] * m[1][2] - m[1][1] * m[0][2]))
        minors.append(det >= -tol * (m[0][0] * m[1][1] * m[2][2]))
    return [sym, *var, *minors]


def cov_rows_ok(cov: np.ndarray, var_bounds: str | tuple[str, ...]) -> np.ndarray:
    """(N,) bool for finite (N, n, n) covariances (n = 2 or 3): symmetric and positive semi-definite
    within :data:`~indoor_loc.contract.COV_RTOL`, variance ``i`` within ``BOUNDS[var_bounds[i]]`` (one
    name: every variance). The vectorised :func:`check_cov`, for the bulk decoder."""
    a = np.asarray(cov, dtype=np.float64)
    n = a.shape[-1]
    lo, hi = _var_bounds(var_bounds, n)
    with np.errstate(all="ignore"):
        tests = _cov_tests([[a[:, i, j] for j in range(n)] for i in range(n)], lo, hi, np.maximum)
    ok = np.ones(len(a), dtype=bool)
    for t in tests:
        ok &= t
    return ok


def check_cov(what: str, cov: Any, var_bounds: str | tuple[str, ...]) -> None:
    """Raise ``bad_covariance`` unless the finite (n, n) covariance ``cov`` (n = 2 or 3) is symmetric
    and positive semi-definite within :data:`~indoor_loc.contract.COV_RTOL` with its variances in their
    bounds (``var_bounds``: the bound's name per variance, or one for all); the detail says which test
    failed. Plain float arithmetic: the per-message path at IMU rates."""
    rows = cov.tolist() if isinstance(cov, np.ndarray) else [list(r) for r in cov]
    n = len(rows)
    lo, hi = _var_bounds(var_bounds, n)
    tests = _cov_tests(rows, lo, hi, max)
    if all(tests):
        return
    if not tests[0]:
        raise InvalidMessageError("bad_covariance", f"{what} is not symmetric: {rows}")
    names = (var_bounds,) * n if isinstance(var_bounds, str) else var_bounds
    for i in range(n):
        if not tests[1 + i]:
            b = BOUNDS[names[i]]
            raise InvalidMessageError("bad_covariance", f"{what} variance [{i}, {i}] = {rows[i][i]:.6g} {b.unit} "
                                                        f"outside [{b.lo:g}, {b.hi:g}] ({b.name}: {b.why})")
    raise InvalidMessageError("bad_covariance", f"{what} is not positive semi-definite: {rows}")
