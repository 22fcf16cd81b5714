"""Factor models of the back-end: errors on hand-made cases and analytic Jacobians against
central differences (the oracle), including the robust rescaling."""
from __future__ import annotations

import math

import numpy as np
import pytest

from indoor_loc.backend import factors as F


def numeric_jac(fun, x, h=1e-6):
    """Central differences of fun: R^n -> R^m at x -> (m, n)."""
    x = np.asarray(x, float)
    cols = []
    for i in range(len(x)):
        d = np.zeros_like(x)
        d[i] = h
        cols.append((np.asarray(fun(x + d)) - np.asarray(fun(x - d))) / (2 * h))
    return np.stack(cols, axis=-1)


def test_pdr_error_is_zero_for_a_consistent_motion():
    # 2 steps of 0.65 m from (1, 2) heading 30 deg, turning +20 deg: the chord follows the mean heading
    th0, dth = math.radians(30), math.radians(20)
    mean = th0 + dth / 2
    prev = np.array([[1.0, 2.0, th0]])
    cur = np.array([[1.0 + 1.3 * math.cos(mean), 2.0 + 1.3 * math.sin(mean), th0 + dth]])
    e = F.pdr_error(prev, cur, np.array([0.65]), np.array([2.0]), np.array([dth]))
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    # a wrong heading change shows up in the third component only (wrapped)
    e = F.pdr_error(prev, cur, np.array([0.65]), np.array([2.0]), np.array([dth + 2 * math.pi + 0.1]))
    np.testing.assert_allclose(e[0], [0.0, 0.0, -0.1], atol=1e-12)


def test_pdr_mean_heading_across_the_cut():
    # headings +179 deg and -179 deg: the walk goes along -x, not along +x
    prev = np.array([[0.0, 0.0, math.radians(179)]])
    cur = np.array([[-1.0, 0.0, math.radians(-179)]])
    e = F.pdr_error(prev, cur, np.array([1.0]), np.array([1.0]), np.array([math.radians(2)]))
    np.testing.assert_allclose(e, 0.0, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pdr_jacobians_match_numerical_derivatives(seed):
    rng = np.random.default_rng(seed)
    prev = rng.normal(size=3) * [5, 5, 2]
    cur = prev + rng.normal(size=3) * [1, 1, 0.5]
    l, f, dth = 0.6 + 0.1 * rng.random(), 1 + 3 * rng.random(), rng.normal() * 0.3

    def e_of(z):
        return F.pdr_error(z[None, 0:3], z[None, 3:6], np.array([z[6]]), np.array([f]), np.array([dth]))[0]

    z = np.concatenate([prev, cur, [l]])
    _, (jp, jc, jl) = F.pdr_error(prev[None], cur[None], np.array([l]), np.array([f]), np.array([dth]),
                                  jacobians=True)
    num = numeric_jac(e_of, z)
    np.testing.assert_allclose(jp[0], num[:, 0:3], atol=1e-6)
    np.testing.assert_allclose(jc[0], num[:, 3:6], atol=1e-6)
    np.testing.assert_allclose(jl[0], num[:, 6], atol=1e-6)


def test_wifi_error_and_jacobians():
    pose = np.array([[2.0, 3.0]])
    nbr = np.array([[[0.0, 0.0], [4.0, 0.0], [4.0, 6.0], [0.0, 6.0]]])
    w = np.array([[0.25, 0.25, 0.25, 0.25]])
    e, (jp, jn) = F.wifi_error(pose, nbr, w, jacobians=True)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)          # at the weighted centroid
    rng = np.random.default_rng(4)
    w = rng.random((1, 4))
    w /= w.sum()
    z = np.concatenate([pose.ravel(), nbr.ravel()])
    num = numeric_jac(lambda q: F.wifi_error(q[None, :2], q[2:].reshape(1, 4, 2), w)[0], z)
    _, (jp, jn) = F.wifi_error(pose, nbr, w, jacobians=True)
    np.testing.assert_allclose(jp[0], num[:, :2], atol=1e-8)
    for j in range(4):
        np.testing.assert_allclose(jn[0, j], num[:, 2 + 2 * j: 4 + 2 * j], atol=1e-8)


@pytest.mark.parametrize("kernel", ["huber", "cauchy", "maxmix"])
def test_robustify_cost_and_jacobian(kernel):
    c = 1.5
    rng = np.random.default_rng(7)
    A = rng.normal(size=(2, 3))           # a linear error e = A x, so J = A

    def robust_e(x):
        return F.robustify((A @ x)[None], None, kernel, c)[0][0]

    for scale in (0.1, 1.0, 5.0):         # inlier, near the threshold, outlier
        x = rng.normal(size=3) * scale
        e = (A @ x)[None]
        e2, (J2,), w = F.robustify(e, [A[None]], kernel, c)
        s = float(e[0] @ e[0])
        rho, _ = F.robust_rho(np.array([s]), kernel, c)
        assert float(e2[0] @ e2[0]) == pytest.approx(float(rho[0]), rel=1e-10)   # |e'|^2 = rho(s)
        np.testing.assert_allclose(J2[0], numeric_jac(robust_e, x), atol=1e-6)
        assert 0 < w[0] <= 1 + 1e-12
    # Huber is quadratic inside the threshold: no change at all
    if kernel == "huber":
        e = np.array([[0.3, 0.4]])
        np.testing.assert_allclose(F.robustify(e, None, kernel, c)[0], e)


def test_unknown_kernel_is_refused():
    with pytest.raises(ValueError, match="robust kernel"):
        F.robust_rho(np.ones(2), "tukey", 1.0)


def test_wrap_scalar_gives_wraps_bits():
    """The per-event scalar wrap equals the vectorised one bit for bit (seeded angles over many
    turns, the borders ±π, ±2π, signed zeros, tiny and huge values)."""
    rng = np.random.default_rng(12)
    a = np.concatenate([rng.normal(0, 20, 2000), rng.uniform(-1e6, 1e6, 200),
                        [0.0, -0.0, math.pi, -math.pi, 2 * math.pi, -2 * math.pi, 3 * math.pi, 1e-300, -1e-300,
                         np.nextafter(math.pi, 0), np.nextafter(-math.pi, 0), 1e17, -1e17]])
    vec = F.wrap(a)
    one = np.array([F.wrap_scalar(v) for v in a.tolist()])
    assert one.tobytes() == vec.tobytes()
    assert all(isinstance(F.wrap_scalar(v), float) for v in (1, np.float64(2.0), -7.5))
