"""A building for the simulator: floors, walls, rooms, access points and the link graph (pure numpy).

Geometry is in the map frame (ENU metres, x east, y north, z up; floor ``k`` at height
``floor_z[k]``). The graph is arrays, as the rest of the package keeps it: ``node_xyz (M, 3)``,
``node_floor (M,)``, ``node_kind (M,)`` (``corridor``, ``junction``, ``door``, ``room``, ``stairs``,
``lift``: a lift car's stop on its floor, joined to the stops above and below by vertical links),
``link_nodes (L, 2)`` and ``link_len_m (L,)`` (3-D length: stairs are longer than their plan).

The shipped sample building (:func:`sample_building`, file ``indoor_loc/data/sample_building.geojson``)
is a two-storey office: a 40 m east-west corridor per floor with five rooms on each side, doors
into every room, and an east stairwell joining the floors. :func:`make_sample_building` builds it
from a handful of numbers; the GeoJSON file is what the package loads (a test keeps both equal).
:func:`make_tower_building` is the same office three storeys high with a lift at the corridor's
west end beside the east stairwell (the multi-floor development building).

GeoJSON layout (RFC 7946 structure, but coordinates are local map metres, not WGS 84 — declared in
the top-level ``"indoor_loc"`` member): one Feature per wall (LineString, ``kind: wall``), room
(Polygon, ``kind: room``), graph node (Point [x, y, z], ``kind: node``, ``node_kind``) and link
(LineString, ``kind: link``, ``nodes: [i, j]``), and access point (Point, ``kind: ap``, see
:class:`ApCluster`). Every feature carries ``floor``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from indoor_loc.errors import MapError

GEOJSON_FORMAT = "indoor_loc.building"
GEOJSON_VERSION = 1
SAMPLE_FILE = "sample_building.geojson"
NODE_KINDS = ("corridor", "junction", "door", "room", "stairs", "lift")


@dataclass(frozen=True)
class ApCluster:
    """One physical access point radiating several BSSIDs (multi-BSSID / dual band).

    ``xyz`` m; ``bssids``/``ssids``/``freq_mhz`` one entry per radiated network; ``off_at_s``:
    the AP disappears (all BSSIDs) this many seconds after the start of a run (None = never);
    ``move_at_s``/``move_to_xyz``: the AP is moved there at that time (None = never).
    """
    name: str
    xyz: tuple[float, float, float]
    floor: int
    bssids: tuple[str, ...]
    ssids: tuple[str, ...]
    freq_mhz: tuple[float, ...]
    off_at_s: float | None = None
    move_at_s: float | None = None
    move_to_xyz: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Building:
    name: str
    floor_z: np.ndarray                  # (F,) m
    walls: np.ndarray                    # (W, 2, 2) m, plan segments
    wall_floor: np.ndarray               # (W,) int
    rooms: tuple[tuple[int, str, np.ndarray], ...]   # (floor, name, polygon (K, 2))
    node_xyz: np.ndarray                 # (M, 3) m
    node_floor: np.ndarray               # (M,) int
    node_kind: tuple[str, ...]           # (M,)
    link_nodes: np.ndarray               # (L, 2) int
    aps: tuple[ApCluster, ...] = ()
    mag_disturbances: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    """(D, 7): x, y, floor, Bx, By, Bz (tesla, ENU, at the centre), radius m (Gaussian fall-off)."""

    @property
    def n_floors(self) -> int:
        return len(self.floor_z)

    @property
    def link_len_m(self) -> np.ndarray:
        a, b = self.node_xyz[self.link_nodes[:, 0]], self.node_xyz[self.link_nodes[:, 1]]
        return np.linalg.norm(b - a, axis=1)

    def extent(self, margin_m: float = 1.0) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) m of walls and nodes, widened by ``margin_m``."""
        pts = np.vstack([self.walls.reshape(-1, 2), self.node_xyz[:, :2]])
        lo, hi = pts.min(axis=0) - margin_m, pts.max(axis=0) + margin_m
        return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])

    def adjacency(self) -> csr_matrix:
        """Symmetric CSR matrix of link lengths (M, M)."""
        m = len(self.node_xyz)
        i, j = self.link_nodes[:, 0], self.link_nodes[:, 1]
        w = self.link_len_m
        return csr_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(m, m))

    def shortest_path(self, a: int, b: int) -> list[int]:
        """Node indices of a shortest path from ``a`` to ``b`` (inclusive); MapError if none."""
        _, pred = dijkstra(self.adjacency(), directed=False, indices=a, return_predecessors=True)
        if a != b and pred[b] < 0:
            raise MapError(f"no path from node {a} to node {b}")
        path = [b]
        while path[-1] != a:
            path.append(int(pred[path[-1]]))
        return path[::-1]

    def all_bssids(self) -> list[str]:
        return [b for ap in self.aps for b in ap.bssids]


