"""The building graph ("link map"): nodes, undirected links and floors, as arrays.

A person (or robot) is somewhere on a link; the graph is the motion constraint of the particle
filter (Koivisto et al., TLL particle filter, §2 "link map": nodes with 3-D positions, undirected
links whose LENGTH is the horizontal Euclidean distance, vertical links for stairs and lifts).

Arrays (all read-only after construction; M nodes, L links):

- ``node_ids (M,) int64`` — the ids used in the map file (any non-negative integers);
- ``node_xyz (M, 3) float`` — x, y in the map frame (m) and the floor height (m);
- ``node_floor (M,) int32`` — index into ``floors``;
- ``link_nodes (L, 2) int32`` — node *indices* (not ids) of each link's ends 0 and 1;
- ``link_len (L,) float`` — walking length (m): horizontal distance, or the given length of a
  vertical link;
- ``link_tll_len (L,) float`` — the length used by the total-link-length computation (vertical
  links carry a penalty so they do not absorb probability mass);
- ``link_vertical (L,) bool``;
- CSR adjacency: the links at node ``k`` are ``adj_link[adj_ptr[k]:adj_ptr[k+1]]``, the node at
  their other end ``adj_node[...]`` and the end of the link that touches ``k`` ``adj_end[...]``
  (0 or 1).

Rooms (optional) name sets of nodes, for room-level accuracy.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from indoor_loc.errors import MapError


@dataclass(frozen=True)
class Floor:
    """One floor: ``id`` (int, used by nodes), a display ``name`` and its ``height_m``."""
    id: int
    name: str
    height_m: float


@dataclass(frozen=True, eq=False)
class BuildingGraph:
    """Validated building graph; build with :func:`build_graph` (or :func:`indoor_loc.graph.load_graph`)."""
    node_ids: np.ndarray
    node_xyz: np.ndarray
    node_floor: np.ndarray
    floors: tuple[Floor, ...]
    link_nodes: np.ndarray
    link_len: np.ndarray
    link_tll_len: np.ndarray
    link_vertical: np.ndarray
    adj_ptr: np.ndarray
    adj_link: np.ndarray
    adj_node: np.ndarray
    adj_end: np.ndarray
    rooms: Mapping[str, tuple[int, ...]] = field(default_factory=dict)   # room name -> node indices
    frame_id: str = "map"

    # -- sizes and derived geometry -----------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return int(len(self.node_xyz))

    @property
    def n_links(self) -> int:
        return int(len(self.link_nodes))

    @property
    def degree(self) -> np.ndarray:
        """(M,) number of links at each node."""
        return np.diff(self.adj_ptr)

    @property
    def link_xy(self) -> np.ndarray:
        """(L, 2, 2) the link end points: ``[:, 0]`` end 0, ``[:, 1]`` end 1 (m)."""
        return self.node_xyz[self.link_nodes, :2]

    def index_of(self, node_id: int) -> int:
        """Node index of a map-file node id (MapError if unknown)."""
        hit = np.flatnonzero(self.node_ids == node_id)
        if len(hit) != 1:
            raise MapError(f"graph: no node with id {node_id}")
        return int(hit[0])

    def point_at(self, link: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(N, 2) map positions of points at fraction ``t`` in [0, 1] from end 0 along ``link``."""
        link = np.asarray(link, np.intp)
        a = self.node_xyz[self.link_nodes[link, 0], :2]
        b = self.node_xyz[self.link_nodes[link, 1], :2]
        t = np.asarray(t, float)[..., None]
        return a + t * (b - a)

    def link_heading(self) -> np.ndarray:
        """(L,) heading of each link from end 0 to end 1 (rad, ENU, 0 along +x); 0 for vertical."""
        d = self.node_xyz[self.link_nodes[:, 1], :2] - self.node_xyz[self.link_nodes[:, 0], :2]
        return np.arctan2(d[:, 1], d[:, 0])

    def project(self, xy: np.ndarray, *, floor: int | None = None,
                chunk: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest point on any link for each query point (Koivisto et al., Algorithm 3, last step:
        project on every link segment, clamp to its ends, take the nearest).

        ``xy (N, 2)`` metres. Returns ``link (N,) int32``, ``t (N,)`` in [0, 1] from end 0 and the
        distance ``(N,)`` in metres. With ``floor`` only links with an end on that floor count.
        Vectorised over points and links in chunks (memory ``chunk * L``)."""
        xy = np.atleast_2d(np.asarray(xy, float))
        n = len(xy)
        links = np.arange(self.n_links)
        if floor is not None:
            on = (self.node_floor[self.link_nodes[:, 0]] == floor) | (self.node_floor[self.link_nodes[:, 1]] == floor)
            links = links[on]
        a = self.node_xyz[self.link_nodes[links, 0], :2]
        ab = self.node_xyz[self.link_nodes[links, 1], :2] - a
        ab2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18)
        out_l = np.empty(n, np.int32)
        out_t = np.empty(n)
        out_d = np.empty(n)
        for s in range(0, n, chunk):
            p = xy[s:s + chunk]
            ap = p[:, None, :] - a[None]                                   # (n, L, 2)
            t = np.clip(np.einsum("nlk,lk->nl", ap, ab) / ab2, 0.0, 1.0)
            diff = ap - t[..., None] * ab[None]
            d2 = np.einsum("nlk,nlk->nl", diff, diff)
            j = np.argmin(d2, axis=1)
            r = np.arange(len(p))
            out_l[s:s + chunk] = links[j]
            out_t[s:s + chunk] = t[r, j]
            out_d[s:s + chunk] = np.sqrt(d2[r, j])
        return out_l, out_t, out_d


# ----------------------------------------------------------------------------------------------
def build_graph(node_ids: Sequence[int], xy: np.ndarray, links: Sequence[Sequence[int]], *,
                node_floor: Sequence[int] | None = None, floors: Sequence[Floor] | None = None,
                vertical: Mapping[int, tuple[float, float]] | None = None,
                rooms: Mapping[str, Sequence[int]] | None = None, frame_id: str = "map",
                min_link_len_m: float = 1e-6, allow_disconnected: bool = False) -> BuildingGraph:
    """Validate and build a :class:`BuildingGraph`.

    ``node_ids (M,)`` map-file ids; ``xy (M, 2)`` metres; ``links`` pairs of node *ids*;
    ``node_floor`` floor id per node (default all on floor 0); ``floors`` the floor table (default
    one floor 0 at height 0); ``vertical`` maps a link's position in ``links`` to
    ``(length_m, tll_length_m)`` for stairs/lifts; ``rooms`` room name -> node ids.

    Raises :class:`MapError` naming the offending element for: duplicate or negative node ids,
    non-finite coordinates, unknown floors, links naming unknown nodes (dangling), self-loops,
    duplicate links, horizontal links shorter than ``min_link_len_m`` (zero length), vertical links
    between nodes of one floor or with a non-positive length, nodes on no link, and a graph in
    more than one connected part (unless ``allow_disconnected``), rooms naming unknown nodes.
    """
    ids = np.asarray(node_ids, np.int64).reshape(-1)
    xy = np.asarray(xy, float)
    m = len(ids)
    if m == 0:
        raise MapError("graph: no nodes")
    if xy.shape != (m, 2):
        raise MapError(f"graph: node coordinates must have shape ({m}, 2), got {xy.shape}")
    if np.any(ids < 0):
        raise MapError(f"graph: node id {int(ids[ids < 0][0])} is negative")
    uniq, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        raise MapError(f"graph: duplicate node id {int(uniq[counts > 1][0])}")
    bad = ~np.all(np.isfinite(xy), axis=1)
    if np.any(bad):
        raise MapError(f"graph: node {int(ids[bad][0])} has a non-finite coordinate {xy[bad][0].tolist()}")
    floors = tuple(floors) if floors else (Floor(0, "0", 0.0),)
    floor_ids = [f.id for f in floors]
    if len(set(floor_ids)) != len(floor_ids):
        raise MapError(f"graph: duplicate floor id in {floor_ids}")
    for f in floors:
        if not np.isfinite(f.height_m):
            raise MapError(f"graph: floor {f.id} has a non-finite height")
    fl = np.zeros(m, np.int64) if node_floor is None else np.asarray(node_floor, np.int64).reshape(-1)
    if len(fl) != m:
        raise MapError(f"graph: {len(fl)} node floors for {m} nodes")
    fidx = {fid: i for i, fid in enumerate(floor_ids)}
    unknown = [int(ids[i]) for i in range(m) if int(fl[i]) not in fidx]
    if unknown:
        raise MapError(f"graph: node {unknown[0]} is on floor {int(fl[ids == unknown[0]][0])}, which is not in the floor table {floor_ids}")
    node_floor_idx = np.array([fidx[int(f)] for f in fl], np.int32)
    heights = np.array([f.height_m for f in floors])[node_floor_idx]
    node_xyz = np.column_stack([xy, heights])

    index = {int(i): k for k, i in enumerate(ids)}
    vertical = dict(vertical or {})
    ln = np.empty((len(links), 2), np.int32)
    seen: dict[tuple[int, int], int] = {}
    for j, pair in enumerate(links):
        if len(pair) != 2:
            raise MapError(f"graph: link #{j} must join two nodes, got {list(pair)}")
        a, b = int(pair[0]), int(pair[1])
        for end in (a, b):
            if end not in index:
                raise MapError(f"graph: link #{j} ({a}, {b}) names unknown node {end} (dangling link)")
        if a == b:
            raise MapError(f"graph: link #{j} ({a}, {b}) is a self-loop")
        key = (min(a, b), max(a, b))
        if key in seen:
            raise MapError(f"graph: link #{j} ({a}, {b}) duplicates link #{seen[key]}")
        seen[key] = j
        ln[j] = index[a], index[b]
    nl = len(ln)
    horiz = np.linalg.norm(xy[ln[:, 1]] - xy[ln[:, 0]], axis=1) if nl else np.zeros(0)
    link_len = horiz.copy()
    tll_len = horiz.copy()
    is_vert = np.zeros(nl, bool)
    for j, (length, tll) in vertical.items():
        if not 0 <= j < nl:
            raise MapError(f"graph: vertical link #{j} does not exist ({nl} links)")
        a, b = ln[j]
        if node_floor_idx[a] == node_floor_idx[b]:
            raise MapError(f"graph: vertical link #{j} ({ids[a]}, {ids[b]}) joins two nodes of one floor")
        if not (np.isfinite(length) and length > 0 and np.isfinite(tll) and tll > 0):
            raise MapError(f"graph: vertical link #{j} ({ids[a]}, {ids[b]}) needs length_m > 0 and tll_length_m > 0, got {length}, {tll}")
        is_vert[j] = True
        link_len[j] = float(length)
        tll_len[j] = float(tll)
    short = (~is_vert) & (horiz < min_link_len_m)
    if np.any(short):
        j = int(np.flatnonzero(short)[0])
        raise MapError(f"graph: link #{j} ({ids[ln[j, 0]]}, {ids[ln[j, 1]]}) has zero length ({horiz[j]:.3g} m)")
    cross = (~is_vert) & (node_floor_idx[ln[:, 0]] != node_floor_idx[ln[:, 1]]) if nl else np.zeros(0, bool)
    if np.any(cross):
        j = int(np.flatnonzero(cross)[0])
        raise MapError(f"graph: link #{j} ({ids[ln[j, 0]]}, {ids[ln[j, 1]]}) joins two floors but is not declared vertical")

    deg = np.bincount(ln.reshape(-1), minlength=m) if nl else np.zeros(m, np.int64)
    if np.any(deg == 0):
        raise MapError(f"graph: node {int(ids[np.flatnonzero(deg == 0)[0]])} is on no link (isolated node)")
    if not allow_disconnected:
        g = coo_matrix((np.ones(nl), (ln[:, 0], ln[:, 1])), shape=(m, m))
        ncomp, labels = connected_components(g, directed=False)
        if ncomp > 1:
            sizes = np.bincount(labels)
            small = int(np.argmin(sizes))
            example = int(ids[np.flatnonzero(labels == small)[0]])
            raise MapError(f"graph: {ncomp} disconnected parts; the smallest ({sizes[small]} nodes) contains node {example}")

    # CSR adjacency: for each node, its links sorted by link index
    ends = np.concatenate([ln[:, 0], ln[:, 1]])
    lk = np.concatenate([np.arange(nl), np.arange(nl)]).astype(np.int32)
    end_of = np.concatenate([np.zeros(nl, np.int8), np.ones(nl, np.int8)])
    other = np.concatenate([ln[:, 1], ln[:, 0]]).astype(np.int32)
    order = np.lexsort((lk, ends))
    adj_ptr = np.zeros(m + 1, np.int64)
    np.cumsum(deg, out=adj_ptr[1:])

    room_idx: dict[str, tuple[int, ...]] = {}
    for name, members in (rooms or {}).items():
        idx = []
        for nid in members:
            if int(nid) not in index:
                raise MapError(f"graph: room {name!r} names unknown node {nid}")
            idx.append(index[int(nid)])
        room_idx[str(name)] = tuple(idx)

    arrays = dict(node_ids=ids, node_xyz=node_xyz, node_floor=node_floor_idx, link_nodes=ln,
                  link_len=link_len, link_tll_len=tll_len, link_vertical=is_vert, adj_ptr=adj_ptr,
                  adj_link=lk[order], adj_node=other[order], adj_end=end_of[order])
    for arr in arrays.values():
        arr.setflags(write=False)
    return BuildingGraph(floors=floors, rooms=room_idx, frame_id=frame_id, **arrays)
