"""Floor plan bitmap -> building graph: the free space's skeleton as a link graph, or a cell grid.

Koivisto et al. 2014 (§II-A) build their link map by hand; the floor-plan-to-graph slides (cell
graph with random-walk transitions, backward-simulation smoothing) divide the walkable area into
cells, drop the cells that touch walls and connect adjacent free cells. Both are offered:

- :func:`skeleton_graph` — walls are the dark strokes (darker than mid-grey): architectural plans
  draw walls in heavy dark lines and door leaves, glazing, furniture and hatching in light ones, so
  a door drawn closed stays passable while a wall drawn with small gaps stays shut; free space is
  what lies further than a clearance (a person's half width) from any wall, inside the building's
  outline (the outside is what a flood fill from the image border reaches through outer-wall gaps
  narrower than ``2 * envelope_gap_m``); only the free-space components containing the given seed
  points (or the largest one not touching the image border) are kept; the medial axis
  (``skimage.morphology.skeletonize``) becomes the links: junction and end pixels become nodes,
  the pixel chains between them are simplified to straight links
  (``skimage.measure.approximate_polygon``, Douglas–Peucker) and spurs shorter than
  ``min_spur_m`` are pruned.
- :func:`grid_graph` — a node at the centre of every square cell of side ``cell_m`` that is free,
  links to the 8 neighbours whose straight connection stays free.

The map frame is nav2's: x right, y up, the image's bottom-left corner at ``origin`` (m), ``px_per_m``
pixels per metre; a pixel's centre is its position.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from indoor_loc import params as P
from indoor_loc.errors import MapError
from indoor_loc.graph.model import BuildingGraph, build_graph


@dataclass(frozen=True)
class PlanParams:
    """How a floor-plan bitmap is read."""
    px_per_m: float = P.field(20.0, "image scale (pixels per metre)")
    wall_threshold: int = P.field(140, "grey level (0-255) below which a pixel is a wall: dark strokes are "
                                       "walls, lighter ones (door leaves, glazing, furniture) are not")
    clearance_m: float = P.field(0.25, "free space keeps at least this distance from walls (m): half a "
                                       "person's width")
    min_spur_m: float = P.field(1.0, "dead-end links shorter than this are pruned (m)")
    simplify_m: float = P.field(0.25, "Douglas-Peucker tolerance when straightening skeleton chains (m)")
    envelope_gap_m: float = P.field(2.5, "outer-wall gaps (windows, doors) up to twice this wide are closed "
                                         "to find the building's inside (m); 0 = keep the outside")
    origin_x_m: float = P.field(0.0, "map x of the image's left edge (m)")
    origin_y_m: float = P.field(0.0, "map y of the image's bottom edge (m)")

    def validate(self) -> None:
        n = type(self).__name__
        P.require(self.px_per_m > 0, n, "px_per_m", "> 0", self.px_per_m)
        P.require(0 < self.wall_threshold < 256, n, "wall_threshold", "in (0, 256)", self.wall_threshold)
        P.require(self.clearance_m >= 0, n, "clearance_m", ">= 0", self.clearance_m)
        P.require(self.min_spur_m >= 0, n, "min_spur_m", ">= 0", self.min_spur_m)
        P.require(self.simplify_m >= 0, n, "simplify_m", ">= 0", self.simplify_m)


def read_plan(path: str | Path) -> np.ndarray:
    """Grey levels (H, W) uint8 of an image file (any format Pillow reads)."""
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("L"))
    except (OSError, UnidentifiedImageError) as err:
        raise MapError(f"cannot read floor plan {path}: {err}") from err


def px_to_map(rows: np.ndarray, cols: np.ndarray, height: int, p: PlanParams) -> np.ndarray:
    """Pixel centres -> map metres (N, 2)."""
    return np.column_stack([p.origin_x_m + (np.asarray(cols) + 0.5) / p.px_per_m,
                            p.origin_y_m + (height - np.asarray(rows) - 0.5) / p.px_per_m])


def map_to_px(xy: np.ndarray, height: int, p: PlanParams) -> tuple[np.ndarray, np.ndarray]:
    """Map metres (N, 2) -> integer pixel (rows, cols)."""
    xy = np.atleast_2d(np.asarray(xy, float))
    cols = np.floor((xy[:, 0] - p.origin_x_m) * p.px_per_m).astype(int)
    rows = np.floor(height - (xy[:, 1] - p.origin_y_m) * p.px_per_m).astype(int)
    return rows, cols


def free_space(grey: np.ndarray, p: PlanParams, seeds_xy: np.ndarray | None = None) -> np.ndarray:
    """Boolean (H, W) walkable pixels: further than ``clearance_m`` from a wall, in the components
    that contain a seed (seeds in a wall's clearance snap to the nearest free pixel within 1 m),
    or the largest component not touching the border when no seeds are given."""
    p.validate()
    wall = grey < p.wall_threshold
    if not wall.any():
        raise MapError("floor plan: no wall pixels (is wall_threshold right?)")
    free = ndimage.distance_transform_edt(~wall) > p.clearance_m * p.px_per_m
    if p.envelope_gap_m > 0:
        free &= building_envelope(wall, p.envelope_gap_m * p.px_per_m)
    labels, n = ndimage.label(free)
    if n == 0:
        raise MapError("floor plan: no free space left after the wall clearance")
    h, w = grey.shape
    if seeds_xy is not None and len(seeds_xy):
        rows, cols = map_to_px(seeds_xy, h, p)
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        if not inside.any():
            raise MapError("floor plan: no seed point lies on the image")
        # snap seeds to the nearest free pixel (a seed drawn next to a wall)
        dist, (ir, ic) = ndimage.distance_transform_edt(~free, return_indices=True)
        r, c = rows[inside], cols[inside]
        near = dist[r, c] <= p.px_per_m
        keep = np.unique(labels[ir[r[near], c[near]], ic[r[near], c[near]]])
        keep = keep[keep > 0]
        if len(keep) == 0:
            raise MapError("floor plan: every seed point is inside a wall")
    else:
        border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        sizes = np.bincount(labels.ravel())
        sizes[0] = 0
        sizes[border] = 0
        if sizes.max() == 0:
            raise MapError("floor plan: every free component touches the image border; give seed points")
        keep = np.array([int(np.argmax(sizes))])
    return np.isin(labels, keep)


def building_envelope(wall: np.ndarray, gap_px: float) -> np.ndarray:
    """Inside of the building's outline: walls closed over gaps up to ``2 * gap_px`` wide (windows,
    doors in the outer wall; closing = dilation then erosion, both from distance transforms), then
    every enclosed hole filled."""
    # pad with empty space wider than the gap: the image border is outside, not a wall, so the
    # closing cannot glue a strip between the outer wall and the border to the building
    pad = int(np.ceil(gap_px)) + 2
    padded = np.pad(wall, pad, constant_values=False)
    dilated = ndimage.distance_transform_edt(~padded) <= gap_px
    closed = ndimage.distance_transform_edt(dilated) > gap_px - 1.0
    return ndimage.binary_fill_holes(closed)[pad:-pad, pad:-pad]


def _neighbour_count(mask: np.ndarray) -> np.ndarray:
    k = np.ones((3, 3), int)
    k[1, 1] = 0
    return ndimage.convolve(mask.astype(int), k, mode="constant") * mask


def skeleton_graph(grey: np.ndarray, p: PlanParams, seeds_xy: np.ndarray | None = None) -> BuildingGraph:
    """The free space's skeleton as a building graph (see the module docstring)."""
    from skimage.measure import approximate_polygon
    from skimage.morphology import skeletonize

    free = free_space(grey, p, seeds_xy)
    skel = skeletonize(free)  # type: ignore[no-untyped-call]
    h, w = skel.shape
    nb = _neighbour_count(skel)
    node_px = skel & (nb != 2)
    # merge adjacent junction/end pixels into one node (clusters of junction pixels)
    node_lab, n_nodes = ndimage.label(node_px, structure=np.ones((3, 3)))
    chain_lab, n_chains = ndimage.label(skel & ~node_px, structure=np.ones((3, 3)))
    rr, cc = np.nonzero(skel)
    index = -np.ones((h, w), np.int64)
    index[rr, cc] = np.arange(len(rr))
    # pixel adjacency (8-neighbourhood) as a sparse graph weighted by step length
    src, dst, wt = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r2, c2 = rr + dr, cc + dc
        ok = (r2 >= 0) & (r2 < h) & (c2 >= 0) & (c2 < w)
        ok[ok] &= skel[r2[ok], c2[ok]]
        src.append(index[rr[ok], cc[ok]])
        dst.append(index[r2[ok], c2[ok]])
        wt.append(np.full(ok.sum(), np.hypot(dr, dc)))
    src_a, dst_a, wt_a = np.concatenate(src), np.concatenate(dst), np.concatenate(wt)
    npx = len(rr)
    pix_node = node_lab[rr, cc] - 1                  # node cluster of each pixel, -1 if a chain pixel
    pix_chain = chain_lab[rr, cc] - 1
    # node positions: cluster centroids
    cnt = np.bincount(pix_node[pix_node >= 0], minlength=n_nodes)
    node_r = np.bincount(pix_node[pix_node >= 0], weights=rr[pix_node >= 0], minlength=n_nodes) / np.maximum(cnt, 1)
    node_c = np.bincount(pix_node[pix_node >= 0], weights=cc[pix_node >= 0], minlength=n_nodes) / np.maximum(cnt, 1)
    # chain ends: which node clusters touch each chain
    touch: dict[int, set[int]] = {}
    both = np.concatenate([np.column_stack([src_a, dst_a]), np.column_stack([dst_a, src_a])])
    cn = both[(pix_chain[both[:, 0]] >= 0) & (pix_node[both[:, 1]] >= 0)]
    for ch, nd in zip(pix_chain[cn[:, 0]], pix_node[cn[:, 1]]):
        touch.setdefault(int(ch), set()).add(int(nd))
    # direct node-node pixel adjacency between different clusters cannot happen (they would merge)
    adj = coo_matrix((np.concatenate([wt_a, wt_a]), (np.concatenate([src_a, dst_a]), np.concatenate([dst_a, src_a]))),
                     shape=(npx, npx)).tocsr()
    pts: list[tuple[float, float]] = [(float(r), float(c)) for r, c in zip(node_r, node_c)]
    links: list[tuple[int, int]] = []
    chain_pixels = ndimage.find_objects(chain_lab)
    tol_px = p.simplify_m * p.px_per_m
    members_of = np.argsort(pix_chain, kind="stable")
    starts = np.searchsorted(pix_chain[members_of], np.arange(n_chains))
    ends = np.searchsorted(pix_chain[members_of], np.arange(n_chains), side="right")
    for ch in range(n_chains):
        ends_nodes = sorted(touch.get(ch, ()))
        if len(ends_nodes) == 0 or chain_pixels[ch] is None:
            continue                                  # an isolated loop without junctions: skipped
        members = members_of[starts[ch]:ends[ch]]
        a = ends_nodes[0]
        b = ends_nodes[1] if len(ends_nodes) > 1 else None
        # order the chain's pixels by geodesic distance from its end next to node a
        sub = adj[members][:, members]
        na = np.flatnonzero([any(pix_node[adj.indices[adj.indptr[m]:adj.indptr[m + 1]]] == a) for m in members])
        if len(na) == 0:
            continue
        d = dijkstra(sub, directed=False, indices=int(na[0]))
        order = members[np.argsort(d)]
        poly = np.column_stack([rr[order], cc[order]]).astype(float)
        rows_: list[np.ndarray] = [np.array([[node_r[a], node_c[a]]]), poly]
        if b is not None:
            rows_.append(np.array([[node_r[b], node_c[b]]]))
        poly = np.vstack(rows_)
        simp = approximate_polygon(poly, tolerance=tol_px) if len(poly) > 2 else poly  # type: ignore[no-untyped-call]
        prev = a
        for q in simp[1:-1] if b is not None else simp[1:]:
            pts.append((float(q[0]), float(q[1])))
            links.append((prev, len(pts) - 1))
            prev = len(pts) - 1
        if b is not None:
            links.append((prev, b))
    xy = px_to_map(np.array([q[0] for q in pts]), np.array([q[1] for q in pts]), h, p)
    return _tidy(xy, links, p.min_spur_m)