#: The stairs' total-link-length weight relative to their walking length (see indoor_loc.graph.io:
#: a longer TLL length keeps stairs from absorbing probability mass in the particle filter).
STAIRS_TLL_FACTOR = 5.0


def building_graph(b: Building):
    """The building's link graph in the package's map format (:class:`indoor_loc.graph.BuildingGraph`,
    validated by :func:`indoor_loc.graph.build_graph`): node ids = indices, floors with their
    heights, stairs as vertical links, rooms -> their room nodes."""
    from indoor_loc.graph import Floor, build_graph

    floors = [Floor(i, f"floor {i}", float(z)) for i, z in enumerate(b.floor_z)]
    vertical = {}
    for k, (i, j) in enumerate(b.link_nodes.tolist()):
        if b.node_floor[i] != b.node_floor[j]:
            length = float(np.linalg.norm(b.node_xyz[j] - b.node_xyz[i]))
            vertical[k] = (length, STAIRS_TLL_FACTOR * length)
    rooms = {}
    for f, name, poly in b.rooms:
        inside = [i for i in range(len(b.node_xyz)) if b.node_floor[i] == f and b.node_kind[i] == "room"
                  and poly[:, 0].min() < b.node_xyz[i, 0] < poly[:, 0].max()
                  and poly[:, 1].min() < b.node_xyz[i, 1] < poly[:, 1].max()]
        if inside:
            rooms[name] = inside
    return build_graph(np.arange(len(b.node_xyz)), b.node_xyz[:, :2], b.link_nodes.tolist(),
                       node_floor=b.node_floor.tolist(), floors=floors, vertical=vertical, rooms=rooms)


def validate_building(b: Building) -> None:
    """Raise MapError unless the building is usable: finite geometry, valid links (no self-loops,
    no duplicates, no zero length), node floors in range, a connected graph, unique BSSIDs."""
    if b.n_floors < 1:
        raise MapError(f"building {b.name}: no floors")
    for name, arr in (("walls", b.walls), ("node_xyz", b.node_xyz)):
        if not np.all(np.isfinite(arr)):
            raise MapError(f"building {b.name}: non-finite {name}")
    m = len(b.node_xyz)
    if m < 2 or len(b.link_nodes) == 0:
        raise MapError(f"building {b.name}: a graph needs at least two nodes and one link")
    if len(b.node_kind) != m or len(b.node_floor) != m:
        raise MapError(f"building {b.name}: node_kind/node_floor have {len(b.node_kind)}/{len(b.node_floor)} "
                       f"entries for {m} nodes")
    bad_kind = sorted(set(b.node_kind) - set(NODE_KINDS))
    if bad_kind:
        raise MapError(f"building {b.name}: unknown node kinds {bad_kind}; expected {NODE_KINDS}")
    if b.node_floor.min() < 0 or b.node_floor.max() >= b.n_floors:
        raise MapError(f"building {b.name}: node floor outside [0, {b.n_floors})")
    links = b.link_nodes
    if links.min() < 0 or links.max() >= m:
        raise MapError(f"building {b.name}: link node index outside [0, {m})")
    if np.any(links[:, 0] == links[:, 1]):
        raise MapError(f"building {b.name}: self-loop link at {int(np.flatnonzero(links[:, 0] == links[:, 1])[0])}")
    key = np.sort(links, axis=1)
    if len(np.unique(key, axis=0)) != len(key):
        raise MapError(f"building {b.name}: duplicate links")
    if np.any(b.link_len_m < 1e-3):
        raise MapError(f"building {b.name}: zero-length link")
    n_comp, _ = connected_components(b.adjacency(), directed=False)
    if n_comp != 1:
        raise MapError(f"building {b.name}: the graph has {n_comp} disconnected parts")
    bss = b.all_bssids()
    if len(set(bss)) != len(bss):
        raise MapError(f"building {b.name}: duplicate BSSIDs")
    for ap in b.aps:
        if not (len(ap.bssids) == len(ap.ssids) == len(ap.freq_mhz)):
            raise MapError(f"building {b.name}: AP {ap.name}: bssids/ssids/freq_mhz lengths differ")
        if not 0 <= ap.floor < b.n_floors:
            raise MapError(f"building {b.name}: AP {ap.name} on floor {ap.floor}, outside [0, {b.n_floors})")


