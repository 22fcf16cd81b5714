"""Factor models of the multi-user graph back-end: errors and analytic Jacobians, vectorised.

Every function takes arrays over *all* factors of one kind (leading dimension N) and returns the
errors and, when asked, their Jacobians — no Python loop per factor, so a whole graph is evaluated
in a few numpy calls whichever solver consumes it. Models from Nowicki & Skrzypczyński, "A
Multi-user Personal Indoor Localization System Employing Graph-based Optimization", Sensors 19(16)
2019, §5 (graph formulation):

- PDR edge between consecutive poses ``(x, y, θ)_{i-1}`` and ``(x, y, θ)_i`` of one user, with the
  measured step count ``f_i`` over the interval, measured heading change ``Δθ_i`` and that user's
  step length ``l``::

      e_p = [x_i − x_{i−1} − l f_i cos θ̄,  y_i − y_{i−1} − l f_i sin θ̄,  wrap(θ_i − θ_{i−1} − Δθ_i)]
      θ̄   = θ_{i−1} + wrap(θ_i − θ_{i−1}) / 2

  (the paper writes θ̄ = (θ_{i−1} + θ_i)/2; the wrapped form is the same angle without the ±π jump
  when the two headings straddle the cut). Information Ω_p = diag(1, 1, 15).
- Step-length prior ``e_s = l − l_0`` (l_0 = 0.65 m, Ω_s = 200).
- WKNN hyperedge between a pose and the k map scans its WiFi scan matched, with the normalised
  similarity weights ``w_j``: ``e_f = p_i − Σ_j w_j p_j`` (Ω_f = 10 I). Map scans are either fixed
  survey positions or other users' poses (then optimised: the multi-user coupling).

Robust kernels (the paper names wrong WKNN matches as its main failure mode) act on the whitened
squared norm ``s = eᵀΩe`` of a hyperedge: Huber ``ρ(s) = s`` for ``s ≤ c²`` else ``2c√s − c²``;
Cauchy ``ρ(s) = c² log(1 + s/c²)``; max-mixture (Olson & Agarwal, "Inference on networks of mixtures
for robust robot mapping", IJRR 2013) of the factor's own Gaussian and a broad one ``MAXMIX_SCALE``
times wider, the component with the lower cost taken: ``ρ(s) = min(s, s/k² + c²(1 − 1/k²))`` (k =
``MAXMIX_SCALE``; the constant, i.e. the components' weights, puts the switch at ``s = c²`` like
Huber's threshold) — beyond the threshold a fix keeps 1/k² of its information (Huber's linear tail
still pulls with c per σ of error, however far). :func:`robustify` rescales the whitened error to
``√(ρ(s)/s) e`` so its squared norm is exactly ``ρ(s)``, with the exact Jacobian of that rescaling.
"""
from __future__ import annotations

import math

import numpy as np

#: Paper values (Nowicki & Skrzypczyński 2019, Sec. 5): PDR information diag(1, 1, 15), WiFi 10 I, step-length prior 200.
PDR_INFO = (1.0, 1.0, 15.0)
WIFI_INFO = 10.0
STEP_PRIOR_INFO = 200.0
STEP_PRIOR_M = 0.65

ROBUST_KERNELS = ("none", "huber", "cauchy", "maxmix")
#: max-mixture kernel: the outlier component's standard deviation over the factor's own
MAXMIX_SCALE = 10.0


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-π, π)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def wrap_scalar(a: float) -> float:
    """:func:`wrap` of one angle in plain floats (the same operations, so the same bits: Python's
    float ``%`` and numpy's both take ``fmod`` and add the divisor to a remainder of the other
    sign), without numpy's per-call overhead in per-event code."""
    return (float(a) + math.pi) % (2.0 * math.pi) - math.pi


def pdr_error(prev: np.ndarray, cur: np.ndarray, step_len: np.ndarray, steps: np.ndarray, dtheta: np.ndarray,
              *, jacobians: bool = False):
    """PDR edges. prev, cur (N, 3) poses (x m, y m, θ rad); step_len (N,) m; steps (N,) step counts
    f_i; dtheta (N,) measured heading change, rad.

    Returns e (N, 3) (unwhitened), and with ``jacobians`` also (J_prev (N, 3, 3), J_cur (N, 3, 3),
    J_len (N, 3)) — d e / d prev, d e / d cur, d e / d l.
    """
    prev = np.asarray(prev, float)
    cur = np.asarray(cur, float)
    l = np.asarray(step_len, float)
    f = np.asarray(steps, float)
    dth = wrap(cur[:, 2] - prev[:, 2])
    mean = prev[:, 2] + 0.5 * dth
    c, s = np.cos(mean), np.sin(mean)
    d = l * f
    e = np.empty((len(prev), 3))
    e[:, 0] = cur[:, 0] - prev[:, 0] - d * c
    e[:, 1] = cur[:, 1] - prev[:, 1] - d * s
    e[:, 2] = wrap(dth - np.asarray(dtheta, float))
    if not jacobians:
        return e
    n = len(prev)
    jp = np.zeros((n, 3, 3))
    jc = np.zeros((n, 3, 3))
    # d θ̄ / d θ_{i-1} = d θ̄ / d θ_i = 1/2
    jp[:, 0, 0] = -1.0
    jp[:, 1, 1] = -1.0
    jp[:, 0, 2] = 0.5 * d * s
    jp[:, 1, 2] = -0.5 * d * c
    jp[:, 2, 2] = -1.0
    jc[:, 0, 0] = 1.0
    jc[:, 1, 1] = 1.0
    jc[:, 0, 2] = 0.5 * d * s
    jc[:, 1, 2] = -0.5 * d * c
    jc[:, 2, 2] = 1.0
    jl = np.stack([-f * c, -f * s, np.zeros(n)], axis=1)
    return e, (jp, jc, jl)