def _tidy(xy: np.ndarray, links: list[tuple[int, int]], min_spur_m: float) -> BuildingGraph:
    """Drop zero-length and duplicate links, prune short spurs, keep the largest component,
    renumber."""
    lk = {tuple(sorted(l)) for l in links if l[0] != l[1] and np.linalg.norm(xy[l[0]] - xy[l[1]]) > 1e-6}
    for _ in range(3):
        deg = np.zeros(len(xy), int)
        for a, b in lk:
            deg[a] += 1
            deg[b] += 1
        spurs = {l for l in lk if (deg[l[0]] == 1) != (deg[l[1]] == 1)
                 and np.linalg.norm(xy[l[0]] - xy[l[1]]) < min_spur_m}
        if not spurs:
            break
        lk -= spurs
    lk_arr = np.array(sorted(lk), np.int64).reshape(-1, 2)
    if len(lk_arr) == 0:
        raise MapError("floor plan: the skeleton has no links")
    used = np.unique(lk_arr)
    m = len(xy)
    g = coo_matrix((np.ones(len(lk_arr)), (lk_arr[:, 0], lk_arr[:, 1])), shape=(m, m))
    _, lab = connected_components(g, directed=False)
    big = np.bincount(lab[used]).argmax()
    keep_nodes = used[lab[used] == big]
    remap = -np.ones(m, np.int64)
    remap[keep_nodes] = np.arange(len(keep_nodes))
    keep_links = lk_arr[(remap[lk_arr[:, 0]] >= 0)]
    return build_graph(list(range(len(keep_nodes))), xy[keep_nodes], remap[keep_links].tolist())


