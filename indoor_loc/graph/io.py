"""Building-graph files: format ``indoor_loc.graph`` version 1 (YAML, one file).

::

    format: indoor_loc.graph
    version: 1
    frame_id: map                     # node coordinates are in this frame (ENU, metres)
    units: {position: m, length: m}
    floors:                           # optional; default one floor {id: 0, height_m: 0}
      - {id: 0, name: "ground", height_m: 0.0}
      - {id: 1, name: "first", height_m: 3.5}
    nodes:                            # [id, x, y] or [id, x, y, floor_id]; ids any ints >= 0
      - [0, 1.50, 2.00]
      - [1, 9.25, 2.00, 0]
    links:                            # undirected horizontal links: [node_id, node_id]
      - [0, 1]
    vertical_links:                   # optional: stairs / lifts between floors
      - {nodes: [7, 31], length_m: 6.0, tll_length_m: 30.0}
    rooms:                            # optional: room name -> node ids (room-level accuracy)
      "301": [4, 5, 6]
    source: {...}                     # optional free-form provenance (tool, image, scale)

Links are walkable straight segments; a link's length is the horizontal distance between its ends
(Koivisto et al.'s LENGTH). A vertical link gives its walking ``length_m`` and the longer
``tll_length_m`` the total-link-length computation uses so that stairs do not absorb probability
mass. Everything is checked on load (see :func:`indoor_loc.graph.model.build_graph`); a bad
file raises :class:`~indoor_loc.errors.MapError` naming the offending element. Files of another
``format`` or of a ``version`` this code does not know are refused.

Why YAML: a graph is small (PUTMC's floor: a few hundred links), diffable and editable by hand;
the libyaml loader reads a 10 000-link file in well under a second. The file's SHA-256 keys the
TLL cache kept beside it (:mod:`indoor_loc.graph.tll`).
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from indoor_loc.errors import MapError
from indoor_loc.graph.model import BuildingGraph, Floor, build_graph

FORMAT_NAME = "indoor_loc.graph"
FORMAT_VERSION = 1

_Loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_Dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


def graph_from_dict(doc: Mapping[str, Any], *, where: str = "graph") -> BuildingGraph:
    """Build a graph from the parsed document (see the module docstring for the schema)."""
    if not isinstance(doc, Mapping):
        raise MapError(f"{where}: expected a mapping at the top level, got {type(doc).__name__}")
    if doc.get("format") != FORMAT_NAME:
        raise MapError(f"{where}: format must be {FORMAT_NAME!r}, got {doc.get('format')!r}")
    if doc.get("version") != FORMAT_VERSION:
        raise MapError(f"{where}: version {doc.get('version')!r} is not supported (this code reads version {FORMAT_VERSION})")
    known = {"format", "version", "frame_id", "units", "floors", "nodes", "links", "vertical_links", "rooms", "source"}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise MapError(f"{where}: unknown key(s) {unknown}; expected some of {sorted(known)}")
    floors = []
    for i, f in enumerate(doc.get("floors") or []):
        if not isinstance(f, Mapping) or "id" not in f:
            raise MapError(f"{where}: floors[{i}] must be a mapping with an 'id', got {f!r}")
        try:
            floors.append(Floor(int(f["id"]), str(f.get("name", f["id"])), float(f.get("height_m", 0.0))))
        except (TypeError, ValueError) as err:
            raise MapError(f"{where}: floors[{i}] {dict(f)!r}: {err}") from err
    nodes = doc.get("nodes")
    if not isinstance(nodes, list) or not nodes:
        raise MapError(f"{where}: 'nodes' must be a non-empty list of [id, x, y(, floor)]")
    ids, xy, fl = [], [], []
    default_floor = floors[0].id if floors else 0
    for i, row in enumerate(nodes):
        if not isinstance(row, (list, tuple)) or len(row) not in (3, 4):
            raise MapError(f"{where}: nodes[{i}] must be [id, x, y] or [id, x, y, floor], got {row!r}")
        try:
            if isinstance(row[0], float) and not float(row[0]).is_integer():
                raise ValueError("node id must be an integer")
            ids.append(int(row[0]))
            xy.append((float(row[1]), float(row[2])))
            fl.append(int(row[3]) if len(row) == 4 else default_floor)
        except (TypeError, ValueError) as err:
            raise MapError(f"{where}: nodes[{i}] {row!r}: {err}") from err
    links: list[tuple[int, int]] = []
    for i, row in enumerate(doc.get("links") or []):
        if not isinstance(row, (list, tuple)) or len(row) != 2:
            raise MapError(f"{where}: links[{i}] must be [node_id, node_id], got {row!r}")
        try:
            links.append((int(row[0]), int(row[1])))
        except (TypeError, ValueError) as err:
            raise MapError(f"{where}: links[{i}] {row!r}: {err}") from err
    vertical: dict[int, tuple[float, float]] = {}
    for i, v in enumerate(doc.get("vertical_links") or []):
        if not isinstance(v, Mapping) or "nodes" not in v or "length_m" not in v:
            raise MapError(f"{where}: vertical_links[{i}] must be {{nodes: [a, b], length_m: L, tll_length_m: T}}, got {v!r}")
        try:
            a, b = (int(x) for x in v["nodes"])
            length = float(v["length_m"])
            tll = float(v.get("tll_length_m", 5.0 * length))
        except (TypeError, ValueError) as err:
            raise MapError(f"{where}: vertical_links[{i}] {v!r}: {err}") from err
        vertical[len(links)] = (length, tll)
        links.append((a, b))
    rooms = doc.get("rooms") or {}
    if not isinstance(rooms, Mapping):
        raise MapError(f"{where}: 'rooms' must map room names to node id lists")
    try:
        return build_graph(ids, np.array(xy, float), links, node_floor=fl, floors=floors or None,
                           vertical=vertical, rooms=rooms, frame_id=str(doc.get("frame_id", "map")))
    except MapError as err:
        raise MapError(f"{where}: {str(err).removeprefix('graph: ')}") from None


def graph_to_dict(g: BuildingGraph, *, source: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The document :func:`graph_from_dict` reads back (round trip exact to the float repr)."""
    ids = g.node_ids
    floor_ids = np.array([f.id for f in g.floors])[g.node_floor]
    multi = len(g.floors) > 1 or g.floors[0] != Floor(0, "0", 0.0)      # a named floor keeps its name
    nodes = [[int(i), float(x), float(y)] + ([int(f)] if multi else [])
             for i, (x, y), f in zip(ids, g.node_xyz[:, :2], floor_ids)]
    hor = [[int(ids[a]), int(ids[b])] for (a, b), v in zip(g.link_nodes, g.link_vertical) if not v]
    vert = [{"nodes": [int(ids[a]), int(ids[b])], "length_m": float(l), "tll_length_m": float(t)}
            for (a, b), v, l, t in zip(g.link_nodes, g.link_vertical, g.link_len, g.link_tll_len) if v]
    doc: dict[str, Any] = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "frame_id": g.frame_id,
                           "units": {"position": "m", "length": "m"}}
    if multi:
        doc["floors"] = [{"id": f.id, "name": f.name, "height_m": f.height_m} for f in g.floors]
    doc["nodes"] = nodes
    doc["links"] = hor
    if vert:
        doc["vertical_links"] = vert
    if g.rooms:
        doc["rooms"] = {name: [int(ids[k]) for k in members] for name, members in g.rooms.items()}
    if source:
        doc["source"] = dict(source)
    return doc