# ------------------------------------------------------------------------------- sample building
def _cluster(name: str, xyz, floor: int, mac_prefix: str, *, bands=("2.4", "5"), ssids=("corp", "guest"),
             channel24: int = 1, channel5: int = 36, **events) -> ApCluster:
    """A multi-BSSID AP: one BSSID per (band, SSID), MACs differing in the last byte (as vendors do)."""
    bssids, names, freqs = [], [], []
    k = 0
    for band in bands:
        f = 2407.0 + 5.0 * channel24 if band == "2.4" else 5000.0 + 5.0 * channel5
        for s in ssids:
            bssids.append(f"{mac_prefix}:{0x10 * (band == '5') + k:02x}")
            names.append(s)
            freqs.append(f)
            k += 1
    return ApCluster(name, tuple(float(v) for v in xyz), floor, tuple(bssids), tuple(names), tuple(freqs), **events)


def make_tower_building() -> Building:
    """The office three storeys high with the east stairwell and a west lift (see module doc)."""
    return make_sample_building(n_floors=3, lift=True)


def make_sample_building(*, n_floors: int = 2, lift: bool = False) -> Building:
    """The shipped two-storey office (see module doc), built from its dimensions; ``n_floors``
    storeys and a ``lift`` at the west end of the corridor for the multi-floor variant."""
    length, depth, corridor_y, half_w = 40.0, 20.0, 10.0, 1.2
    room_w, floor_h, door_w = 8.0, 3.5, 1.0
    room_xc = np.arange(room_w / 2, length, room_w)                    # 4, 12, 20, 28, 36
    ys, yn = corridor_y - half_w, corridor_y + half_w                   # corridor walls
    stair = (length, length + 4.0, 6.0, 14.0)                          # stairwell x0, x1, y0, y1
    walls, wall_floor, rooms = [], [], []
    nodes, kinds, floors, links = [], [], [], []

    def node(x, y, f, kind) -> int:
        nodes.append((x, y, f * floor_h))
        kinds.append(kind)
        floors.append(f)
        return len(nodes) - 1

    lift_x = (-3.0, 0.0)                                                # lift car x0, x1 (corridor width)
    for f in range(n_floors):
        def wall(x0, y0, x1, y1, floor=f):
            walls.append(((x0, y0), (x1, y1)))
            wall_floor.append(floor)
        # outer shell, with the opening into the stairwell at the corridor's east end
        wall(0, 0, length, 0)
        wall(0, depth, length, depth)
        if lift:                                     # the lift opens onto the corridor's west end
            wall(0, 0, 0, ys)
            wall(0, yn, 0, depth)
            wall(lift_x[0], ys, lift_x[1], ys)
            wall(lift_x[0], ys, lift_x[0], yn)
            wall(lift_x[0], yn, lift_x[1], yn)
        else:
            wall(0, 0, 0, depth)
        wall(length, 0, length, ys)
        wall(length, yn, length, depth)
        sx0, sx1, sy0, sy1 = stair
        wall(sx0, sy0, sx1, sy0)
        wall(sx1, sy0, sx1, sy1)
        wall(sx0, sy1, sx1, sy1)
        # corridor walls with a door gap in front of each room, room partitions
        for y in (ys, yn):
            x = 0.0
            for xc in room_xc:
                wall(x, y, xc - door_w / 2, y)
                x = xc + door_w / 2
            wall(x, y, length, y)
        for xw in np.arange(room_w, length, room_w):
            wall(xw, 0, xw, ys)
            wall(xw, yn, xw, depth)
        for i, xc in enumerate(room_xc):
            x0, x1 = xc - room_w / 2, xc + room_w / 2
            rooms.append((f, f"F{f}-S{i + 1}", np.array([[x0, 0], [x1, 0], [x1, ys], [x0, ys]], float)))
            rooms.append((f, f"F{f}-N{i + 1}", np.array([[x0, yn], [x1, yn], [x1, depth], [x0, depth]], float)))
        # graph: corridor centreline (junctions in front of doors), doors, rooms, stair landing
        west = node(1.0, corridor_y, f, "corridor")
        prev = west
        for xc in room_xc:
            j = node(float(xc), corridor_y, f, "junction")
            links.append((prev, j))
            prev = j
            for y_door, y_room in ((ys, ys / 2), (yn, (yn + depth) / 2)):
                d = node(float(xc), y_door, f, "door")
                r = node(float(xc), y_room, f, "room")
                links += [(j, d), (d, r)]
        east = node(length, corridor_y, f, "corridor")
        links.append((prev, east))
        landing = node(length + 1.0, sy0 + 1.0 if f % 2 == 0 else sy1 - 1.0, f, "stairs")
        links.append((east, landing))
        if lift:
            car = node(0.5 * (lift_x[0] + lift_x[1]), corridor_y, f, "lift")
            links.append((west, car))
    # each flight joins two landings (6 m of plan, 3.5 m up); the lift joins its stops
    for kind in ("stairs", "lift"):
        stops = [i for i, k in enumerate(kinds) if k == kind]
        links += list(zip(stops[:-1], stops[1:]))

    aps = (
        _cluster("F0-AP1", (4.0, 4.0, 2.5), 0, "00:1a:2b:00:00"),
        _cluster("F0-AP2", (20.0, 16.0, 2.5), 0, "00:1a:2b:00:01", channel24=6, channel5=52),
        _cluster("F0-AP3", (36.0, 4.0, 2.5), 0, "00:1a:2b:00:02", channel24=11, channel5=100,
                 off_at_s=60.0),                                     # switched off mid-run
        _cluster("F1-AP1", (12.0, 16.0, 6.0), 1, "00:1a:2b:01:00", channel24=6, channel5=149),
        _cluster("F1-AP2", (28.0, 4.0, 6.0), 1, "00:1a:2b:01:01", channel24=1, channel5=44,
                 move_at_s=45.0, move_to_xyz=(28.0, 16.0, 6.0)),    # moved to the room across the corridor
        _cluster("F1-AP3", (40.5, 10.0, 6.0), 1, "00:1a:2b:01:02", bands=("2.4",), ssids=("corp",), channel24=11),
        _cluster("printer", (16.0, 8.0, 1.0), 0, "a4:5e:60:00:00", bands=("2.4",), ssids=("DIRECT-printer",),
                 channel24=6),
    )
    if n_floors > 2:
        aps += (_cluster("F2-AP1", (8.0, 4.0, 9.5), 2, "00:1a:2b:02:00", channel24=1, channel5=36),
                _cluster("F2-AP2", (32.0, 16.0, 9.5), 2, "00:1a:2b:02:01", channel24=11, channel5=100))
    # indoor magnetic disturbances (steel: the stairwell, a server cabinet, a row of lockers, the lift)
    ut = 1e-6
    dist = np.array([[42.0, 10.0, 0, 15 * ut, -10 * ut, 8 * ut, 2.5],
                     [42.0, 10.0, 1, 15 * ut, -10 * ut, 8 * ut, 2.5],
                     [12.0, 9.0, 0, -20 * ut, 5 * ut, -10 * ut, 1.5],
                     [28.0, 11.0, 1, 8 * ut, 18 * ut, 5 * ut, 1.5]]
                    + [[42.0, 10.0, f, 15 * ut, -10 * ut, 8 * ut, 2.5] for f in range(2, n_floors)]
                    + ([[-1.5, 10.0, f, -25 * ut, 10 * ut, 20 * ut, 2.0] for f in range(n_floors)] if lift else []))
    name = "sample_office" if n_floors == 2 and not lift else f"office_{n_floors}_floors"
    return Building(name, floor_h * np.arange(n_floors), np.array(walls, float), np.array(wall_floor),
                    tuple(rooms), np.array(nodes, float), np.array(floors), tuple(kinds),
                    np.array(links, dtype=np.int64), aps, dist)


