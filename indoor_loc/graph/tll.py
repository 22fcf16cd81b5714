"""Link transition probabilities: total link lengths (TLL), the uniform and angle rules, learning.

Koivisto, Nurminen, Ali-Löytty, Piché, "Graph-based map matching for indoor positioning" /
"TLL particle filter" (IPIN 2014; the paper digested as the TLL filter), §II-B and Algorithm 1:
a person arriving at node ν along link λ_k heads for a destination uniformly distributed over the
link points within along-graph distance ℓ_MAX, by the shortest path, so the probability of leaving
along λ_i is proportional to TLL(λ_i, d_i), the total length of the links whose shortest path from
ν starts with λ_i (eq. 4–5). Algorithm 1's recursion counts a link fully when it lies on the
shortest-path tree; a link whose far end is reached shorter another way contributes only the part
nearer this side, ``min(½(ℓ + δ_far − ℓ_used), ℓ_MAX − ℓ_used)``, and a link crossing ℓ_MAX only
its part inside ℓ_MAX.

Here the recursion is replaced by an equivalent vectorised sum over the shortest-path tree of each
source node (scipy's Dijkstra with ``limit=ℓ_MAX``; the tree's branch of every node by pointer
doubling), in chunks of sources, so a 10 000-link graph takes seconds. One difference, by design:
where two shortest paths tie exactly, Algorithm 1 follows both and counts the subtree twice;
the tree keeps Dijkstra's one predecessor and counts it once (the tied link itself still counts
fully through the partial-length formula, whose value is then ℓ).

Transition tables are indexed by *adjacency slot* (see :class:`~indoor_loc.graph.model.BuildingGraph`):
a particle arriving at node ν over the link in slot ``s`` (a position in ``adj_link``) chooses the
``j``-th link at ν with probability ``probs[s, j]`` (``j`` < degree(ν); the rest of the row is 0).
Dead ends (degree 1) reflect: the only option is the U-turn back along the same link. Otherwise the
arriving link is excluded (the shortest path never returns along it), and probabilities are clamped
to ``[p_min, p_max]`` and renormalised so Monte Carlo can represent rare branches (§II-B end).

Comparison rules: ``uniform`` (every other link alike) and ``angle`` (Evennou & Marx 2006 as used
by Koivisto et al.: ``P ∝ 1 + cos Δθ``, Δθ the turn between arriving and leaving directions).

Learning (Dirichlet posterior, eq. 8–9): with the prior row π (the TLL probabilities), weight ``a``
and observed choice counts ``y``, ``p' = (a π + y) / (a + n)``.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from indoor_loc import params as P
from indoor_loc.errors import ConfigError, MapError
from indoor_loc.graph.model import BuildingGraph

RULES = ("tll", "uniform", "angle")
CACHE_VERSION = 1


@dataclass(frozen=True)
class TransitionParams:
    """Link-transition rule at graph nodes (Koivisto et al. 2014, §II-B)."""
    rule: str = P.field("tll", "transition rule: tll (total link lengths), uniform, or angle (1 + cos of the turn)")
    l_max_m: float = P.field(40.0, "TLL destination horizon l_MAX (m)")
    p_min: float = P.field(0.02, "smallest transition probability to a non-arriving link (keeps rare branches alive)")
    p_max: float = P.field(0.98, "largest transition probability at a node with a choice")
    u_turn_prob: float = P.field(0.0, "probability of turning back at a node that is not a dead end (0 = never, as in positioning)")

    def validate(self) -> None:
        n = type(self).__name__
        P.require(self.rule in RULES, n, "rule", f"one of {RULES}", self.rule)
        P.require(self.l_max_m > 0, n, "l_max_m", "> 0", self.l_max_m)
        P.require(0.0 <= self.p_min < 0.5, n, "p_min", "in [0, 0.5)", self.p_min)
        P.require(0.5 < self.p_max <= 1.0, n, "p_max", "in (0.5, 1]", self.p_max)
        P.require(0.0 <= self.u_turn_prob < 1.0, n, "u_turn_prob", "in [0, 1)", self.u_turn_prob)


# ----------------------------------------------------------------------------------------------
# total link lengths
# ----------------------------------------------------------------------------------------------
def _weights_csr(g: BuildingGraph) -> csr_matrix:
    ln = g.link_nodes
    w = g.link_tll_len
    return csr_matrix((np.concatenate([w, w]), (np.concatenate([ln[:, 0], ln[:, 1]]),
                                                  np.concatenate([ln[:, 1], ln[:, 0]]))),
                      shape=(g.n_nodes, g.n_nodes))


def _link_lookup(g: BuildingGraph) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """Vectorised (u, v) -> link index via sorted keys u * M + v (both orders)."""
    m = g.n_nodes
    ln = g.link_nodes.astype(np.int64)
    keys = np.concatenate([ln[:, 0] * m + ln[:, 1], ln[:, 1] * m + ln[:, 0]])
    vals = np.concatenate([np.arange(g.n_links), np.arange(g.n_links)])
    order = np.argsort(keys)
    keys, vals = keys[order], vals[order]

    def lookup(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        q = u.astype(np.int64) * m + v.astype(np.int64)
        pos = np.searchsorted(keys, q)
        assert np.all(keys[np.minimum(pos, len(keys) - 1)] == q)
        return vals[pos]
    return lookup


def total_link_lengths(g: BuildingGraph, l_max_m: float = 40.0, *, chunk: int = 256) -> np.ndarray:
    """TLL of every link from both ends, ``(L, 2)`` metres: ``tll[i, e]`` is the total length of
    link points within ``l_max_m`` of node ``link_nodes[i, e]`` whose shortest path from that node
    starts along link ``i`` (Koivisto et al. 2014, eq. 5 and Algorithm 1). Link lengths are the
    TLL lengths (vertical links carry their penalty)."""
    if not l_max_m > 0:
        raise ConfigError(f"total_link_lengths: expected l_max_m > 0, got {l_max_m!r}")
    m, nl = g.n_nodes, g.n_links
    lookup = _link_lookup(g)
    w = _weights_csr(g)
    ln = g.link_nodes
    length = g.link_tll_len
    tll = np.zeros((nl, 2))
    for s0 in range(0, m, chunk):
        src = np.arange(s0, min(m, s0 + chunk))
        ns = len(src)
        dist, pred = dijkstra(w, directed=False, indices=src, limit=l_max_m * (1 + 1e-12) + 1e-9,
                              return_predecessors=True)
        reached = np.isfinite(dist)
        # first node after the source on the tree path to every reached node: pointer doubling on
        # J[x] = pred[x], except that the source's children (and the source, unreached nodes)
        # point to themselves, so J^inf(x) is the source's child above x
        rows = np.arange(ns)[:, None]
        ident = np.broadcast_to(np.arange(m)[None, :], (ns, m))
        jump = np.where((pred >= 0) & (pred != src[:, None]), pred, ident)
        while True:
            nxt = jump[rows, jump]
            if np.array_equal(nxt, jump):
                break
            jump = nxt
        first = np.where(reached & (ident != src[:, None]), jump, -1)
        # branch link of every reached node (the link at the source its tree path starts with)
        has = first >= 0
        branch = np.full((ns, m), -1, np.int64)
        si, xi = np.nonzero(has)
        branch[si, xi] = lookup(src[si], first[si, xi])
        # contributions of every link, seen from each of its ends u (other end v)
        for e in (0, 1):
            u = ln[:, e]
            v = ln[:, 1 - e]
            du = dist[:, u]                          # (ns, L)
            dv = dist[:, v]
            ok = np.isfinite(du)
            is_tree = (pred[:, v] == u[None, :]) & ok  # link runs u -> v down the tree
            with np.errstate(invalid="ignore"):
                partial = np.minimum(0.5 * (length[None, :] + dv - du), l_max_m - du)
            partial = np.where(np.isfinite(partial), partial, l_max_m - du)
            contrib = np.where(is_tree, length[None, :], np.maximum(partial, 0.0))
            # a tree link u -> v belongs to v's branch; a non-tree link seen from u to u's branch;
            # when u is the source the link is its own branch
            owner = np.where(is_tree, branch[:, v], branch[:, u])
            at_src = u[None, :] == src[:, None]
            owner = np.where(at_src, np.arange(nl)[None, :], owner)
            use = ok & (owner >= 0) & (contrib > 0)
            si, li = np.nonzero(use)
            # credit to the TLL of the branch link, at its end touching the source
            bl = owner[si, li]
            end = (ln[bl, 1] == src[si]).astype(np.int64)
            np.add.at(tll, (bl, end), contrib[si, li])
    return tll


# ----------------------------------------------------------------------------------------------
# transition tables
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Transitions:
    """Per-arrival-slot categorical distributions over the links at the node reached.

    ``probs (2L, D_max)``: row ``s`` is for arriving over adjacency slot ``s`` (the link
    ``adj_link[s]`` reaching node ``owner[s]``); column ``j`` is the ``j``-th link at that node
    (adjacency slot ``adj_ptr[node] + j``). ``cdf`` is the row-wise cumulative sum with the last
    valid column forced to exactly 1 (round-off guard). ``rule`` names how it was built."""
    probs: np.ndarray
    cdf: np.ndarray
    rule: str

    @classmethod
    def from_probs(cls, probs: np.ndarray, rule: str) -> "Transitions":
        probs = np.asarray(probs, float)
        cdf = np.cumsum(probs, axis=1)
        # the guard: everything from the last nonzero column on is exactly 1
        last = probs.shape[1] - 1 - np.argmax((probs > 0)[:, ::-1], axis=1)
        cols = np.arange(probs.shape[1])[None, :]
        cdf = np.where(cols >= last[:, None], 1.0, cdf)
        for a in (probs, cdf):
            a.setflags(write=False)
        return cls(probs, cdf, rule)


def slot_nodes(g: BuildingGraph) -> np.ndarray:
    """(2L,) node owning each adjacency slot."""
    return np.repeat(np.arange(g.n_nodes), g.degree)


def _clamp_rows(p: np.ndarray, valid: np.ndarray, p_min: float, p_max: float) -> np.ndarray:
    """Clamp the valid entries of each row into [p_min, p_max] and renormalise (a few passes:
    renormalising can push an entry back out of the band)."""
    for _ in range(20):
        q = np.where(valid, np.clip(p, p_min, p_max), 0.0)
        q /= q.sum(axis=1, keepdims=True)
        if np.allclose(q, p, atol=1e-12):
            break
        p = q
    return q


def transition_table(g: BuildingGraph, params: TransitionParams | None = None, *,
                     tll: np.ndarray | None = None) -> Transitions:
    """Build the transition table for ``params.rule`` (``tll`` may be passed precomputed)."""
    params = params or TransitionParams()
    params.validate()
    deg = g.degree
    dmax = int(deg.max())
    nslots = len(g.adj_link)
    owner = slot_nodes(g)
    local = np.arange(nslots) - g.adj_ptr[owner]                   # arriving slot's column
    cols = np.arange(dmax)[None, :]
    valid = cols < deg[owner][:, None]                              # (2L, D) columns that exist
    cand = np.where(valid, g.adj_ptr[owner][:, None] + np.minimum(cols, deg[owner][:, None] - 1), 0)
    cand_link = g.adj_link[cand]                                    # (2L, D) link of each option
    cand_end = g.adj_end[cand]                                      # end of that link at the node
    arriving = cols == local[:, None]
    if params.rule == "tll":
        if tll is None:
            tll = total_link_lengths(g, params.l_max_m)
        score = tll[cand_link, cand_end]
    elif params.rule == "uniform":
        score = np.ones(cand_link.shape)
    else:
        # heading of leaving along each option, and of arriving (entering the node)
        heading = g.link_heading()
        leave = np.where(cand_end == 0, heading[cand_link], heading[cand_link] + np.pi)
        arr_link = g.adj_link
        arr_end = g.adj_end
        arrive = np.where(arr_end == 1, heading[arr_link], heading[arr_link] + np.pi)
        score = 1.0 + np.cos(leave - arrive[:, None])
        score = np.maximum(score, 1e-9)
    choose = valid & ~arriving
    score = np.where(choose, score, 0.0)
    dead_end = deg[owner] == 1
    total = score.sum(axis=1, keepdims=True)
    # a node whose other links have no length within l_MAX (cannot happen on a connected graph
    # with positive lengths, but guard): fall back to uniform over the other links
    empty = (total[:, 0] <= 0) & ~dead_end
    score[empty] = choose[empty].astype(float)
    total = score.sum(axis=1, keepdims=True)
    probs = np.divide(score, total, out=np.zeros_like(score), where=total > 0)
    probs = np.where(dead_end[:, None], 0.0, probs)
    multi = (~dead_end) & (choose.sum(axis=1) > 1)
    if np.any(multi):
        probs[multi] = _clamp_rows(probs[multi], choose[multi], params.p_min, params.p_max)
    if params.u_turn_prob > 0:
        probs = np.where(dead_end[:, None], probs, probs * (1.0 - params.u_turn_prob))
        probs[~dead_end, local[~dead_end]] += params.u_turn_prob
    probs[dead_end, local[dead_end]] = 1.0                          # dead end: U-turn
    return Transitions.from_probs(probs, params.rule)


def dirichlet_update(prior: np.ndarray, counts: np.ndarray, a: float) -> np.ndarray:
    """Posterior mean of link-choice probabilities (Koivisto et al. 2014, eq. 9):
    ``(a π + y) / (a + n)`` per row; ``prior`` and ``counts`` of equal shape, rows = arrivals."""
    prior = np.asarray(prior, float)
    counts = np.asarray(counts, float)
    if prior.shape != counts.shape:
        raise ConfigError(f"dirichlet_update: prior {prior.shape} and counts {counts.shape} differ")
    if not a > 0 or np.any(counts < 0):
        raise ConfigError(f"dirichlet_update: expected a > 0 and counts >= 0, got a={a!r}")
    n = counts.sum(axis=-1, keepdims=True)
    return (a * prior + counts) / (a + n)


def count_choices(g: BuildingGraph, link_sequences: list[np.ndarray]) -> np.ndarray:
    """Observed choices ``(2L, D_max)``: for every pair of consecutive distinct links (i, j) in each
    sequence that share a node, one count in row (arrival over i at that node), column of j."""
    dmax = int(g.degree.max())
    counts = np.zeros((len(g.adj_link), dmax))
    owner = slot_nodes(g)
    slot_of = {(int(owner[s]), int(g.adj_link[s])): s for s in range(len(g.adj_link))}
    for seq in link_sequences:
        seq = np.asarray(seq, np.int64)
        if len(seq) == 0:
            continue
        seq = seq[np.concatenate([[True], seq[1:] != seq[:-1]])]
        for i, j in zip(seq[:-1], seq[1:]):
            shared = set(g.link_nodes[i].tolist()) & set(g.link_nodes[j].tolist())
            if len(shared) != 1:
                continue                                            # not adjacent: skipped
            node = shared.pop()
            s_in, s_out = slot_of[(node, int(i))], slot_of[(node, int(j))]
            counts[s_in, s_out - g.adj_ptr[node]] += 1
    return counts


def learn_transitions(g: BuildingGraph, prior: Transitions, link_sequences: list[np.ndarray],
                      a: float = 10.0) -> Transitions:
    """Dirichlet update of a transition table from observed link sequences (e.g. smoothed tracks
    snapped to the graph); the dead-end U-turns stay certain."""
    counts = count_choices(g, link_sequences)
    post = dirichlet_update(prior.probs, counts, a)
    post = np.where(prior.probs > 0, post, 0.0)
    post /= post.sum(axis=1, keepdims=True)
    return Transitions.from_probs(post, f"{prior.rule}+dirichlet")


# ----------------------------------------------------------------------------------------------
# cache beside the map file
# ----------------------------------------------------------------------------------------------
def cache_path(graph_file: str | Path) -> Path:
    p = Path(graph_file)
    return p.with_name(p.name + ".tll.npz")


def _cache_key(graph_file: Path, params: TransitionParams) -> str:
    body = {"v": CACHE_VERSION, "sha": hashlib.sha256(graph_file.read_bytes()).hexdigest(),
            "rule": params.rule, "l_max_m": params.l_max_m, "p_min": params.p_min, "p_max": params.p_max,
            "u_turn_prob": params.u_turn_prob}
    return json.dumps(body, sort_keys=True)


def cached_transitions(g: BuildingGraph, graph_file: str | Path, params: TransitionParams, *,
                       write: bool = True) -> tuple[Transitions, bool]:
    """Transition table for the graph loaded from ``graph_file``, read from ``<file>.tll.npz``
    when its key (file SHA-256 + parameters) matches, else computed (and written when ``write``
    and the directory is writable). Returns (table, hit)."""
    graph_file = Path(graph_file)
    cp = cache_path(graph_file)
    key = _cache_key(graph_file, params)
    if cp.exists():
        try:
            with np.load(cp, allow_pickle=False) as z:
                if str(z["key"]) == key:
                    return Transitions.from_probs(z["probs"], params.rule), True
        except (OSError, KeyError, ValueError):
            pass                                                    # a stale or broken cache is rebuilt
    tr = transition_table(g, params)
    if write:
        try:
            tmp = cp.with_name(cp.name + ".tmp.npz")
            np.savez(tmp, key=np.array(key), probs=tr.probs)
            tmp.replace(cp)
        except OSError:
            pass                                                    # read-only map directory: no cache
    return tr, False


def check_transitions(g: BuildingGraph, tr: Transitions) -> None:
    """MapError unless ``tr`` fits ``g`` (shape) and every row is a distribution."""
    if tr.probs.shape[0] != len(g.adj_link) or tr.probs.shape[1] < int(g.degree.max()):
        raise MapError(f"transition table of shape {tr.probs.shape} does not fit a graph with "
                       f"{len(g.adj_link)} adjacency slots and max degree {int(g.degree.max())}")
    if not np.allclose(tr.probs.sum(axis=1), 1.0):
        raise MapError("transition table rows do not sum to 1")


# ----------------------------------------------------------------------------------------------
# learned tables on disk
# ----------------------------------------------------------------------------------------------
def link_sequence(g: BuildingGraph, xy: np.ndarray) -> np.ndarray:
    """Links visited by a track of positions (N, 2) on (or near) the graph: the nearest link of
    each position, consecutive repeats collapsed (what :func:`count_choices` reads)."""
    if len(xy) == 0:
        return np.zeros(0, np.int64)
    links = g.project(np.asarray(xy, float))[0].astype(np.int64)
    return links[np.concatenate([[True], links[1:] != links[:-1]])]


def save_transitions(tr: Transitions, path: str | Path, graph_file: str | Path, *, note: str = "") -> Path:
    """Write a transition table for the graph in ``graph_file`` (keyed by its SHA-256)."""
    path = Path(path)
    sha = hashlib.sha256(Path(graph_file).read_bytes()).hexdigest()
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as fh:
        np.savez(fh, probs=tr.probs, rule=np.array(tr.rule), graph_sha256=np.array(sha), note=np.array(note))
    return path


def load_transitions(path: str | Path, g: BuildingGraph, graph_file: str | Path) -> Transitions:
    """Read a table written by :func:`save_transitions`; MapError unless it was made for this very
    graph file and every row is a distribution."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            probs, rule, sha = z["probs"], str(z["rule"]), str(z["graph_sha256"])
    except (OSError, KeyError, ValueError) as err:
        raise MapError(f"cannot read transition table {path}: {err}") from err
    if sha != hashlib.sha256(Path(graph_file).read_bytes()).hexdigest():
        raise MapError(f"{path} was made for another graph than {graph_file}")
    tr = Transitions.from_probs(probs, rule)
    check_transitions(g, tr)
    return tr