def wifi_error(pose_xy: np.ndarray, nbr_xy: np.ndarray, weights: np.ndarray, *, jacobians: bool = False):
    """WKNN hyperedges. pose_xy (N, 2) m; nbr_xy (N, k, 2) m the matched scans' positions; weights
    (N, k) normalised similarities (rows sum to 1; padding entries 0).

    Returns e (N, 2) and with ``jacobians`` (J_pose (N, 2, 2) = I, J_nbr (N, k, 2, 2) = −w_j I).
    """
    p = np.asarray(pose_xy, float)
    q = np.asarray(nbr_xy, float)
    w = np.asarray(weights, float)
    # Σ_j w_j q_j accumulated neighbour by neighbour (numpy's einsum costs ~50 us a call here)
    acc = w[:, 0, None] * q[:, 0]
    for j in range(1, w.shape[1]):
        acc = acc + w[:, j, None] * q[:, j]
    e = p - acc
    if not jacobians:
        return e
    n, k = w.shape
    jpose = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    jnbr = -w[:, :, None, None] * np.eye(2)[None, None]
    return e, (jpose, jnbr)


def step_prior_error(step_len: np.ndarray, prior_m: float = STEP_PRIOR_M) -> np.ndarray:
    """Step-length prior e_s = l − l_0, (N,); its Jacobian is 1."""
    return np.asarray(step_len, float) - prior_m


def robust_rho(s: np.ndarray, kernel: str, c: float) -> tuple[np.ndarray, np.ndarray]:
    """ρ(s) and ρ'(s) of a kernel at whitened squared norms s (N,), threshold c (whitened units)."""
    s = np.asarray(s, float)
    if kernel == "none":
        return s, np.ones_like(s)
    if kernel == "huber":
        root = np.sqrt(np.maximum(s, 1e-300))
        inl = s <= c * c
        rho = np.where(inl, s, 2.0 * c * root - c * c)
        drho = np.where(inl, 1.0, c / root)
        return rho, drho
    if kernel == "cauchy":
        c2 = c * c
        return c2 * np.log1p(s / c2), 1.0 / (1.0 + s / c2)
    if kernel == "maxmix":
        k2 = MAXMIX_SCALE * MAXMIX_SCALE
        inl = s <= c * c
        return np.where(inl, s, s / k2 + c * c * (1.0 - 1.0 / k2)), np.where(inl, 1.0, 1.0 / k2)
    raise ValueError(f"robust kernel: expected one of {ROBUST_KERNELS}, got {kernel!r}")


def robustify(e: np.ndarray, jac: list[np.ndarray] | None, kernel: str, c: float):
    """Rescale whitened errors e (N, d) to g(s) e with g = √(ρ(s)/s), s = |e|², so the squared norm
    is ρ(s). ``jac``: Jacobians of e, each (N, d, ...) — returned as d(g e)/dx = g J + e g'(s) 2 eᵀJ.
    Returns (e', jac' or None, weights g² = ρ(s)/s (N,) — 1 for inliers)."""
    if kernel == "none":
        return e, jac, np.ones(len(e))
    s = e[:, 0] * e[:, 0]                  # |e|² term by term (numpy's einsum costs ~50 us a call here)
    for j in range(1, e.shape[1]):
        s = s + e[:, j] * e[:, j]
    rho, drho = robust_rho(s, kernel, c)
    small = s < 1e-12
    ss = np.where(small, 1.0, s)
    g = np.where(small, 1.0, np.sqrt(np.maximum(rho, 0.0) / ss))
    # g'(s) = (ρ' s − ρ) / (2 s² g)
    dg = np.where(small, 0.0, (drho * ss - rho) / (2.0 * ss * ss * np.maximum(g, 1e-300)))
    e2 = g[:, None] * e
    if jac is None:
        return e2, None, g * g
    out = []
    for J in jac:
        extra = J.ndim - 2
        gsh = g.reshape((-1,) + (1,) * (extra + 1))
        esh = (-1,) + (1,) * extra
        # eᵀJ: (N, ...) contracted over the error dimension
        eTJ = e[:, 0].reshape(esh) * J[:, 0]
        for j in range(1, e.shape[1]):
            eTJ = eTJ + e[:, j].reshape(esh) * J[:, j]
        corr = (2.0 * dg).reshape((-1,) + (1,) * extra) * eTJ
        out.append(gsh * J + e.reshape(e.shape + (1,) * extra) * corr[:, None, ...])
    return e2, out, g * g
