"""The back-end's max-mixture fix kernel (``robust_kernel: maxmix``): a stretch of fixes matched to a
look-alike place far away (not one bias of the whole track, so the bias state cannot take it) pulls
the track much less than under Huber, whose linear tail keeps pulling however far the fixes are;
the kernel's cost and Jacobian: test_backend_factors.py."""
from __future__ import annotations

import numpy as np

from indoor_loc.backend.graph import FIX_GRAPH_PARAMS, GraphParams, MultiUserGraph

SEC = 1_000_000_000


def _walk_with_lookalike_stretch(kernel: str, rng) -> np.ndarray:
    """A user walking along y = 0 (a step of 0.65 m every 0.5 s, 30 s), a fix (σ 2 m) every 2 s;
    four consecutive fixes in the middle sit 25 m off (a look-alike corridor). Returns the optimised
    poses' errors from y = 0 (m)."""
    g = MultiUserGraph(GraphParams(**{**FIX_GRAPH_PARAMS, "robust_kernel": kernel, "window_poses": 0,
                                      "pdr_info": [25.0, 25.0, 400.0], "gauge_std_rad": 0.37}), None)
    t, x = 0, 0.0
    for k in range(60):
        t0, t = t, t + SEC // 2
        x += 0.65
        g.add_hop("u", t0, t, 1.0, 0.0)
        if k % 4 == 3:
            off = 25.0 if 5 <= k // 4 <= 8 else 0.0
            g.add_fix("u", t, np.array([x, off]) + rng.normal(0, 2.0, 2), np.eye(2) * 4.0)
    g.optimize()
    _, xs = g.trajectory("u")
    return np.abs(xs[:, 1])


def test_maxmix_lets_a_lookalike_stretch_of_fixes_go_where_huber_bends_the_track():
    err = {k: float(_walk_with_lookalike_stretch(k, np.random.default_rng(3)).mean()) for k in ("huber", "maxmix")}
    assert err["huber"] > 2.0                      # Huber: the stretch drags the stiff track metres off
    assert err["maxmix"] < 0.6 * err["huber"]      # max-mixture: the stretch is left to its broad component


def test_maxmix_is_the_plain_least_squares_when_every_fix_is_an_inlier():
    """Inside the threshold the kernel is the fix's own Gaussian: the same track as with no kernel."""
    rng = np.random.default_rng(5)
    g = {}
    for kernel in ("none", "maxmix"):
        p = GraphParams(**{**FIX_GRAPH_PARAMS, "robust_kernel": kernel, "robust_threshold_m": 50.0,
                           "window_poses": 0})
        g[kernel] = MultiUserGraph(p, None)
    fixes = rng.normal(0, 1.0, (10, 2))
    for gr in g.values():
        t = 0
        for k in range(40):
            t0, t = t, t + SEC // 2
            gr.add_hop("u", t0, t, 1.0, 0.0)
            if k % 4 == 3:
                gr.add_fix("u", t, fixes[k // 4] + [0.65 * (k + 1), 0.0], np.eye(2))
        gr.optimize()
    np.testing.assert_allclose(g["maxmix"].trajectory("u")[1], g["none"].trajectory("u")[1], atol=1e-4)
