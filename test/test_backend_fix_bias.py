"""The back-end's per-track fix bias (``GraphParams.fix_bias_std_m``): the fixes of one track share a
2-D error state with a zero-mean prior, so the floor plan can move a whole track whose fixes all sit
metres off (one bias prior) instead of fighting every fix; its Jacobian; nothing changes without it
or without the plan (the importer writing it: test_backend_ms_import.py)."""
from __future__ import annotations

import numpy as np
import pytest

from indoor_loc.backend.graph import FIX_GRAPH_PARAMS, GraphParams, MultiUserGraph
from indoor_loc.backend.walkable_term import load_walkable_fields
from indoor_loc.errors import ConfigError
from test_backend_walkable import _biased_walk, _floor


def _graph(field, **kw) -> MultiUserGraph:
    return MultiUserGraph(GraphParams(**{**FIX_GRAPH_PARAMS, "window_poses": 0, "pdr_info": [25.0, 25.0, 400.0],
                                         "gauge_std_rad": 0.37, **kw}), None, field)


def test_the_plan_moves_a_whole_biased_track_into_the_corridor_with_the_bias_state(tmp_path):
    """Fixes 6 m off into a shop along the whole walk: with independent fixes the plan (σ 1 m) holds the
    track half-way (every fix pulls); with the shared bias the whole track enters the corridor and the
    bias takes the fixes' offset."""
    field = load_walkable_fields(_floor(tmp_path))
    off = {}
    for std in (0.0, 5.0):
        g = _graph(field, walkable_std_m=1.0, fix_bias_std_m=std)
        _, xs = _biased_walk(g, 6.0, np.random.default_rng(4))
        off[std] = float(np.abs(xs[:, 1] - 3.0).mean())
        if std:
            assert 2.5 < g.fix_bias[g.users["u"].index][1] < 6.5        # the fixes' common offset (+y)
    assert off[0.0] > 2.5
    assert off[5.0] < off[0.0] - 0.5


def test_without_the_plan_the_bias_changes_nothing(tmp_path):
    """Without a second reference the bias is not observable: its zero-mean prior keeps it at zero and the
    track is the one independent fixes give."""
    field = load_walkable_fields(_floor(tmp_path))
    xs = {}
    for std in (0.0, 5.0):
        g = _graph(field, walkable_std_m=0.0, fix_bias_std_m=std)
        _, xs[std] = _biased_walk(g, 6.0, np.random.default_rng(4))
        assert np.allclose(g.fix_bias, 0.0, atol=0.01)
    np.testing.assert_allclose(xs[5.0][:, :2], xs[0.0][:, :2], atol=0.02)


@pytest.mark.parametrize("robust", ["none", "huber"])
def test_fix_bias_jacobian_matches_numerical_derivatives(tmp_path, robust):
    field = load_walkable_fields(_floor(tmp_path))
    rng = np.random.default_rng(6)
    g = _graph(field, walkable_std_m=0.7, fix_bias_std_m=3.0, robust_kernel=robust)
    _biased_walk(g, 6.0, rng)
    g.poses.x[:g.poses.n] += rng.normal(0, 0.5, (g.poses.n, 3))
    g.fix_bias[:] = rng.normal(0, 2.0, g.fix_bias.shape)
    fun, jac, z0, unpack, _ = g.problem(np.arange(g.poses.n))
    assert len(z0) == 3 * g.poses.n + 1 + 2                 # poses, the step length, the bias
    np.testing.assert_allclose(unpack(z0)[2], g.fix_bias)
    J = jac(z0).toarray()
    h = 1e-6
    num = np.stack([(fun(z0 + d) - fun(z0 - d)) / (2 * h) for d in h * np.eye(len(z0))], axis=1)
    np.testing.assert_allclose(J, num, atol=2e-4)
    assert np.abs(J[:, -2:]).sum() > 0                       # the bias columns are filled


def test_fix_bias_std_is_validated():
    with pytest.raises(ConfigError, match="fix_bias_std_m"):
        GraphParams(fix_bias_std_m=-1.0).validate()


def test_the_live_pose_takes_the_plan_through_the_bias_with_walkable_live(tmp_path):
    """Causal: the newest pose after each fix's window optimisation (what backend/<u>/pose publishes).
    Fixes 6 m off into a shop along the whole walk: with the plan in the windows (walkable_live) and the
    shared bias, the live poses enter the corridor; without the plan in the windows they follow the fixes."""
    field = load_walkable_fields(_floor(tmp_path))
    off = {}
    for live in (False, True):
        g = _graph(field, walkable_std_m=1.0, fix_bias_std_m=3.0, window_poses=30, walkable_live=live)
        rng = np.random.default_rng(4)
        g.set_floor("u", -5.0)
        t, x, newest = 0, 2.0, []
        for k in range(60):
            t0, t = t, t + 500_000_000
            x += 0.65
            g.add_hop("u", t0, t, 1.0, 0.0)
            if k % 4 == 3:
                g.add_fix("u", t, np.array([x + rng.normal(0, 1.0), 9.0 + rng.normal(0, 1.0)]), np.eye(2) * 4.0)
                newest.append(g.poses.x[g.users["u"].poses[-1], 1])
        off[live] = float(np.abs(np.asarray(newest[3:]) - 3.0).mean())    # after the first few fixes
    assert off[False] > 4.5                     # the live poses stay with the fixes, 6 m off
    assert off[True] < off[False] - 2.0         # the plan moves the live track (and its bias) into the corridor