def load_graph(path: str | Path) -> BuildingGraph:
    """Read and validate a graph file (MapError with the file name on any problem)."""
    path = Path(path)
    try:
        doc = yaml.load(path.read_text(), Loader=_Loader)
    except (OSError, yaml.YAMLError) as err:
        raise MapError(f"cannot read graph file {path}: {err}") from err
    return graph_from_dict(doc, where=str(path))


def save_graph(g: BuildingGraph, path: str | Path, *, source: Mapping[str, Any] | None = None) -> Path:
    """Write ``g`` in format version 1 (flow-style rows, one node or link per line)."""
    path = Path(path)
    doc = graph_to_dict(g, source=source)
    head = {k: v for k, v in doc.items() if k not in ("nodes", "links", "vertical_links", "rooms")}
    lines = [yaml.dump(head, Dumper=_Dumper, sort_keys=False).rstrip()]
    for key in ("nodes", "links", "vertical_links"):
        if key in doc:
            lines.append(f"{key}:")
            lines += [f"  - {yaml.dump(row, Dumper=_Dumper, default_flow_style=True, width=1_000_000).strip()}"
                      for row in doc[key]]
    if "rooms" in doc:
        lines.append(yaml.dump({"rooms": doc["rooms"]}, Dumper=_Dumper, default_flow_style=None,
                               sort_keys=False).rstrip())
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def graph_digest(path: str | Path) -> str:
    """SHA-256 of a graph file's bytes (keys caches derived from it)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
