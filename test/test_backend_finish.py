"""The back-end's end of input is bounded: one factorisation for every user's final covariance, a
time budget on the whole-graph optimisation, every path published whatever the budget cut short."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from backend_synth import SEC, corridor_walk, feed, survey
from indoor_loc.backend import graph as graph_mod
from indoor_loc.backend.graph import GraphParams, MultiUserGraph
from indoor_loc.pipeline.backend_stage import BackendParams, BackendStage
from msg_adapters.path import path_from_msg
from test_backend_stage import WKNN, _messages


def _fed_stage(n_users: int, **kw) -> BackendStage:
    """A back-end that took ``n_users`` short corridor walks (a tenth of a second apart), live
    window optimisation on, everything but the end of input done."""
    rng = np.random.default_rng(3)
    st = BackendStage(BackendParams(wknn=WKNN, **kw), survey=survey(0, 60, np.random.default_rng(1)))
    msgs = []
    for u in range(n_users):
        walk = corridor_walk(f"u{u}", 2, 14, u * SEC // 10, rng)
        msgs += [(stamp, f"u{u}", topic, msg) for stamp, topic, msg in _messages(walk)]
    msgs.sort(key=lambda m: m[0])
    for _, user, topic, msg in msgs:
        st.process(topic, msg, 0, user)
    assert sum(st.diag.rejected.values()) == 0
    return st


def _paths(outs) -> dict[str, np.ndarray]:
    return {t.split("/")[1]: path_from_msg(m)[1] for t, m in outs if t.endswith("/path")}


def test_the_final_covariances_of_all_users_take_one_factorisation(monkeypatch):
    """Every user's final pose asks for its marginal covariance: the information matrix is factorised
    once per solve, not once per user (quadratic: 507 s for 500 users)."""
    st = _fed_stage(12)
    calls = []
    real = graph_mod.splu
    monkeypatch.setattr(graph_mod, "splu", lambda *a, **k: calls.append(1) or real(*a, **k))
    outs = st.run_finish()
    assert sum(t.endswith("/pose") for t, _ in outs) >= 12
    assert len(calls) <= 2       # the last live window's (poses taken at the end), the whole graph's


def test_the_cached_covariance_is_the_inverse_information_matrix():
    """Oracle: the cached factorisation's marginals equal the factorisation made anew per pose and
    the dense inverse of JᵀJ (+ 1e-9 I)."""
    rng = np.random.default_rng(5)
    g = MultiUserGraph(GraphParams(window_poses=0), survey(0, 24, rng))
    feed(g, corridor_walk("a", 2, 22, 0, rng, scan_period_s=1.0))
    feed(g, corridor_walk("b", 22, 2, 3 * SEC, rng, scan_period_s=1.0))
    assert g.optimize() is not None
    jac, z, var, col = g._last_J
    J = jac(z).toarray()
    dense = np.linalg.inv(J.T @ J + 1e-9 * np.eye(J.shape[1]))
    for pose in var[::5]:
        c = int(col[pose])
        plain, cached = g.marginal_cov_plain(int(pose)), g.marginal_cov(int(pose))
        np.testing.assert_allclose(cached, plain, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(cached, dense[c:c + 3, c:c + 3], rtol=1e-6, atol=1e-9)
    assert g.marginal_cov(int(np.flatnonzero(g.poses.view("frozen"))[0])) is None if g.n_frozen else True
    assert sp.issparse(g._last_J[0].jac)       # the factorisation is kept with its Jacobian


def test_a_budget_that_runs_out_publishes_every_path_and_names_the_users():
    """A budget too short for any solver step: every user's path still comes out (the window-optimised
    tracks, unchanged), the notice and /diagnostics name the users whose final optimisation did not
    complete and say that their final poses were not published."""
    st = _fed_stage(8, finish_budget_s=1e-9)
    before = {u: st.graph.trajectory(u)[1][:, :2].copy() for u in st.graph.users}
    outs = st.run_finish()
    paths = _paths(outs)
    assert sorted(paths) == sorted(f"u{u}" for u in range(8))
    for u, xy in paths.items():
        np.testing.assert_allclose(xy[:len(before[u])], before[u], atol=1e-9)   # and the poses buffered till the end
    notes = st.take_notices()
    assert any("stopped at the 1e-09 s budget" in n and "did not complete: u0" in n for n in notes), notes
    diag = st.extra_diagnostics()
    assert diag["finish.incomplete_users"] == "8" and diag["finish.incomplete"].split(",")[0] == "u0"
    assert diag["finish.final_poses_not_published"] == "8"


def test_a_budget_that_suffices_changes_nothing():
    """With a budget the solve fits in, the end of input is that of no budget at all, and says nothing."""
    free, timed = _fed_stage(6, finish_budget_s=0.0), _fed_stage(6, finish_budget_s=600.0)
    a, b = _paths(free.run_finish()), _paths(timed.run_finish())
    assert a.keys() == b.keys()
    for u in a:
        np.testing.assert_array_equal(a[u], b[u])
    assert not timed.take_notices()
    assert timed.extra_diagnostics()["finish.incomplete_users"] == "0"
    assert timed.extra_diagnostics()["finish.optimisation"] == "completed"


def test_a_solve_stopped_by_its_deadline_keeps_the_best_state_it_reached():
    """The deadline stops the whole-graph solve between two evaluations; the estimates are then the
    lowest-cost point evaluated: never worse than the start, and the report says it did not complete."""
    import time
    rng = np.random.default_rng(7)
    g = MultiUserGraph(GraphParams(window_poses=0), survey(0, 60, rng))
    for k in range(6):
        feed(g, corridor_walk(f"w{k}", 2, 40, k * SEC, rng, scan_period_s=1.0))
    fun, _, z0, _, _ = g.problem(np.flatnonzero(~g.poses.view("frozen")))
    cost0 = 0.5 * float(fun(z0) @ fun(z0))
    rep = g.optimize(deadline=time.monotonic() - 1.0)
    assert rep is not None and not rep.completed and rep.cost == cost0
    assert g.solved_users() == [f"w{k}" for k in range(6)]
    full = g.optimize()
    assert full is not None and full.completed and full.cost < cost0
