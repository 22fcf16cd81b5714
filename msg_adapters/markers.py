"""Point sets and link graphs -> visualization_msgs/MarkerArray for RViz (``map/graph``,
``backend/wifi_map``; published latched).

Every array starts with a DELETEALL marker for its ``ns`` (``clear=True``) so a latched topic that
shrinks leaves no stale markers behind; :func:`marker_points` reads positions back for tests/tools.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from indoor_loc.errors import InvalidMessageError
from msg_adapters.time import as_vector, require_finite, stamp_from_ns

Color = tuple[float, float, float, float]   # r, g, b, a in [0, 1]


def _color(c: Color) -> ColorRGBA:
    v = as_vector("color", c, 4)
    if np.any((v < 0) | (v > 1)):
        raise InvalidMessageError("bad_value", f"color {tuple(v)} outside [0, 1]")
    return ColorRGBA(r=float(v[0]), g=float(v[1]), b=float(v[2]), a=float(v[3]))


def _xy(name: str, xy) -> np.ndarray:
    pts = np.asarray(xy, dtype=np.float64)
    if pts.size == 0:
        pts = pts.reshape(0, 2)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise InvalidMessageError("shape", f"{name}: expected shape (N, 2), got {pts.shape}")
    require_finite(name, pts)
    return pts


def _marker(ns: str, mid: int, mtype: int, frame_id: str, stamp_ns: int, color: Color, scale: float) -> Marker:
    m = Marker()
    m.header.frame_id = frame_id
    m.header.stamp = stamp_from_ns(stamp_ns)
    m.ns = ns
    m.id = mid
    m.type = mtype
    m.action = Marker.ADD
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = float(scale)
    m.color = _color(color)
    return m


def _delete_all(ns: str, frame_id: str, stamp_ns: int) -> Marker:
    m = Marker()
    m.header.frame_id = frame_id
    m.header.stamp = stamp_from_ns(stamp_ns)
    m.ns = ns
    m.action = Marker.DELETEALL
    return m


def points_markers(ns: str, xy, frame_id: str = "map", stamp_ns: int = 0, *, z: float = 0.0,
                   color: Color = (0.1, 0.4, 1.0, 0.9), scale: float = 0.3, per_point: bool = False,
                   texts: Sequence[str] | None = None, text_scale: float = 0.4, clear: bool = True) -> MarkerArray:
    """Points xy (N, 2) m at height ``z`` m: one SPHERE_LIST marker (id 0), or with ``per_point``
    one SPHERE marker per point (ids 0..N-1); ``texts`` (N strings) adds TEXT_VIEW_FACING labels
    in namespace ``ns + "/text"`` just above each point. ``scale`` is the sphere diameter, m."""
    pts = _xy("xy", xy)
    require_finite("z", float(z))
    out: list[Marker] = []
    if clear:
        out.append(_delete_all(ns, frame_id, stamp_ns))
    if per_point:
        for i, (x, y) in enumerate(pts.tolist()):
            m = _marker(ns, i, Marker.SPHERE, frame_id, stamp_ns, color, scale)
            m.pose.position.x, m.pose.position.y, m.pose.position.z = x, y, float(z)
            out.append(m)
    else:
        m = _marker(ns, 0, Marker.SPHERE_LIST, frame_id, stamp_ns, color, scale)
        m.points = [Point(x=x, y=y, z=float(z)) for x, y in pts.tolist()]
        out.append(m)
    if texts is not None:
        if len(texts) != len(pts):
            raise InvalidMessageError("shape", f"texts has {len(texts)} entries for {len(pts)} points")
        tns = f"{ns}/text"
        if clear:
            out.append(_delete_all(tns, frame_id, stamp_ns))
        for i, ((x, y), t) in enumerate(zip(pts.tolist(), texts)):
            m = _marker(tns, i, Marker.TEXT_VIEW_FACING, frame_id, stamp_ns, (1.0, 1.0, 1.0, 1.0), text_scale)
            m.pose.position.x, m.pose.position.y, m.pose.position.z = x, y, float(z) + scale
            m.text = str(t)
            out.append(m)
    return MarkerArray(markers=out)


def graph_markers(node_xy, link_nodes, frame_id: str = "map", stamp_ns: int = 0, *, ns: str = "graph",
                  z: float = 0.0, link_color: Color = (0.2, 0.8, 0.2, 1.0), link_width: float = 0.1,
                  node_color: Color = (0.9, 0.6, 0.1, 1.0), node_scale: float = 0.25,
                  clear: bool = True) -> MarkerArray:
    """A link graph: node_xy (M, 2) m, link_nodes (L, 2) int node indices. One LINE_LIST marker
    (ns ``ns + "/links"``, two points per link) and one SPHERE_LIST of nodes (``ns + "/nodes"``)."""
    nodes = _xy("node_xy", node_xy)
    links = np.asarray(link_nodes)
    if links.size == 0:
        links = links.reshape(0, 2).astype(np.int64)
    if links.ndim != 2 or links.shape[1] != 2 or not np.issubdtype(links.dtype, np.integer):
        raise InvalidMessageError("shape", f"link_nodes: expected int shape (L, 2), got {links.dtype} {links.shape}")
    if links.size and (links.min() < 0 or links.max() >= len(nodes)):
        raise InvalidMessageError("bad_value", f"link_nodes index outside [0, {len(nodes)})")
    out: list[Marker] = []
    lns, nns = f"{ns}/links", f"{ns}/nodes"
    if clear:
        out += [_delete_all(lns, frame_id, stamp_ns), _delete_all(nns, frame_id, stamp_ns)]
    line = _marker(lns, 0, Marker.LINE_LIST, frame_id, stamp_ns, link_color, link_width)
    seg = nodes[links.reshape(-1)]
    line.points = [Point(x=x, y=y, z=float(z)) for x, y in seg.tolist()]
    out.append(line)
    sph = _marker(nns, 0, Marker.SPHERE_LIST, frame_id, stamp_ns, node_color, node_scale)
    sph.points = [Point(x=x, y=y, z=float(z)) for x, y in nodes.tolist()]
    out.append(sph)
    return MarkerArray(markers=out)


def marker_points(marker: Marker) -> np.ndarray:
    """Positions (K, 3) m of a marker: its ``points`` (lists) or its pose position (single shapes)."""
    if marker.points:
        return np.array([[p.x, p.y, p.z] for p in marker.points], dtype=np.float64)
    p = marker.pose.position
    return np.array([[p.x, p.y, p.z]], dtype=np.float64)
