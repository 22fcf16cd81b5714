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