# ----------------------------------------------------------------------------------- floor plans
def floor_plan_image(b: Building, floor: int, *, resolution_m: float = 0.05, margin_m: float = 1.0,
                     wall_width_m: float = 0.15) -> tuple[np.ndarray, tuple[float, float]]:
    """Occupancy image of one floor: (H, W) uint8, walls 0 (black), free 254, row 0 at the top; and
    the map-frame position (x, y) of the image's bottom-left corner (the nav2 map_server ``origin``)."""
    from PIL import Image, ImageDraw

    if not 0 <= floor < b.n_floors:
        raise MapError(f"building {b.name}: no floor {floor} (it has {b.n_floors})")
    if not resolution_m > 0:
        raise MapError(f"floor plan resolution must be > 0 m/pixel, got {resolution_m}")
    x0, x1, y0, y1 = b.extent(margin_m)
    w, h = int(np.ceil((x1 - x0) / resolution_m)), int(np.ceil((y1 - y0) / resolution_m))
    img = Image.new("L", (w, h), 254)
    draw = ImageDraw.Draw(img)
    width = max(1, int(round(wall_width_m / resolution_m)))
    for (a, c) in b.walls[b.wall_floor == floor]:
        pts = [((p[0] - x0) / resolution_m, h - 1 - (p[1] - y0) / resolution_m) for p in (a, c)]
        draw.line(pts, fill=0, width=width)
    return np.asarray(img, dtype=np.uint8), (x0, y0)