def grid_graph(grey: np.ndarray, p: PlanParams, cell_m: float, seeds_xy: np.ndarray | None = None) -> BuildingGraph:
    """Cells of side ``cell_m`` whose whole square is free become nodes; 8-neighbour links whose
    straight connection stays free (the cell graph of the floor-plan slides)."""
    if not cell_m > 0:
        raise MapError(f"grid_graph: expected cell_m > 0, got {cell_m!r}")
    free = free_space(grey, p, seeds_xy)
    h, w = free.shape
    cpx = max(1, int(round(cell_m * p.px_per_m)))
    gh, gw = h // cpx, w // cpx
    cells = free[:gh * cpx, :gw * cpx].reshape(gh, cpx, gw, cpx).all(axis=(1, 3))
    idx = -np.ones((gh, gw), np.int64)
    cr, cc = np.nonzero(cells)
    idx[cr, cc] = np.arange(len(cr))
    links = []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r0, r1 = 0, gh - dr
        c0, c1 = max(0, -dc), gw - max(0, dc)

        def shifted(sr: int, sc: int, r0: int = r0, r1: int = r1, c0: int = c0, c1: int = c1) -> np.ndarray:
            return idx[r0 + sr:r1 + sr, c0 + sc:c1 + sc]
        a, b = shifted(0, 0), shifted(dr, dc)
        ok = (a >= 0) & (b >= 0)
        if dr and dc:
            # diagonal: both side cells free too, so the connection does not cut a wall corner
            ok &= (shifted(dr, 0) >= 0) & (shifted(0, dc) >= 0)
        links.append(np.column_stack([a[ok], b[ok]]))
    lk = np.concatenate(links)
    centres = px_to_map(cr * cpx + (cpx - 1) / 2.0, cc * cpx + (cpx - 1) / 2.0, h, p)
    return _tidy(centres, [tuple(l) for l in lk.tolist()], 0.0)