def save_floor_plans(b: Building, directory: str | Path, *, resolution_m: float = 0.05) -> list[Path]:
    """``floor<k>.png`` + ``floor<k>.yaml`` per floor, in the nav2 map_server format (``image``,
    ``resolution``, ``origin``, ``negate``, ``occupied_thresh``, ``free_thresh``). Returns the YAML paths."""
    import yaml
    from PIL import Image

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    out = []
    for f in range(b.n_floors):
        img, (x0, y0) = floor_plan_image(b, f, resolution_m=resolution_m)
        Image.fromarray(img).save(d / f"floor{f}.png")
        meta = {"image": f"floor{f}.png", "mode": "trinary", "resolution": resolution_m,
                "origin": [round(x0, 6), round(y0, 6), 0.0], "negate": 0, "occupied_thresh": 0.65,
                "free_thresh": 0.25, "floor": f, "height_m": float(b.floor_z[f])}
        (d / f"floor{f}.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
        out.append(d / f"floor{f}.yaml")
    return out


# ------------------------------------------------------------------------------------ GeoJSON I/O
def building_to_geojson(b: Building) -> dict:
    feats: list[dict] = []

    def feat(geom_type, coords, **props):
        feats.append({"type": "Feature", "geometry": {"type": geom_type, "coordinates": coords}, "properties": props})

    for (a, c), f in zip(b.walls.tolist(), b.wall_floor.tolist()):
        feat("LineString", [a, c], kind="wall", floor=int(f))
    for f, name, poly in b.rooms:
        ring = poly.tolist() + [poly[0].tolist()]
        feat("Polygon", [ring], kind="room", floor=int(f), name=name)
    for i, (xyz, f, k) in enumerate(zip(b.node_xyz.tolist(), b.node_floor.tolist(), b.node_kind)):
        feat("Point", xyz, kind="node", id=i, floor=int(f), node_kind=k)
    for i, j in b.link_nodes.tolist():
        feat("LineString", [b.node_xyz[i].tolist(), b.node_xyz[j].tolist()], kind="link", nodes=[i, j],
             floor=int(b.node_floor[i]))
    for ap in b.aps:
        props = {"kind": "ap", "floor": ap.floor, "name": ap.name, "bssids": list(ap.bssids),
                 "ssids": list(ap.ssids), "freq_mhz": list(ap.freq_mhz)}
        if ap.off_at_s is not None:
            props["off_at_s"] = ap.off_at_s
        if ap.move_at_s is not None:
            props["move_at_s"] = ap.move_at_s
            props["move_to_xyz"] = list(ap.move_to_xyz)
        feat("Point", list(ap.xyz), **props)
    for x, y, f, bx, by, bz, r in b.mag_disturbances.tolist():
        feat("Point", [x, y], kind="mag_disturbance", floor=int(f), field_t=[bx, by, bz], radius_m=r)
    return {"type": "FeatureCollection",
            "indoor_loc": {"format": GEOJSON_FORMAT, "version": GEOJSON_VERSION, "name": b.name, "frame": "map",
                           "units": "m", "crs": "local ENU metres of the map frame (not WGS 84)",
                           "floor_z": b.floor_z.tolist()},
            "features": feats}


def save_building(b: Building, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(building_to_geojson(b), indent=None, separators=(",", ":")) + "\n")
    return path


def building_from_geojson(data: dict, where: str = "building") -> Building:
    """Parse the layout of :func:`building_to_geojson`; MapError naming what is wrong."""
    try:
        meta = data["indoor_loc"]
        if meta.get("format") != GEOJSON_FORMAT or int(meta.get("version", -1)) != GEOJSON_VERSION:
            raise MapError(f"{where}: expected format {GEOJSON_FORMAT} v{GEOJSON_VERSION}, got "
                           f"{meta.get('format')} v{meta.get('version')}")
        walls, wall_floor, rooms, nodes, links, aps, dist = [], [], [], {}, [], [], []
        for k, ft in enumerate(data["features"]):
            g, p = ft["geometry"], ft["properties"]
            kind = p["kind"]
            if kind == "wall":
                walls.append(g["coordinates"][:2])
                wall_floor.append(int(p["floor"]))
            elif kind == "room":
                rooms.append((int(p["floor"]), str(p.get("name", "")), np.array(g["coordinates"][0][:-1], float)))
            elif kind == "node":
                nodes[int(p["id"])] = (g["coordinates"], int(p["floor"]), str(p["node_kind"]))
            elif kind == "link":
                links.append(tuple(int(v) for v in p["nodes"]))
            elif kind == "ap":
                aps.append(ApCluster(str(p["name"]), tuple(float(v) for v in g["coordinates"]), int(p["floor"]),
                                     tuple(p["bssids"]), tuple(p["ssids"]), tuple(float(v) for v in p["freq_mhz"]),
                                     p.get("off_at_s"), p.get("move_at_s"),
                                     tuple(p["move_to_xyz"]) if p.get("move_to_xyz") else None))
            elif kind == "mag_disturbance":
                x, y = g["coordinates"][:2]
                dist.append([x, y, int(p["floor"]), *p["field_t"], float(p["radius_m"])])
            else:
                raise MapError(f"{where}: feature {k} has unknown kind {kind!r}")
        ids = sorted(nodes)
        if ids != list(range(len(ids))):
            raise MapError(f"{where}: node ids must be 0..{len(ids) - 1}")
        b = Building(str(meta.get("name", "")), np.array(meta["floor_z"], float), np.array(walls, float).reshape(-1, 2, 2),
                     np.array(wall_floor, dtype=np.int64), tuple(rooms),
                     np.array([nodes[i][0] for i in ids], float).reshape(-1, 3),
                     np.array([nodes[i][1] for i in ids], dtype=np.int64), tuple(nodes[i][2] for i in ids),
                     np.array(links, dtype=np.int64).reshape(-1, 2), tuple(aps),
                     np.array(dist, float).reshape(-1, 7))
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise MapError(f"{where}: not a building GeoJSON ({type(err).__name__}: {err})") from err
    validate_building(b)
    return b


def load_building(path: str | Path) -> Building:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise MapError(f"cannot read building file {path}: {err}") from err
    return building_from_geojson(data, str(path))


def sample_building_path() -> Path:
    """Path of the shipped sample building GeoJSON (package data)."""
    return Path(str(resources.files("indoor_loc") / "data" / SAMPLE_FILE))


def sample_building() -> Building:
    return load_building(sample_building_path())
